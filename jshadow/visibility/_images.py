"""Visibility of single rays from the BSV's occlusion images (sharp shadows of small lights).

The base sphere visibility is, before its projection to SH, a binary image per shell point: the
edge-scan's gnomonic cone of ``N_y × N_x`` pixels (:func:`jshadow.visibility.edgescan_occlusion`),
True where the ray from the shell point ``p_ij`` through the pixel hits the mesh. Together they
sample the occluder's 4D visibility field (Zhou et al. 2005, "Precomputed shadow fields", Sec. 4:
the occluder's visibility as a function of position and direction, of which the BSV's SH keep only
the low frequencies). A ray from a receiver x outside the shell either misses the bounding sphere
(it is free) or enters the shell at a point p; beyond p it *is* the ray (p, ω), so its visibility
is the shell's visibility at p in direction ω — no extrapolation model is involved.

:func:`image_ray_visibility` looks a ray up in the images of the four grid points around p, with
bilinear weights in the grid coordinates (θ, φ) of p. At a grid point p_ij the looked-up direction
is the one toward ``q``, the point of the ray closest to the occluder's centre (a *focal point*):
an occluder feature at q's depth then lies in the same place in all four images, and the parallax
of the others grows with their distance from that depth. Each image is read at its nearest pixel.
The result is a visibility in [0, 1] (a blend of four binary lookups).

Derivatives. With boolean images a lookup is piecewise constant in the geometry (no derivative).
With *coverage* images — the same 0/1 values as floats, from
:func:`jshadow.visibility.bsv_and_coverage_edgescan_diff` or any float array — each read is taken
as a point sample of the pixel's box-filtered coverage, and differentiated as such: the pixel's
own change (the silhouette's boundary integral over the pixel, when the vertices move) plus the
read point's motion across the image times the image's slope there (central differences of the
neighbouring pixels; :func:`_read`). The cut at the bounding sphere (rays whose line misses it are
free) gets the same treatment, its jump spread over one pixel's width at the cone's edge. The
tangent of all of it is written out (:func:`_fan_lookup`; where only the images, centre or
radius move, :func:`_placement_tangent` forms it as a linear map with precomputed coefficients);
it equals JAX's derivative of the same lookups read through :func:`_read` and is formed several
times faster (BENCHMARKS.md, "Where the lookups' derivative goes" and "Coverage images"). Summed
over many rays (a light's cap, many receivers) this is the derivative of the shadow; per ray it is
rough. Measured (``tests/test_image_lookup_grad.py``): a mesh sphere's gradients with respect to
the light's centre, its own centre and radius 1.7 %, 8 % and 4.6 % from the closed-form lens's at
24² receivers; a taper's 5.4 % from exact ray-cast differences (``experiments/image_grad.py``:
0.6–19 % on the shipped deforming configs).

Images with ``reads = "bilinear"`` (:func:`jshadow.visibility.scan_coverage`'s coverage along the
scan lines) are read bilinearly between pixel centres instead: continuous lookups whose derivative
is JAX's own, exact for what they compute (BENCHMARKS.md "Coverage images").

Accuracy (``experiments/light_field.py``, BENCHMARKS.md "Sharp sphere-light shadows"): the
visible fraction of a sphere light from 4 × 8 cap directions looked up this way brings the mesh
scenes with sphere lights to about 1 % relative RMSE of irradiance or less, where the n-band
product gives 2.5–9 % (and exact n-band visibility is no better than 2.5–8.8 %).

Limitations: receivers outside the shell (R = shell · r) only — a ray from inside it (an
occluder's own vertex, a receiver in contact) is looked up as if it entered at its own position,
which is not exact; closed meshes and shell > 1 (the edge-scan's domain); the images are
``T·P·N_y·N_x`` booleans per occluder (12 × 20 × 32² = 246k).
"""

from __future__ import annotations

import math
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._numerics import safe_atan2, safe_div, safe_sqrt
from ..geometry import bounding_sphere
from ._bsv import BSV
from ._edgescan import always, bsv_and_occlusion_edgescan, edgescan_occlusion, staged
from ._frames import bsv_grid_angles
from ._lamps import LampImages

__all__ = [
    "OcclusionImages",
    "occlusion_images",
    "bsv_with_occlusion_images",
    "image_ray_visibility",
    "image_fan_visibility",
    "image_fan_visibility_components",
    "image_reach",
]


class OcclusionImages(eqx.Module):
    """The BSV's binary images of one occluder (see the module docstring).

    Attributes:
        occluded: (T, P, N_y, N_x) bool, True where the ray from the shell point (θ_i, φ_j)
            through pixel (y, x) of its gnomonic cone hits the mesh (:func:`edgescan_occlusion`);
            or the same as 0.0 / 1.0 floats carrying the coverage derivative
            (:func:`jshadow.visibility.bsv_and_coverage_edgescan_diff`), which lookups then
            differentiate (:func:`_read`).
        center: (3,) bounding-sphere centre c (world units).
        radius: () bounding-sphere radius r.
        shell: the shell radius over r (static; the cone's half-angle is asin(1/shell)).
        reads: how lookups read the images (static): "nearest" pixel (the 0/1 samples) or
            "bilinear" between pixel centres (continuous images such as
            :func:`jshadow.visibility.scan_coverage`'s; their derivative is then JAX's own).
        lamps: None, or the occluder's orthographic images along the environment lights'
            directions (:class:`jshadow.visibility.LampImages`, ``method.lamp_images``), which
            :func:`jshadow.scene.environment_visible_fraction` then reads for those lights.
    """

    occluded: Bool[Array, "T P Ny Nx"] | Float[Array, "T P Ny Nx"]
    center: Float[Array, "3"]
    radius: Float[Array, ""]
    shell: float = eqx.field(static=True)
    reads: str = eqx.field(static=True, default="nearest")
    lamps: LampImages | None = None

    def __check_init__(self):
        if self.reads not in ("nearest", "bilinear"):
            raise ValueError(f"reads must be 'nearest' or 'bilinear', got {self.reads!r}")


def occlusion_images(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    grid: tuple[int, int] = (12, 20),
    directions: tuple[int, int] = (32, 32),
    shell: float = 1.5,
) -> OcclusionImages:
    """The occlusion images of a closed mesh on the BSV's shell (the edge-scan's, before SH).

    Same grid, directions and shell as :func:`jshadow.visibility.bsv_mesh_edgescan`, and the same
    cost (a few ms for the bunny). Raises like it for open meshes or ``shell <= 1``.
    """
    v = jnp.asarray(vertices)
    occ, _ = edgescan_occlusion(v, faces, tuple(grid), tuple(directions), shell)
    c, r = bounding_sphere(v)
    return OcclusionImages(occluded=occ, center=c, radius=r, shell=float(shell))


def bsv_with_occlusion_images(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    n: int = 4,
    grid: tuple[int, int] = (12, 20),
    directions: tuple[int, int] = (32, 32),
    shell: float = 1.5,
) -> tuple[BSV, OcclusionImages]:
    """The edge-scan BSV (n bands) and the occlusion images of one pose from a single edge-scan
    (:func:`jshadow.visibility.bsv_and_occlusion_edgescan`); concrete vertices only."""
    bsv, occ = bsv_and_occlusion_edgescan(vertices, faces, n, tuple(grid), tuple(directions), shell)
    return bsv, OcclusionImages(occluded=occ, center=bsv.center, radius=bsv.radius, shell=float(shell))


def image_reach(images: OcclusionImages) -> Float[Array, ""]:
    """The distance from ``images.center`` beyond which a ray is free: a lookup of a ray whose
    line passes farther from the centre is 1, with zero derivative. The bounding radius r plus the
    width of the cut's derivative ramp (:func:`image_fan_visibility_components`; it reaches half a
    width beyond r, twice that is kept as margin)."""
    return images.radius * (1.0 + 2.0 * _ramp_width(images.shell, images.occluded.shape[-1]))


def _ramp_width(shell: float, nx: int) -> float:
    """The width Δρ / r of the cut's derivative ramp: one pixel at the cone's edge (x = ρ/√(R² − ρ²)
    seen from the entry point, dx/dρ = shell²/(r (shell² − 1)^{3/2}) at ρ = r)."""
    return 2.0 * (shell**2 - 1.0) / (nx * shell**2)


@jax.jit
def image_ray_visibility(
    images: OcclusionImages,
    origins: Float[ArrayLike, "... 3"],
    dirs: Float[ArrayLike, "... 3"],
) -> Float[Array, "..."]:
    """Visibility in [0, 1] of the rays ``origins + t·dirs`` (t > 0, unit dirs) past one occluder.

    1 for a ray whose line misses the bounding sphere or that points away from it; otherwise the
    bilinear blend of the four grid images around its entry point, each read at the focal
    direction (module docstring). Batches over the broadcast leading axes of origins and dirs.
    """
    o, d = jnp.broadcast_arrays(jnp.asarray(origins), jnp.asarray(dirs))
    shape = o.shape[:-1]
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    # each ray its own fan of one, about itself: its own four grid points
    comps = tuple(d[:, c : c + 1] for c in range(3))
    return image_fan_visibility_components(images, o, comps, d).reshape(shape)


@jax.jit
def image_fan_visibility(
    images: OcclusionImages,
    origins: Float[ArrayLike, "N 3"],
    dirs: Float[ArrayLike, "N K 3"],
    axis: Float[ArrayLike, "N 3"],
) -> Float[Array, "N K"]:
    """:func:`image_ray_visibility` of fans of K rays sharing an origin, the four grid points
    chosen once per fan: around the shell entry of the unit ``axis`` ray (for a light, the
    direction to its centre; for an axis that misses the shell, around the direction of its
    closest approach). Each ray is still looked up toward its own focal point and tested against
    the bounding sphere, so only the grid points and their bilinear weights are shared. For the
    small caps of lights the difference from :func:`image_ray_visibility` (a fan of one ray each)
    is small (``tests/test_light_images.py`` bounds it on a convex mesh), and the work per
    (ray, grid point) is a 3 × 3 frame product, two divisions and one gather: no trigonometry or
    table gathers per ray. The renderer uses this (``jshadow.scene.light_visible_fractions``).
    """
    d = jnp.asarray(dirs)
    return image_fan_visibility_components(images, origins, (d[..., 0], d[..., 1], d[..., 2]), axis)


@jax.jit
def image_fan_visibility_components(
    images: OcclusionImages,
    origins: Float[ArrayLike, "N 3"],
    dirs: tuple[Float[ArrayLike, "N K"], Float[ArrayLike, "N K"], Float[ArrayLike, "N K"]],
    axis: Float[ArrayLike, "N 3"],
) -> Float[Array, "N K"]:
    """:func:`image_fan_visibility` with ``dirs`` as three (N, K) arrays of x, y, z components (or
    arrays that broadcast to (N, K), such as (1, K) directions shared by every origin)."""
    origins, axis = jnp.asarray(origins), jnp.asarray(axis)
    dtype = jnp.result_type(origins, dirs[0], images.center)
    dx, dy, dz = (jnp.asarray(x).astype(dtype) for x in dirs)
    args = (
        images.occluded,
        images.center.astype(dtype),
        images.radius.astype(dtype),
        origins.astype(dtype),
        dx,
        dy,
        dz,
        axis.astype(dtype),
    )
    if jnp.issubdtype(images.occluded.dtype, jnp.bool_):
        return _fan_lookup(images.shell, *args)[0]
    return _coverage_lookup(images.shell, images.reads == "bilinear", *args)


def _fan_lookup(
    shell, occluded, center, radius, origins, dx, dy, dz, axis, tangents=None, reference=False, bilinear=False
):
    """The lookups of :func:`image_fan_visibility_components` (inputs in one dtype): ``(value,
    tangent)``, the tangent None unless ``tangents`` (one per input after ``shell``, None where
    zero) are given, then the derivative of the coverage images' lookups (module docstring) written
    out: the read points' motion (through the focal point q, each grid point's frame coordinates and
    the pixel coordinates) times the images' central-difference slopes, the pixels' own change, the
    bilinear weights' motion (through the shell entry of the axis) and the cut's ramp. With
    ``reference``, coverage is read through :func:`_read` instead and JAX's own derivative of the
    whole lookup applies: the same derivative (``tests/test_image_lookup_grad.py`` checks every
    input in float64), formed 2.6× slower (BENCHMARKS.md "Where the lookups' derivative goes").
    With ``bilinear`` (float images) each image is read bilinearly between its pixel centres
    (:func:`_bilinear`) instead, and the tangent is that of the bilinear reads (exact; no ramp at the
    cut, which the forward pass does not have either).
    """
    live = tangents is not None
    d_occ, d_c, d_r, d_o, d_dx, d_dy, d_dz, d_ax = tangents if live else (None,) * 8
    dtype = origins.dtype
    t_n, p_n, ny, nx = occluded.shape
    flat = occluded.reshape(-1)
    coverage = not jnp.issubdtype(flat.dtype, jnp.bool_)
    r = radius
    big_r = shell * r
    tan_a = math.tan(math.asin(1.0 / shell))
    rel = origins - center
    rx, ry, rz = rel[:, 0], rel[:, 1], rel[:, 2]
    rr = rx * rx + ry * ry + rz * rz

    def grid(rel, axis, big_r):
        return _axis_grid(rel, axis, big_r, t_n, p_n)

    d_rel = _lin_sum(d_o, None if d_c is None else -d_c)
    d_rel = None if d_rel is None else jnp.broadcast_to(d_rel, rel.shape)  # a centre's tangent alone is (3,)
    d_big_r = None if d_r is None else shell * d_r
    values, moves = (rel, axis, big_r), (d_rel, d_ax, d_big_r)
    moving = [i for i, t in enumerate(moves) if t is not None]

    def grid_of(*xs):  # of the moving inputs, the others held
        args = list(values)
        for i, x in zip(moving, xs, strict=True):
            args[i] = x
        return grid(*args)

    if moving:  # the per-origin part by JAX's JVP (N values, cheap), the rest written out below
        (gi, gj), (d_gi, d_gj) = jax.jvp(
            grid_of, tuple(values[i] for i in moving), tuple(moves[i] for i in moving)
        )
    else:
        gi, gj = grid(rel, axis, big_r)
        d_gi = d_gj = None
    cell, angles, b, meets, (qx, qy, qz) = _rays(gi, gj, rel, rr, r, dx, dy, dz, t_n, p_n, dtype)
    # the focal point's tangent: dq = drel − db·d − b·dd with db = drel·d + rel·dd
    d_b = _lin_sum(
        None if d_rel is None else d_rel[:, 0:1] * dx + d_rel[:, 1:2] * dy + d_rel[:, 2:3] * dz,
        *(None if t is None else x[:, None] * t for x, t in ((rx, d_dx), (ry, d_dy), (rz, d_dz))),
    )
    d_q = [
        _lin_sum(
            None if d_rel is None else d_rel[:, i : i + 1],
            None if d_b is None else -d_b * di,
            None if ddi is None else -b * ddi,
        )
        for i, (di, ddi) in enumerate(((dx, d_dx), (dy, d_dy), (dz, d_dz)))
    ]
    if coverage and live:
        _, *slopes = _padded_tables(flat, ny, nx)
    vis = jnp.zeros(b.shape, dtype)
    d_vis = None
    for di, dj, wi, wj, st, ct, sp, cp, k in _corners(cell, angles, t_n, p_n):
        d_wi = None if d_gi is None else (d_gi if di else -d_gi)
        d_wj = None if d_gj is None else (d_gj if dj else -d_gj)
        xl, yl, zl = _grid_point_coordinates(qx, qy, qz, ct, st, cp, sp, big_r)
        front = zl > 0
        inv = safe_div(1.0, zl)
        x, y = xl * inv, yl * inv
        u = (x + tan_a) * (nx / (2.0 * tan_a))  # continuous pixel coordinates
        v = (y + tan_a) * (ny / (2.0 * tan_a))
        if bilinear:
            read, (ax, ay), corners = _bilinear(flat, k, u, v, ny, nx)
            hit = read * front.astype(flat.dtype)
        elif coverage and reference:
            hit = _read(flat, k, u, v, ny, nx) * front.astype(flat.dtype)
        else:
            px, py = jnp.floor(u), jnp.floor(v)
            hit = _gather(flat, k, px, py, ny, nx)
            hit = hit & front if hit.dtype == jnp.bool_ else hit * front.astype(hit.dtype)
        w = (wi * wj)[:, None]
        vis = vis + w * (1.0 - hit.astype(dtype))
        if not live:
            continue
        # tangent: the pixel coordinates (through q and R), the pixels' own change, the weights
        dqx, dqy, dqz = d_q
        d_h = _lin_sum(None if dqx is None else dqx * cp, None if dqy is None else dqy * sp)
        d_xl = _lin_sum(None if d_h is None else d_h * ct, None if dqz is None else -dqz * st)
        d_yl = _lin_sum(None if dqx is None else dqx * sp, None if dqy is None else -dqy * cp)
        d_zl = _lin_sum(d_big_r, None if d_h is None else -d_h * st, None if dqz is None else -dqz * ct)
        d_x = _lin_sum(d_xl, None if d_zl is None else -x * d_zl)
        d_y = _lin_sum(d_yl, None if d_zl is None else -y * d_zl)
        terms = []
        if bilinear:  # the bilinear read's own derivative, and the pixels' change read alike
            c00, c10, c01, c11 = corners
            if d_x is not None:
                slope = (1.0 - ay) * (c10 - c00) + ay * (c11 - c01)
                terms.append(slope * (d_x * inv) * (nx / (2.0 * tan_a)))
            if d_y is not None:
                slope = (1.0 - ax) * (c01 - c00) + ax * (c11 - c10)
                terms.append(slope * (d_y * inv) * (ny / (2.0 * tan_a)))
            if d_occ is not None:
                terms.append(_bilinear(d_occ.reshape(-1), k, u, v, ny, nx)[0].astype(dtype))
        elif d_x is not None or d_y is not None:
            near, idx = _padded_index(k, px, py, ny, nx)
            for d_xy, table, scale in ((d_x, slopes[0], nx), (d_y, slopes[1], ny)):
                if d_xy is not None:
                    slope = jnp.where(near, table[idx], 0.0).astype(dtype)
                    terms.append(slope * (d_xy * inv) * (scale / (2.0 * tan_a)))
        if d_occ is not None and not bilinear:
            terms.append(_gather(d_occ.reshape(-1), k, px, py, ny, nx).astype(dtype))
        d_hit = None if not terms else _lin_sum(*terms) * front.astype(dtype)
        d_w = _lin_sum(None if d_wi is None else d_wi * wj, None if d_wj is None else wi * d_wj)
        d_vis = _lin_sum(
            d_vis,
            None if d_w is None else d_w[:, None] * (1.0 - hit.astype(dtype)),
            None if d_hit is None else -w * d_hit,
        )
    out = jnp.where(meets, vis, 1.0)
    if not coverage or reference:
        if coverage:  # the cut's ramp, for JAX's derivative (value-neutral), as written out below
            rho = safe_sqrt(rr[:, None] - b * b)
            width = r * _ramp_width(shell, nx)
            ramp = jnp.clip((r - rho) / width + 0.5, 0.0, 1.0)
            ramp = jnp.where(b < 0, ramp - lax.stop_gradient(ramp), 0.0)
            out = out - lax.stop_gradient(1.0 - vis) * ramp
        return out, None
    if not live:
        return out, None
    d_out = jnp.zeros(b.shape, dtype) if d_vis is None else jnp.where(meets, d_vis, 0.0)
    # The cut at the bounding sphere (rays whose line misses it are free) is a jump of 1 − vis
    # where the line's distance ρ from c crosses r, which a sphere-like mesh's silhouette nearly
    # meets. Its derivative, as the images' own: spread over the width Δρ of one pixel at the cone's
    # edge (:func:`_ramp_width`), with no change of value: −(1 − vis) d/dt clip((r − ρ)/Δρ + ½, 0, 1).
    rho = safe_sqrt(rr[:, None] - b * b)
    width = r * _ramp_width(shell, nx)
    arg = (r - rho) / width + 0.5
    ramping = (arg > 0.0) & (arg < 1.0) & (b < 0)
    d_rr = None if d_rel is None else 2.0 * (rx * d_rel[:, 0] + ry * d_rel[:, 1] + rz * d_rel[:, 2])
    d_rho2 = _lin_sum(None if d_rr is None else d_rr[:, None], None if d_b is None else -2.0 * b * d_b)
    d_rho = None if d_rho2 is None else safe_div(d_rho2, 2.0 * rho)
    d_arg = _lin_sum(
        None if d_r is None else d_r * (1.0 - (r - rho) / r) / width,
        None if d_rho is None else -d_rho / width,
    )
    if d_arg is not None and not bilinear:  # bilinear reads: the exact derivative, the cut has none
        d_out = d_out - jnp.where(ramping, (1.0 - vis) * d_arg, 0.0)
    return out, d_out


def _rays(gi, gj, rel, rr, radius, dx, dy, dz, t_n: int, p_n: int, dtype):
    """What every lookup of a fan needs once per ray: the cell ``(i0, j0, fi, fj)`` of the grid
    coordinates (N,), the grid's angles ``(sin θ, cos θ, sin φ, cos φ)``, ``b = rel·d`` (N, K),
    whether the ray's line meets the bounding sphere ahead (N, K), and the focal point q = rel − b·d
    (three (N, K)), the ray's point nearest the centre."""
    i0, j0 = jnp.floor(gi), jnp.floor(gj)
    fi, fj = gi - i0, gj - j0
    i0, j0 = i0.astype(jnp.int32), j0.astype(jnp.int32)
    th, ph = bsv_grid_angles(t_n, p_n, dtype)
    angles = (jnp.sin(th), jnp.cos(th), jnp.sin(ph), jnp.cos(ph))
    rx, ry, rz = rel[:, 0], rel[:, 1], rel[:, 2]
    b = rx[:, None] * dx + ry[:, None] * dy + rz[:, None] * dz
    meets = (b * b - (rr[:, None] - radius * radius) > 0) & (b < 0)
    q = (rx[:, None] - b * dx, ry[:, None] - b * dy, rz[:, None] - b * dz)
    return (i0, j0, fi, fj), angles, b, meets, q


def _corners(cell, angles, t_n: int, p_n: int):
    """The four grid points around each fan's entry (:func:`_rays`' cell): per point ``(di, dj, wi,
    wj, st, ct, sp, cp, k)``, its offsets in the cell, bilinear weights (N,), sines and cosines of
    its angles and its image index (N, 1)."""
    i0, j0, fi, fj = cell
    sin_t, cos_t, sin_p, cos_p = angles
    for di in (0, 1):
        ii = jnp.clip(i0 + di, 0, t_n - 1)
        wi = fi if di else 1.0 - fi
        st, ct = sin_t[ii][:, None], cos_t[ii][:, None]
        for dj in (0, 1):
            jj = jnp.mod(j0 + dj, p_n)
            wj = fj if dj else 1.0 - fj
            sp, cp = sin_p[jj][:, None], cos_p[jj][:, None]
            yield di, dj, wi, wj, st, ct, sp, cp, (ii * p_n + jj)[:, None]


def _axis_grid(rel, axis, big_r, t_n: int, p_n: int):
    """Continuous grid coordinates (gi, gj) (N,) of the shell entry of each origin's axis (origins
    relative to the centre, ``rel`` (N, 3); unit ``axis`` (N, 3); shell radius ``big_r``)."""
    rx, ry, rz = rel[:, 0], rel[:, 1], rel[:, 2]
    ax, ay, az = axis[:, 0], axis[:, 1], axis[:, 2]
    b0 = rx * ax + ry * ay + rz * az
    rr = rx * rx + ry * ry + rz * rz
    t0 = -b0 - safe_sqrt(b0 * b0 - (rr - big_r * big_r))
    # an axis that misses the shell: its point nearest c (t0 = −b0), whose direction is used
    ex, ey, ez = rx + t0 * ax, ry + t0 * ay, rz + t0 * az
    u_z = jnp.clip(safe_div(ez, safe_sqrt(ex * ex + ey * ey + ez * ez)), -1.0, 1.0)
    theta = safe_atan2(safe_sqrt(1.0 - u_z * u_z), u_z)
    phi = safe_atan2(ey, ex)
    return theta * (t_n / math.pi) - 0.5, phi * (p_n / (2.0 * math.pi))


def _grid_point_coordinates(qx, qy, qz, ct, st, cp, sp, big_r):
    """Local coordinates ``(x_l, y_l, z_l)`` of the focal point q relative to the grid point R·u at
    polar angle θ, azimuth φ (their sines and cosines): the frame of :func:`bsv_frames`, x = (ct cp,
    ct sp, −st), y = (sp, −cp, 0), z = −u, applied to q − R·u (frameᵀ u = (0, 0, −1))."""
    h = qx * cp + qy * sp
    return h * ct - qz * st, qx * sp - qy * cp, big_r - (h * st + qz * ct)


def _lin_sum(*terms):
    """The sum of the terms that are not None (None if all are): tangents with symbolic zeros."""
    terms = [t for t in terms if t is not None]
    if not terms:
        return None
    out = terms[0]
    for t in terms[1:]:
        out = out + t
    return out


@partial(jax.custom_jvp, nondiff_argnums=(0, 1))
def _coverage_lookup(shell, bilinear, occluded, center, radius, origins, dx, dy, dz, axis):
    """:func:`_fan_lookup`'s value for float images (read at the nearest pixel, or ``bilinear``),
    with its written-out tangent."""
    return _fan_lookup(shell, occluded, center, radius, origins, dx, dy, dz, axis, bilinear=bilinear)[0]


def _coverage_lookup_jvp(shell, bilinear, primals, tangents):
    """The value and the written-out tangent. Where only the images, the centre or the radius move
    (a mesh's vertices and its placement), the tangent is a linear map with coefficients formed
    from the primals (:func:`_placement_tangent`), which reverse mode transposes to a few reductions
    and scatters; the frames' value_and_grad through the images 0.47–0.73× the time of the tangent
    written out in a ``lax.cond`` branch before it (BENCHMARKS.md, "Coverage images"). Where the
    rays' own inputs move (origins, directions, axes: a light's position), the written-out tangent
    of :func:`_fan_lookup` in the same program as the value. With ``bilinear`` the tangent is the
    bilinear reads' exact one (equal to JAX's derivative of them, a test checks)."""
    out = _fan_lookup(shell, *primals, bilinear=bilinear)[0]
    live = tuple(not isinstance(t, SymbolicZero) for t in tangents)
    if not any(live):
        return out, jnp.zeros_like(out)
    given = tuple(t.astype(p.dtype) if i else t for t, p, i in zip(tangents, primals, live, strict=True) if i)

    def tangent(primals, given):
        it = iter(given)
        full = tuple(next(it) if i else None for i in live)
        return _fan_lookup(shell, *primals, tangents=full, bilinear=bilinear)[1]

    if any(live[3:]):  # origins, directions or axes move
        return out, tangent(primals, given)
    return out, _placement_tangent(shell, bilinear, primals, tangents[:3])


def _placement_tangent(shell, bilinear, primals, tangents):
    """The lookups' tangent where only the images, the centre or the radius move, as a linear map
    with coefficients formed from the primals: ``α·δr + β·δc + Σ_g W_g·δimages[pixels_g]`` with α, β
    (N, K) per ray and W_g the weights of each grid point's read (four corners for ``bilinear``
    reads, one pixel otherwise). In reverse mode JAX transposes that to reductions and four
    scatters (of 4-vectors for bilinear reads: a read's corners are one row of a table of shifted
    images), where the transpose of :func:`_fan_lookup`'s written-out tangent kept every
    intermediate of the four reads (BENCHMARKS.md, "Coverage images"). The same derivative
    (``tests/test_image_lookup_grad.py``)."""
    d_occ, d_c, d_r = (None if isinstance(t, SymbolicZero) else t for t in tangents)
    # a stage of its own (in one program with the value and the rest, XLA:CPU fused the four
    # reads' coefficients into their consumers: the radius's gradient 77 against 14.5 ms on the egg)
    coefficients = partial(
        _placement_coefficients,
        shell,
        bilinear,
        need_occ=d_occ is not None,
        need_c=d_c is not None,
        need_r=d_r is not None,
    )
    coef, reads = staged(always(primals[2]), coefficients, *primals)
    occluded = primals[0]
    dtype = primals[3].dtype
    terms = []
    if d_r is not None:
        terms.append(coef["r"] * d_r.astype(dtype))
    if d_c is not None:
        d_c = d_c.astype(dtype)
        terms.append(coef["c"][0] * d_c[0] + coef["c"][1] * d_c[1] + coef["c"][2] * d_c[2])
    if d_occ is not None:
        d_occ = d_occ.astype(occluded.dtype)
        t_n, p_n, ny, nx = occluded.shape
        table = _corner_table(d_occ) if bilinear else _padded_tables(d_occ.reshape(-1), ny, nx)[0]
        for base, weights in reads:
            read = jnp.sum(table[base] * weights, axis=-1) if bilinear else table[base] * weights
            terms.append(read.astype(dtype))
    return _lin_sum(*terms)


def _corner_table(images):
    """(G, N_y, N_x) images, padded by one pixel of background, as rows of the four pixels
    ``(p, p + 1, p + W, p + W + 1)`` at each flat padded index p (W = N_x + 2): a bilinear read's
    corners in one gather (:func:`_placement_coefficients`' ``base``)."""
    t_n, p_n, ny, nx = images.shape
    wid = nx + 2
    flat = jnp.pad(images.reshape(-1, ny, nx), ((0, 0), (1, 1), (1, 1))).reshape(-1)
    flat = jnp.concatenate([flat, jnp.zeros(wid + 1, flat.dtype)])
    size = flat.shape[0] - wid - 1
    return jnp.stack([flat[:size], flat[1 : size + 1], flat[wid : size + wid], flat[wid + 1 :]], axis=-1)


def _placement_coefficients(
    shell, bilinear, occluded, center, radius, origins, dx, dy, dz, axis, *, need_occ, need_c, need_r
):
    """The coefficients of :func:`_placement_tangent`: a dict with ``"r"`` (N, K) and ``"c"``
    (three (N, K)), where needed, and per grid point ``(base, weights)``: for ``bilinear`` reads the
    flat index (N, K) into :func:`_corner_table` and the corner weights (N, K, 4), otherwise the
    index into :func:`_padded_tables` and the weight (N, K) of the images' own change. Derived from
    :func:`_fan_lookup`'s tangent: the read points move with the shell radius R = shell·r and with
    the centre through the focal point q (times the bilinear read's own slopes, or the images'
    central-difference slopes at the nearest pixel), the weights of the four grid points move with
    the shell entry of the axis, and for nearest reads the cut at the bounding sphere has its ramp
    (bilinear reads: no derivative at the cut)."""
    dtype = origins.dtype
    t_n, p_n, ny, nx = occluded.shape
    flat = occluded.reshape(-1)
    r = radius
    big_r = shell * r
    tan_a = math.tan(math.asin(1.0 / shell))
    sx, sy = nx / (2.0 * tan_a), ny / (2.0 * tan_a)
    rel = origins - center
    rx, ry, rz = rel[:, 0], rel[:, 1], rel[:, 2]
    rr = rx * rx + ry * ry + rz * rz
    gi, gj = _axis_grid(rel, axis, big_r, t_n, p_n)
    # the grid coordinates' derivatives per origin (N,): along R, and along each component of rel
    d_grid = {}
    if need_r:
        d_grid["r"] = jax.jvp(
            lambda b: _axis_grid(rel, axis, b, t_n, p_n), (big_r,), (jnp.ones_like(big_r),)
        )[1]
    if need_c:
        for c in range(3):
            e = jnp.zeros_like(rel).at[:, c].set(1.0)
            d_grid[c] = jax.jvp(lambda x: _axis_grid(x, axis, big_r, t_n, p_n), (rel,), (e,))[1]
    cell, angles, b, meets, (qx, qy, qz) = _rays(gi, gj, rel, rr, r, dx, dy, dz, t_n, p_n, dtype)
    if not bilinear:
        tables = _padded_tables(flat, ny, nx)
    vis = jnp.zeros(b.shape, dtype)
    coef_r = jnp.zeros(b.shape, dtype) if need_r else None
    coef_q = [jnp.zeros(b.shape, dtype) for _ in range(3)] if need_c else None  # along q
    coef_g = [jnp.zeros(b.shape, dtype) for _ in range(3)] if need_c else None  # the grid weights
    reads = []
    wid = nx + 2
    for di, dj, wi, wj, st, ct, sp, cp, k in _corners(cell, angles, t_n, p_n):
        sgn_i, sgn_j = (1.0 if di else -1.0), (1.0 if dj else -1.0)
        w = (wi * wj)[:, None]

        def read_slopes(qx, qy, qz, ct, st, cp, sp, k, w):
            """The read's pixel coordinates (u, v), its 1 − hit, and (a_x, a_y, a_z): the value's
            change per unit change of x_l, y_l and −z_l·(x, y)."""
            xl, yl, zl = _grid_point_coordinates(qx, qy, qz, ct, st, cp, sp, big_r)
            front = (zl > 0).astype(dtype)
            inv = safe_div(1.0, zl)
            x, y = xl * inv, yl * inv
            u, v = (x + tan_a) * sx, (y + tan_a) * sy
            if bilinear:
                read, (ax, ay), (c00, c10, c01, c11) = _bilinear(flat, k, u, v, ny, nx)
                slope_x = (1.0 - ay) * (c10 - c00) + ay * (c11 - c01)
                slope_y = (1.0 - ax) * (c01 - c00) + ax * (c11 - c10)
            else:  # the nearest pixel and the images' central-difference slopes there
                near, idx = _padded_index(k, jnp.floor(u), jnp.floor(v), ny, nx)
                read, slope_x, slope_y = (jnp.where(near, t[idx], 0.0) for t in tables)
            # −w·front·(slope of the read along x, y) per unit motion of the image coordinates
            gx = -w * front * slope_x.astype(dtype) * sx
            gy = -w * front * slope_y.astype(dtype) * sy
            # x = x_l / z_l: δx = (δx_l − x·δz_l)·inv, and alike for y
            a_x, a_y = gx * inv, gy * inv
            return u, v, front, 1.0 - read.astype(dtype) * front, a_x, a_y, a_x * x + a_y * y

        # for the three centre coefficients each grid point's ingredients are a stage (buffers):
        # fused into them, XLA:CPU recomputed the four reads for each (58 against 15 ms); for the
        # radius alone the stage costs more than it saves
        ingredients = partial(staged, always(big_r), read_slopes) if need_c else read_slopes
        u, v, front, free, a_x, a_y, a_z = ingredients(qx, qy, qz, ct, st, cp, sp, k, w)

        def weight_motion(d_gi, d_gj, wi=wi, wj=wj, sgn_i=sgn_i, sgn_j=sgn_j, free=free):
            return (sgn_i * d_gi * wj + wi * sgn_j * d_gj)[:, None] * free

        if need_r:  # q is fixed; z_l moves by δR
            coef_r = coef_r + weight_motion(*d_grid["r"]) - a_z
        if need_c:  # x_l, y_l, z_l move with q (the grid point's frame rows)
            dxl = (ct * cp, ct * sp, -st)
            dyl = (sp, -cp, None)
            dzl = (-st * cp, -st * sp, -ct)
            for c in range(3):
                term = a_x * dxl[c] - a_z * dzl[c]
                coef_q[c] = coef_q[c] + (term if dyl[c] is None else term + a_y * dyl[c])
                coef_g[c] = coef_g[c] + weight_motion(*d_grid[c])
        vis = vis + w * free
        if need_occ and not bilinear:
            near, idx = _padded_index(k, jnp.floor(u), jnp.floor(v), ny, nx)
            reads.append((idx, jnp.where(near & meets, -w * front, 0.0).astype(occluded.dtype)))
        elif need_occ:
            uu, vv = u - 0.5, v - 0.5
            x0, y0 = jnp.floor(uu), jnp.floor(vv)
            fx, fy = uu - x0, vv - y0
            near = (x0 >= -1) & (x0 <= nx - 1) & (y0 >= -1) & (y0 <= ny - 1) & meets
            base = (k * (ny + 2) + jnp.clip(y0, -1, ny - 1).astype(jnp.int32) + 1) * wid
            base = base + jnp.clip(x0, -1, nx - 1).astype(jnp.int32) + 1
            scale = jnp.where(near, -w * front, 0.0)
            weights = (
                jnp.stack([(1.0 - fx) * (1.0 - fy), fx * (1.0 - fy), (1.0 - fx) * fy, fx * fy], axis=-1)
                * scale[..., None]
            )
            reads.append((base, weights.astype(occluded.dtype)))
    coef = {}
    if not bilinear:  # the cut's ramp: −(1 − vis)·δarg, arg = (r − ρ)/Δρ + ½, Δρ ∝ r, ρ = |q|
        rho = safe_sqrt(rr[:, None] - b * b)
        width = r * _ramp_width(shell, nx)
        arg = (r - rho) / width + 0.5
        ramp = jnp.where((arg > 0.0) & (arg < 1.0) & (b < 0), (1.0 - vis) / width, 0.0)
        ramp_q = safe_div(ramp, rho)  # δρ = q·δrel / ρ
    if need_r:
        coef["r"] = shell * jnp.where(meets, coef_r, 0.0)
        if not bilinear:
            coef["r"] = coef["r"] - ramp * (1.0 - (r - rho) / r)
    if need_c:  # δrel = −δc moves q by δrel − (δrel·d) d
        proj = coef_q[0] * dx + coef_q[1] * dy + coef_q[2] * dz
        coef["c"] = tuple(
            -jnp.where(meets, coef_q[c] - proj * d + coef_g[c], 0.0) for c, d in enumerate((dx, dy, dz))
        )
        if not bilinear:
            coef["c"] = tuple(cc - ramp_q * q for cc, q in zip(coef["c"], (qx, qy, qz), strict=True))
    return coef, reads


_coverage_lookup.defjvp(_coverage_lookup_jvp, symbolic_zeros=True)


def _gather(flat, k, px, py, ny: int, nx: int):
    """``flat[k, py, px]`` of the (G·N_y·N_x,) images for integer-valued float pixel indices, the
    image's background (False / 0) outside it."""
    inside = (px >= 0) & (px < nx) & (py >= 0) & (py < ny)
    pxi = jnp.clip(px, 0, nx - 1).astype(jnp.int32)
    pyi = jnp.clip(py, 0, ny - 1).astype(jnp.int32)
    got = flat[(k * ny + pyi) * nx + pxi]
    return got & inside if got.dtype == jnp.bool_ else jnp.where(inside, got, 0.0)


def _bilinear(flat, k, u, v, ny: int, nx: int):
    """The (G·N_y·N_x,) float images read bilinearly between pixel centres at the continuous pixel
    coordinates (u, v) (pixel (i, j) spans [j, j + 1) × [i, i + 1); background 0 outside):
    ``(value, (a_x, a_y), (c00, c10, c01, c11))``, the weights toward the next column and row and
    the four pixels read."""
    uu, vv = u - 0.5, v - 0.5
    x0, y0 = jnp.floor(uu), jnp.floor(vv)
    ax, ay = uu - x0, vv - y0
    corners = tuple(_gather(flat, k, x0 + i, y0 + j, ny, nx) for j, i in ((0, 0), (0, 1), (1, 0), (1, 1)))
    c00, c10, c01, c11 = corners
    value = (1.0 - ay) * ((1.0 - ax) * c00 + ax * c10) + ay * ((1.0 - ax) * c01 + ax * c11)
    return value, (ax, ay), corners


@partial(jax.custom_jvp, nondiff_argnums=(4, 5))
def _read(flat, k, u, v, ny: int, nx: int):
    """The coverage image read at its nearest pixel to the continuous pixel coordinates (u, v).

    The derivative has two parts: the pixel's own (the coverage's tangent, from the silhouette
    boundary integral of :func:`jshadow.visibility.bsv_and_coverage_edgescan_diff`) and the motion
    of the read point over the image, ``∂cov/∂u du + ∂cov/∂v dv``, with the slope taken as the
    central difference of the two neighbouring pixels (background outside the image). Summed
    along a row, those slopes telescope to the image's jumps, so the read point's motion across an
    edge of the shadow carries the whole jump, spread over the two pixels beside it.
    """
    return _gather(flat, k, jnp.floor(u), jnp.floor(v), ny, nx)


def _read_jvp(ny, nx, primals, tangents):
    flat, k, u, v = primals
    dflat, _, du, dv = tangents
    px, py = jnp.floor(u), jnp.floor(v)
    near, idx = _padded_index(k, px, py, ny, nx)
    value, sx, sy = (jnp.where(near, t[idx], 0.0) for t in _padded_tables(flat, ny, nx))
    tangent = _zero_or(du, sx) + _zero_or(dv, sy)
    if not isinstance(dflat, SymbolicZero):
        tangent = tangent + _gather(dflat, k, px, py, ny, nx)
    return value, tangent


def _padded_tables(flat, ny: int, nx: int):
    """The images padded by one pixel of background and their two central-difference slopes, each
    flattened to (G·(N_y + 2)·(N_x + 2),): a read's value and slopes at one index
    (:func:`_padded_index`), reads just outside an image still seeing its border: three gathers
    instead of five."""
    pad = jnp.pad(flat.reshape(-1, ny, nx), ((0, 0), (2, 2), (2, 2)))
    return (
        pad[:, 1:-1, 1:-1].reshape(-1),
        (0.5 * (pad[:, 1:-1, 2:] - pad[:, 1:-1, :-2])).reshape(-1),
        (0.5 * (pad[:, 2:, 1:-1] - pad[:, :-2, 1:-1])).reshape(-1),
    )


def _padded_index(k, px, py, ny: int, nx: int):
    """(within one pixel of image k, the index into :func:`_padded_tables`) of pixel (px, py)."""
    near = (px >= -1) & (px <= nx) & (py >= -1) & (py <= ny)
    pxi = jnp.clip(px + 1, 0, nx + 1).astype(jnp.int32)
    pyi = jnp.clip(py + 1, 0, ny + 1).astype(jnp.int32)
    return near, (k * (ny + 2) + pyi) * (nx + 2) + pxi


def _zero_or(d, slope):
    """``slope · d`` in the images' dtype, or zeros where the tangent d is symbolically zero."""
    return jnp.zeros_like(slope) if isinstance(d, SymbolicZero) else slope * d.astype(slope.dtype)


_read.defjvp(_read_jvp, symbolic_zeros=True)
