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
free) gets the same treatment, its jump spread over one pixel's width at the cone's edge. Summed
over many rays (a light's cap, many receivers) this is the derivative of the shadow; per ray it is
rough. Measured (``tests/test_image_lookup_grad.py``): a mesh sphere's gradients with respect to
the light's centre, its own centre and radius 1.7 %, 8 % and 4.6 % from the closed-form lens's at
24² receivers; a taper's 5.4 % from exact ray-cast differences (``experiments/image_grad.py``:
0.6–19 % on the shipped deforming configs).

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
from ._edgescan import bsv_and_occlusion_edgescan, edgescan_occlusion
from ._frames import bsv_grid_angles

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
    """

    occluded: Bool[Array, "T P Ny Nx"] | Float[Array, "T P Ny Nx"]
    center: Float[Array, "3"]
    radius: Float[Array, ""]
    shell: float = eqx.field(static=True)


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
    nx = images.occluded.shape[-1]
    return images.radius * (1.0 + 2.0 * (images.shell**2 - 1.0) / (nx * images.shell**2))


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
    """:func:`image_fan_visibility` with ``dirs`` as three (N, K) arrays of x, y, z components."""
    origins, axis = jnp.asarray(origins), jnp.asarray(axis)
    dtype = jnp.result_type(origins, dirs[0], images.center)
    origins, axis = origins.astype(dtype), axis.astype(dtype)
    t_n, p_n, ny, nx = images.occluded.shape
    flat = images.occluded.reshape(-1)
    coverage = not jnp.issubdtype(flat.dtype, jnp.bool_)
    r = images.radius.astype(dtype)
    big_r = images.shell * r
    tan_a = math.tan(math.asin(1.0 / images.shell))
    rel = origins - images.center.astype(dtype)
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
    gi = theta * (t_n / math.pi) - 0.5
    gj = phi * (p_n / (2.0 * math.pi))
    i0, j0 = jnp.floor(gi), jnp.floor(gj)
    fi, fj = gi - i0, gj - j0
    i0, j0 = i0.astype(jnp.int32), j0.astype(jnp.int32)
    th, ph = bsv_grid_angles(t_n, p_n, dtype)
    sin_t, cos_t, sin_p, cos_p = jnp.sin(th), jnp.cos(th), jnp.sin(ph), jnp.cos(ph)
    dx, dy, dz = (x.astype(dtype) for x in dirs)
    b = rx[:, None] * dx + ry[:, None] * dy + rz[:, None] * dz
    meets = (b * b - (rr[:, None] - r * r) > 0) & (b < 0)
    # the focal point q = rel − b·d (the ray's point nearest c), once per ray for all grid points
    qx, qy, qz = rx[:, None] - b * dx, ry[:, None] - b * dy, rz[:, None] - b * dz
    vis = jnp.zeros(b.shape, dtype)
    for di in (0, 1):
        ii = jnp.clip(i0 + di, 0, t_n - 1)
        wi = fi if di else 1.0 - fi
        st, ct = sin_t[ii], cos_t[ii]
        for dj in (0, 1):
            jj = jnp.mod(j0 + dj, p_n)
            wj = fj if dj else 1.0 - fj
            sp, cp = sin_p[jj], cos_p[jj]
            # the grid point's frame (bsv_frames): x = (ct cp, ct sp, −st), y = (sp, −cp, 0), z = −u;
            # local coordinates of q − R·u, where frameᵀ u = (0, 0, −1)
            h = qx * cp[:, None] + qy * sp[:, None]
            xl = h * ct[:, None] - qz * st[:, None]
            yl = qx * sp[:, None] - qy * cp[:, None]
            zl = big_r - (h * st[:, None] + qz * ct[:, None])
            front = zl > 0
            inv = safe_div(1.0, zl)
            x, y = xl * inv, yl * inv
            u = (x + tan_a) * (nx / (2.0 * tan_a))  # continuous pixel coordinates
            v = (y + tan_a) * (ny / (2.0 * tan_a))
            k = (ii * p_n + jj)[:, None]
            if coverage:
                hit = _read(flat, k, u, v, ny, nx) * front.astype(flat.dtype)
            else:
                hit = _gather(flat, k, jnp.floor(u), jnp.floor(v), ny, nx) & front
            vis = vis + (wi * wj)[:, None] * (1.0 - hit.astype(dtype))
    out = jnp.where(meets, vis, 1.0)
    if coverage:
        # The cut at the bounding sphere (rays whose line misses it are free) is a jump of 1 − vis
        # where the line's distance ρ from c crosses r, which a sphere-like mesh's silhouette
        # nearly meets. Its derivative, as the images' own: spread over the width Δρ of one pixel
        # at the cone's edge (x = ρ/√(R² − ρ²) seen from the entry point, dx/dρ = shell²/(r
        # (shell² − 1)^{3/2}) at ρ = r), with no change of value (φ − stop_gradient(φ) = 0).
        rho = safe_sqrt(rr[:, None] - b * b)
        width = r * (2.0 * (images.shell**2 - 1.0) / (nx * images.shell**2))
        ramp = jnp.clip((r - rho) / width + 0.5, 0.0, 1.0)
        ramp = jnp.where(b < 0, ramp - lax.stop_gradient(ramp), 0.0)
        out = out - lax.stop_gradient(1.0 - vis) * ramp
    return out


def _gather(flat, k, px, py, ny: int, nx: int):
    """``flat[k, py, px]`` of the (G·N_y·N_x,) images for integer-valued float pixel indices, the
    image's background (False / 0) outside it."""
    inside = (px >= 0) & (px < nx) & (py >= 0) & (py < ny)
    pxi = jnp.clip(px, 0, nx - 1).astype(jnp.int32)
    pyi = jnp.clip(py, 0, ny - 1).astype(jnp.int32)
    got = flat[(k * ny + pyi) * nx + pxi]
    return got & inside if got.dtype == jnp.bool_ else jnp.where(inside, got, 0.0)


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
    # the value and the two slopes from tables padded by one pixel (reads just outside the image
    # still see its border), all at one index: three gathers instead of five
    g = flat.reshape(-1, ny, nx)
    pad = jnp.pad(g, ((0, 0), (2, 2), (2, 2)))
    tables = (
        pad[:, 1:-1, 1:-1],
        0.5 * (pad[:, 1:-1, 2:] - pad[:, 1:-1, :-2]),
        0.5 * (pad[:, 2:, 1:-1] - pad[:, :-2, 1:-1]),
    )
    near = (px >= -1) & (px <= nx) & (py >= -1) & (py <= ny)
    pxi = jnp.clip(px + 1, 0, nx + 1).astype(jnp.int32)
    pyi = jnp.clip(py + 1, 0, ny + 1).astype(jnp.int32)
    idx = (k * (ny + 2) + pyi) * (nx + 2) + pxi
    value, sx, sy = (jnp.where(near, t.reshape(-1)[idx], 0.0) for t in tables)
    tangent = _zero_or(du, sx) + _zero_or(dv, sy)
    if not isinstance(dflat, SymbolicZero):
        tangent = tangent + _gather(dflat, k, px, py, ny, nx)
    return value, tangent


def _zero_or(d, slope):
    """``slope · d`` in the images' dtype, or zeros where the tangent d is symbolically zero."""
    return jnp.zeros_like(slope) if isinstance(d, SymbolicZero) else slope * d.astype(slope.dtype)


_read.defjvp(_read_jvp, symbolic_zeros=True)
