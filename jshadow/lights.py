"""Light sources as SH radiance: environment maps and spherical area lights.

* :func:`read_latlong` reads a lat-long (equirectangular) radiance map; the convention (v = 0 at
  the zenith +y, u from +x counter-clockwise seen from above) is :func:`jshadow.entities.latlong_to_dir`.
* :func:`environment_sh` projects an :class:`~jshadow.entities.Environment` onto n SH bands in the
  world frame (Zhou et al. 2005 represent distant lighting the same way).
* :func:`sphere_light_sh` is the exact SH of a spherical light seen from receivers: a cap of
  half-angle asin(r/d) around the direction to the centre, times the light's radiance.
* :func:`sphere_light_srf` is the deformable-shadow-fields paper's source radiance field (SRF) path
  for the same light: the radiance sampled on the light's bounding sphere (a hemisphere) and
  extrapolated to distance d with an M_k table (Sec. 4.1–4.2, Appendix A). It exists to measure
  that path against :func:`sphere_light_sh`.

Radiance is linear RGB; SH arrays put the coefficient axis before the colour axis: (..., n², 3).
"""

from __future__ import annotations

import math
import os
from functools import lru_cache

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from . import sh
from ._numerics import fast_acos, fast_atan2, safe_div, safe_norm, safe_normalize, safe_sqrt, small_sum
from .entities import Environment, latlong_to_dir
from .scaling import MkTable, mk_apply, mk_apply_zonal

__all__ = [
    "read_latlong",
    "environment_sh",
    "sphere_light_sh",
    "sphere_light_dot",
    "sphere_light_srf",
    "cap_zonal_t",
    "sphere_light_irradiance",
    "IrradianceMap",
    "environment_irradiance_map",
    "environment_irradiance",
]


# ---- reading lat-long maps -------------------------------------------------------------------------


def _read_rgbe(path: str) -> np.ndarray:
    """Decode a Radiance RGBE (.hdr) file: flat or new-style run-length encoded scanlines."""
    with open(path, "rb") as f:
        data = f.read()
    if not (data.startswith(b"#?RADIANCE") or data.startswith(b"#?RGBE")):
        raise ValueError("not a Radiance .hdr file (missing '#?RADIANCE' header)")
    pos = 0
    while True:  # header lines up to an empty line
        end = data.index(b"\n", pos)
        line = data[pos:end].strip()
        pos = end + 1
        if line.startswith(b"FORMAT=") and line != b"FORMAT=32-bit_rle_rgbe":
            raise ValueError(f"unsupported .hdr pixel format {line.decode(errors='replace')}")
        if not line:
            break
    end = data.index(b"\n", pos)
    res = data[pos:end].split()
    pos = end + 1
    if len(res) != 4 or res[0] != b"-Y" or res[2] != b"+X":
        raise ValueError(f"unsupported .hdr orientation {b' '.join(res).decode(errors='replace')!r}")
    h, w = int(res[1]), int(res[3])
    buf = np.frombuffer(data, dtype=np.uint8)
    out = np.empty((h, w, 4), np.uint8)
    for row in range(h):
        head = [int(b) for b in buf[pos : pos + 4]]
        rle = 8 <= w < 32768 and head[:2] == [2, 2] and (head[2] << 8 | head[3]) == w
        if not rle:  # flat scanline
            out[row] = buf[pos : pos + 4 * w].reshape(w, 4)
            pos += 4 * w
            continue
        pos += 4
        for ch in range(4):
            x = 0
            while x < w:
                count = int(buf[pos])
                pos += 1
                if count > 128:
                    count -= 128
                    out[row, x : x + count, ch] = buf[pos]
                    pos += 1
                else:
                    out[row, x : x + count, ch] = buf[pos : pos + count]
                    pos += count
                x += count
    e = out[..., 3].astype(np.int32)
    scale = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0)  # 2^(e − 128 − 8)
    return ((out[..., :3].astype(np.float64) + 0.5) * scale[..., None]).astype(np.float32)


def read_latlong(path: str | os.PathLike) -> np.ndarray:
    """Read a lat-long radiance map as float32 (H, W, 3), W = 2H, linear RGB.

    ``.hdr`` (Radiance RGBE) is decoded here; other formats (e.g. ``.exr``) go through imageio,
    which reads them only if one of its plugins can. Raises ``ValueError`` naming the file when it
    is missing or unreadable, not (H, 2H, 3|4), or has negative or non-finite values.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ValueError(f"environment map {path!r}: file not found")
    try:
        if path.lower().endswith(".hdr"):
            img = _read_rgbe(path)
        else:
            import imageio.v3 as iio

            img = np.asarray(iio.imread(path), dtype=np.float32)
    except Exception as err:  # any decoder failure is the user's file problem
        raise ValueError(f"environment map {path!r}: cannot read it ({err})") from None
    if img.ndim != 3 or img.shape[2] not in (3, 4) or img.shape[1] != 2 * img.shape[0] or img.shape[0] < 1:
        raise ValueError(
            f"environment map {path!r}: expected a lat-long image of shape (H, 2H, 3), got {img.shape}"
        )
    img = np.ascontiguousarray(img[..., :3], dtype=np.float32)
    if not np.all(np.isfinite(img)):
        raise ValueError(f"environment map {path!r}: contains non-finite values")
    if np.any(img < 0):
        raise ValueError(f"environment map {path!r}: contains negative radiance")
    return img


# ---- environment ---------------------------------------------------------------------------------


def _rot_y(alpha: float) -> np.ndarray:
    c, s = math.cos(alpha), math.sin(alpha)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


@lru_cache(maxsize=8)
def _pixel_basis(h: int, w: int, n: int, spp: int, rotation_y: float) -> np.ndarray:
    """B[i, j, c] = ∫_pixel(i,j) Y_c(R_y ω) dω ((H, W, n²), summed in float64), by a spp×spp product rule.

    In each pixel: Gauss–Legendre in cos θ and midpoints in φ, with the pixel's exact solid angle
    (cos θ_top − cos θ_bottom)·Δφ as the total weight. Evaluated eagerly even when called while
    tracing (it depends on static sizes only).
    """
    with jax.ensure_compile_time_eval():
        return _pixel_basis_eager(h, w, n, spp, rotation_y)


def _pixel_basis_eager(h: int, w: int, n: int, spp: int, rotation_y: float) -> np.ndarray:
    x, wq = np.polynomial.legendre.leggauss(spp)
    th_edges = np.linspace(0.0, math.pi, h + 1)
    c_top, c_bot = np.cos(th_edges[:-1]), np.cos(th_edges[1:])
    cos_nodes = 0.5 * (c_top + c_bot)[:, None] + 0.5 * (c_top - c_bot)[:, None] * x[None, :]  # (H, spp)
    cos_w = 0.5 * (c_top - c_bot)[:, None] * wq[None, :]
    v = np.arccos(np.clip(cos_nodes, -1.0, 1.0)) / math.pi
    u = (np.arange(w)[:, None] + (np.arange(spp)[None, :] + 0.5) / spp) / w  # (W, spp)
    dphi = 2.0 * math.pi / (w * spp)
    vv = np.broadcast_to(v[:, None, :, None], (h, w, spp, spp))
    uu = np.broadcast_to(u[None, :, None, :], (h, w, spp, spp))
    d = np.asarray(latlong_to_dir(jnp.asarray(uu, jnp.float32), jnp.asarray(vv, jnp.float32)), np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    d = d @ _rot_y(rotation_y).T
    y = np.asarray(sh.sh_basis(jnp.asarray(d, jnp.float32), n), np.float64)
    wt = np.broadcast_to(cos_w[:, None, :, None] * dphi, (h, w, spp, spp))
    return np.einsum("hwabc,hwab->hwc", y, wt)


def environment_sh(
    env: Environment, n: int, samples_per_pixel: int = 2, rotation_y: float = 0.0
) -> Float[Array, "n2 3"]:
    """SH coefficients (n², 3) of the environment's radiance in the world frame.

    * "constant": exact, ``sqrt(4π)·L`` on e0.
    * "hdr": the piecewise-constant image integrated over every pixel with its exact solid angle
      ``(cos θ_top − cos θ_bottom)·Δφ`` and a ``samples_per_pixel``² product rule for Y_i inside
      the pixel (Gauss–Legendre in cos θ, midpoints in φ); the per-pixel integrals of the basis are
      cached per (H, W, n, samples, rotation) and the projection is one contraction with the image,
      so it is differentiable in ``env.image`` and ``env.radiance``.
    * "sky": quadrature of :meth:`Environment.radiance_at` (Gauss–Legendre in y on each hemisphere
      × uniform φ), exact for the CIE overcast sky (linear in y, black ground).

    ``rotation_y`` (radians, a Python float) turns the environment about +y: what the unrotated map
    shows at direction ω appears at ``R_y(rotation_y)·ω``.
    """
    if int(n) != n or n < 1:
        raise ValueError(f"n (number of SH bands) must be a positive integer, got {n}")
    if int(samples_per_pixel) != samples_per_pixel or samples_per_pixel < 1:
        raise ValueError(f"samples_per_pixel must be a positive integer, got {samples_per_pixel}")
    rad = jnp.asarray(env.radiance)
    dtype = rad.dtype
    if env.kind == "constant":
        return jnp.zeros((n * n, 3), dtype).at[0].set(math.sqrt(4.0 * math.pi) * rad)
    if env.kind == "hdr":
        img = jnp.asarray(env.image)
        if img.ndim != 3 or img.shape[-1] != 3:
            raise ValueError(f"Environment.image must have shape (H, W, 3), got {img.shape}")
        b = _pixel_basis(img.shape[0], img.shape[1], int(n), int(samples_per_pixel), float(rotation_y))
        return jnp.einsum("hwc,hwk->ck", jnp.asarray(b, img.dtype), img).astype(dtype) * rad
    if env.kind == "sky":
        d_world, d_src, wgt = _sky_nodes(n, float(rotation_y))  # static nodes, eager under a trace
        vals = env.radiance_at(jnp.asarray(d_src, dtype))  # (N, 3)
        basis = sh.sh_basis(jnp.asarray(d_world, dtype), n)  # (N, n²)
        return jnp.einsum("q,qk,qc->kc", jnp.asarray(wgt, dtype), basis, vals)
    raise ValueError(f"unknown environment kind {env.kind!r}; expected constant, hdr or sky")


@lru_cache(maxsize=8)
def _sky_nodes(n: int, rotation_y: float):
    """Quadrature for the sky: world directions, unrotated source directions, weights (numpy)."""
    with jax.ensure_compile_time_eval():
        t, wt = np.polynomial.legendre.leggauss(n + 2)
        y = np.concatenate([0.5 * (t + 1.0), 0.5 * (t - 1.0)])  # both hemispheres, split at the horizon
        wy = np.concatenate([0.5 * wt, 0.5 * wt])
        n_phi = 2 * n + 1
        u = (np.arange(n_phi) + 0.5) / n_phi
        yy, uu = np.meshgrid(y, u, indexing="ij")
        # latlong_to_dir's convention, in float64 NumPy whatever JAX's dtype mode (the result is cached)
        st, phi = np.sqrt(1.0 - yy**2), 2.0 * math.pi * uu
        d_src = np.stack([st * np.cos(phi), yy, -st * np.sin(phi)], axis=-1).reshape(-1, 3)
        d = d_src @ _rot_y(rotation_y).T
        wgt = (wy[:, None] * np.full(n_phi, 2.0 * math.pi / n_phi)[None, :]).reshape(-1)
        # radiance_at is evaluated at the *unrotated* direction, the basis at the rotated one
        return d, d_src, wgt


# ---- spherical lights ----------------------------------------------------------------------------


@lru_cache(maxsize=16)
def _cap_polys(n: int) -> tuple[tuple[float, ...], ...]:
    """Coefficients (ascending) of Q_l(t) = ∫_{1−t}^1 P_l(x) dx, l < n (zero constant term)."""
    out = []
    for l in range(n):
        p = np.polynomial.Legendre.basis(l).convert(kind=np.polynomial.Polynomial)
        q = p(np.polynomial.Polynomial([1.0, -1.0])).integ(lbnd=0.0)
        out.append(tuple(float(c) for c in q.coef))
    return tuple(out)


def cap_zonal_t(one_minus_cos: Float[ArrayLike, "..."], n: int) -> Float[Array, "... n"]:
    """Zonal coefficients (..., n) of a cap's indicator, from t = 1 − cos α ∈ [0, 2].

    ``z_l = 2π sqrt((2l+1)/4π) ∫_{1−t}^1 P_l``, evaluated as a polynomial in t with zero constant
    term, so small caps (t ≪ 1) keep full relative accuracy in float32 (the form in cos α loses it).
    """
    t = jnp.asarray(one_minus_cos)
    out = []
    for l, coef in enumerate(_cap_polys(int(n))):
        acc = jnp.zeros_like(t)
        for c in coef[:0:-1]:  # Horner, highest degree first, constant term (0) skipped
            acc = (acc + c) * t
        out.append(2.0 * math.pi * math.sqrt((2 * l + 1) / (4.0 * math.pi)) * acc)
    return jnp.stack(out, axis=-1)


@lru_cache(maxsize=16)
def _np_cap_zonal(cos_a: float, n: int) -> np.ndarray:
    """Zonal coefficients (n,) of the cap {cos θ >= cos_a} in float64: ``z_l = 2π √((2l+1)/4π)
    ∫_{cos a}^1 P_l``, with ``∫_x^1 P_l = (P_{l−1}(x) − P_{l+1}(x)) / (2l + 1)`` (l >= 1) and the
    three-term recurrence of P_l (stable for any l, unlike a polynomial in 1 − cos a)."""
    p = [1.0, cos_a]
    for l in range(1, n + 1):
        p.append(((2 * l + 1) * cos_a * p[l] - l * p[l - 1]) / (l + 1))
    integral = [1.0 - cos_a] + [(p[l - 1] - p[l + 1]) / (2 * l + 1) for l in range(1, n)]
    return np.asarray(
        [2.0 * math.pi * math.sqrt((2 * l + 1) / (4.0 * math.pi)) * v for l, v in enumerate(integral)]
    )


def _light_geometry(center, radius, points):
    center, radius, points = jnp.asarray(center), jnp.asarray(radius), jnp.asarray(points)
    if center.shape[-1:] != (3,) or points.shape[-1:] != (3,):
        raise ValueError(
            f"center and points must have a trailing axis of length 3, got {center.shape} and {points.shape}"
        )
    rel = center - points
    return safe_norm(rel), safe_normalize(rel), radius


def _cap_geometry(center, radius, points, n):
    """Distance d to the light's centre, the unit axis toward it, the radius and the cap's
    ``t = 1 − cos α`` (α = asin(r/d); 1 inside the light), checking n."""
    if int(n) != n or n < 1:
        raise ValueError(f"n (number of SH bands) must be a positive integer, got {n}")
    d, axis, radius = _light_geometry(center, radius, points)
    s = jnp.clip(safe_div(radius, d, fill=1.0), 0.0, 1.0)  # sin α
    return d, axis, radius, s * s / (1.0 + safe_sqrt(1.0 - s * s))  # 1 − cos α without cancellation


def _full_sphere(shape, n, dtype):
    return jnp.zeros((*shape, n * n), dtype).at[..., 0].set(math.sqrt(4.0 * math.pi))


def sphere_light_sh(
    center: Float[ArrayLike, "... 3"],
    radius: Float[ArrayLike, "..."],
    radiance: Float[ArrayLike, "... 3"],
    points: Float[ArrayLike, "... 3"],
    n: int,
) -> Float[Array, "... n2 3"]:
    """Exact SH (..., n², 3) of a spherical light of constant radiance seen from receiver points.

    From distance d > r the light fills the cap of half-angle α = asin(r/d) around the direction to
    its centre (Zhou et al. 2005 treat spherical sources the same way); receivers inside the light
    (d <= r) see it over the whole sphere. World frame. Gradients with respect to center, radius,
    radiance and points are finite everywhere (the cap's edge moves infinitely fast as d → r⁺; at
    d = r itself the gradient of α is 0 by construction).
    """
    d, axis, radius, t = _cap_geometry(center, radius, points, n)
    c = sh.zonal_rotate(cap_zonal_t(t, n), axis)
    c = jnp.where((d > radius)[..., None], c, _full_sphere(d.shape, n, c.dtype))
    return c[..., None] * jnp.asarray(radiance)[..., None, :]


def sphere_light_dot(
    center: Float[ArrayLike, "... 3"],
    radius: Float[ArrayLike, "..."],
    points: Float[ArrayLike, "... 3"],
    w: Float[ArrayLike, "... n2"],
    n: int,
) -> Float[Array, "..."]:
    """``Σ_i c_i w_i`` (...) for the SH c of a unit-radiance spherical light seen from the points.

    The same number as ``jnp.sum(sphere_light_sh(center, radius, 1, points, n)[..., 0] * w, -1)``
    (receivers inside the light see it everywhere), evaluated as one fused polynomial per receiver
    (:func:`jshadow.sh.zonal_dot`) without the light's (..., n²) coefficients. With w the transfer
    T this is the light's unoccluded n-band irradiance; with ``w = P(T) V`` (``P(T)`` the matrix of
    "multiply by T") its irradiance through the visibility V. ``w`` broadcasts against the points'
    batch axes (one shared (n²,) row for a plane's common transfer).
    """
    d, axis, radius, t = _cap_geometry(center, radius, points, n)
    w = jnp.asarray(w)
    cap = sh.zonal_dot(cap_zonal_t(t, n), axis, w)
    return jnp.where(d > radius, cap, math.sqrt(4.0 * math.pi) * w[..., 0])


def sphere_light_srf(
    center: Float[ArrayLike, "... 3"],
    radius: Float[ArrayLike, "..."],
    radiance: Float[ArrayLike, "... 3"],
    points: Float[ArrayLike, "... 3"],
    n: int,
    table: MkTable,
    shell: float = 1.0,
) -> Float[Array, "... n2 3"]:
    """The paper's SRF of a spherical light (..., n², 3), for comparison with :func:`sphere_light_sh`.

    ``shell`` (≥ 1) samples the radiance on a shell of ``shell`` × r, where the light fills the cap
    of half-angle asin(1/shell) (k = shell·r/d); the paper's setting is 1 (the hemisphere). The
    radiance is sampled and extrapolated with the table's bands and truncated to n afterwards, so a
    table with more bands than n gives the band split of :class:`jshadow.entities.Method`. With
    ``table.model == "sphere"`` (the concentric-sphere rescaling, exact for a sphere's cap) and the
    plain-warp "radiance" kind, the only errors left are the truncation of the sampled cap and its
    warp (tests/test_lights.py measures them against :func:`sphere_light_sh`). The radiance at a
    point is zonal about the direction to the light's centre, so a zonal table
    (:func:`jshadow.scaling.mk_zonal_table`: the m = 0 block of M_k in up to 48 bands) carries the
    sampled cap nearly untruncated: at shell 1.5 with the sphere model and 48 bands, the 4-band
    coefficients are within 1 % of the closed form from 1.2 to 24 light radii (irradiance on the
    axis within 0.8 % from 1.05 to 24; 1.2 % at 32, 3 % at 48, where the default table ends).

    The radiance sampled on the light's sampling shell (radius r: there the light fills the
    hemisphere toward its centre, a zonal function) is extrapolated to the receiver's distance with
    ``S_d = M_k S_r``, k = r/d, from ``table`` (kind "radiance": the plain warp, or
    "radiance_jacobian": the paper's Appendix A factor), and rotated to the direction of the centre.
    Receivers inside the light see it everywhere, as in :func:`sphere_light_sh`; beyond the table's
    largest distance the table clamps (the light stays at its size there), so build the table far
    enough. Neither variant is exact: the plain warp inherits f_k's silhouette error
    (tan α = r/(d − r) instead of sin α = r/d for the paper's model) and warps an already truncated
    hemisphere; the Jacobian variant keeps ∫L dω = 2πL at every distance, so it does not dim.
    """
    if table.kind not in ("radiance", "radiance_jacobian"):
        raise ValueError(
            f"sphere_light_srf needs a 'radiance' or 'radiance_jacobian' table, got {table.kind!r}"
        )
    if int(n) != n or not 1 <= n <= table.n:
        raise ValueError(f"n must be in 1..{table.n} (the table's bands), got {n}")
    if not shell >= 1.0:
        raise ValueError(f"shell must be >= 1 (a multiple of the light's radius), got {shell}")
    d, axis, radius = _light_geometry(center, radius, points)
    dtype = d.dtype
    nb = table.n
    t_shell = 1.0 - math.sqrt(1.0 - 1.0 / (shell * shell))  # 1 − cos α on the shell (1: hemisphere)
    k = safe_div(shell * radius, d, fill=1e6)
    if table.zonal:  # the cap in up to 48 bands (float64 constants: Horner in t loses them)
        z_r = jnp.asarray(_np_cap_zonal(1.0 - t_shell, nb), dtype)
        z_d = mk_apply_zonal(table, k, z_r, n)
    else:
        z_r = cap_zonal_t(jnp.full((), t_shell, dtype), nb)
        s_r = jnp.zeros((nb * nb,), dtype).at[jnp.asarray([l * l + l for l in range(nb)])].set(z_r)
        s_d = mk_apply(table, k, s_r)
        z_d = s_d[..., jnp.asarray([l * l + l for l in range(n)])]
    c = sh.zonal_rotate(z_d, axis)
    c = jnp.where((d > radius)[..., None], c, _full_sphere(d.shape, n, c.dtype))
    return c[..., None] * jnp.asarray(radiance)[..., None, :]


# ---- exact unoccluded irradiance ------------------------------------------------------------------


def sphere_light_irradiance(
    center: Float[ArrayLike, "... 3"],
    radius: Float[ArrayLike, "..."],
    radiance: Float[ArrayLike, "... 3"],
    points: Float[ArrayLike, "... 3"],
    normals: Float[ArrayLike, "... 3"],
) -> Float[Array, "... 3"]:
    """Exact unoccluded irradiance (..., 3) of a spherical light at receivers with unit normals.

    ``E = L · ∫_cap max(0, n·ω) dω`` over the cap of half-angle α = asin(r/d) around the direction
    to the light's centre, at angle β from the normal (sin α = s, cos β = c):

    * cap wholly above the horizon (c >= s): ``π s² c`` (the projected solid angle of the cap);
    * wholly below (c <= −s): 0;
    * cut by the horizon: with ``x = cos α / sin α``, ``y = −x c / sin β`` and
      ``q = sin β √(1 − y²)``, ``(c · acos y − x q) · s² + atan2(q, x)`` (the horizon-clipped cap
      integral, as tabulated for spherical area lights in real-time rendering; checked here against
      quadrature in tests/test_lights.py).

    Receivers inside the light (d <= r) see its radiance over the whole upper hemisphere: π L.
    This is what the shadow fields' SH cap (:func:`sphere_light_sh`) times the clamped cosine
    approximates with n bands; the "ratio" shading of :func:`jshadow.scene.combine` uses it to make
    unoccluded receivers exact. Value and gradients are finite at the branch boundaries (c = ±s,
    β = 0, s = 1).
    """
    d, axis, radius = _light_geometry(center, radius, points)
    normals = jnp.asarray(normals)
    s = jnp.clip(safe_div(radius, d, fill=1.0), 0.0, 1.0)  # sin α
    c = jnp.clip(small_sum(normals * axis), -1.0, 1.0)  # cos β
    above = c >= s
    part = (c > -s) & ~above
    s_p = jnp.where(part, s, 1.0)  # > 0 on the cut branch (|c| < s); double where below
    c_p = jnp.where(part, c, 0.0)
    sin_b = safe_sqrt(1.0 - c_p * c_p)
    x = safe_div(safe_sqrt(1.0 - s_p * s_p), s_p, fill=0.0)
    y = jnp.clip(safe_div(-x * c_p, sin_b, fill=0.0), -1.0, 1.0)
    q = sin_b * safe_sqrt(1.0 - y * y)
    e_cut = (c_p * fast_acos(y) - x * q) * s_p * s_p + fast_atan2(q, x)
    e = jnp.where(above, math.pi * s * s * c, jnp.where(part, e_cut, 0.0))
    e = jnp.where(d > radius, e, math.pi)
    return jnp.maximum(e, 0.0)[..., None] * jnp.asarray(radiance)


class IrradianceMap(eqx.Module):
    """Unoccluded irradiance of an environment as a function of the receiver normal.

    ``values[i, j]`` is E at the normal ``latlong_to_dir(u = j/W, v = i/(H−1))``: rows run from the
    zenith (+y, i = 0) to the nadir (i = H−1), so both poles are exact nodes (an upward plane's
    normal is one); columns wrap. :func:`environment_irradiance` interpolates bilinearly.
    """

    values: Float[Array, "H W 3"]


def _np_latlong_dirs(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """:func:`jshadow.entities.latlong_to_dir` on the grid u (W,) × v (H,) in NumPy float64 (H, W, 3):
    static geometry, concrete even under a trace."""
    theta, phi = np.pi * v[:, None], 2.0 * np.pi * u[None, :]
    st = np.sin(theta)
    return np.stack(np.broadcast_arrays(st * np.cos(phi), np.cos(theta), -st * np.sin(phi)), axis=-1)


def _block_sum(img, b):
    h, w = img.shape[0] // b, img.shape[1] // b
    return img[: h * b, : w * b].reshape(h, b, w, b, *img.shape[2:]).sum(axis=(1, 3))


def _env_samples(env: Environment, max_rows: int):
    """Radiance·solid angle (P, 3) and unit directions (P, 3) of the environment in lat-long cells.

    "hdr": pixels summed in b×b blocks (b the largest divisor of both sides with H/b >= max_rows,
    or 1; maps of fewer rows are first split into equal sub-pixels), each block at the centroid
    of its pixels' directions weighted by luminance × solid angle; "sky": a max_rows × 2·max_rows
    grid of cells at their centres. Every cell's solid angle is exact.
    """
    rad = jnp.asarray(env.radiance)
    if env.kind == "hdr":
        img = jnp.asarray(env.image)
        up = -(-max_rows // img.shape[0])  # small maps: split pixels (piecewise constant: exact)
        if up > 1:
            img = jnp.repeat(jnp.repeat(img, up, axis=0), up, axis=1)
        h, w = img.shape[:2]
        b = max([k for k in range(1, h + 1) if h % k == 0 and w % k == 0 and h // k >= max_rows] or [1])
    else:
        h, w, b = max_rows, 2 * max_rows, 1
    edges = np.cos(np.pi * np.arange(h + 1) / h)
    omega = (edges[:-1] - edges[1:]) * (2.0 * np.pi / w)  # (h,) solid angle of one cell in each row
    v = (np.arange(h) + 0.5) / h
    u = (np.arange(w) + 0.5) / w
    dirs = _np_latlong_dirs(u, v)
    wdir = dirs * omega[:, None, None]
    om = np.broadcast_to(omega[:, None], (h, w))
    if env.kind == "hdr":
        energy = _block_sum(img * jnp.asarray(om[..., None], img.dtype), b) * rad
        # a block's light sits at its energy centroid (a small sun keeps its direction); the
        # solid-angle term keeps black blocks well defined
        lum = jax.lax.stop_gradient(jnp.mean(img, -1))
        lum = lum / jnp.maximum(jnp.mean(lum), 1e-30)
        d = _block_sum(jnp.asarray(wdir, img.dtype) * (lum[..., None] + 1e-6), b)
        d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)  # never 0: the 1e-6 keeps every weight > 0
    else:
        energy = env.radiance_at(jnp.asarray(dirs, rad.dtype)) * jnp.asarray(om[..., None], rad.dtype)
        d = jnp.asarray(wdir / np.linalg.norm(wdir, axis=-1, keepdims=True))
    return energy.reshape(-1, 3), d.reshape(-1, 3).astype(rad.dtype)


def environment_irradiance_map(env: Environment, resolution: tuple[int, int] = (33, 64)) -> IrradianceMap:
    """Tabulate the unoccluded irradiance ``E(n) = ∫ L(ω) max(0, n·ω) dω`` over normals.

    Direct summation over the environment's cells (see :class:`IrradianceMap` for the layout): for
    the "hdr" kind the map's pixels are summed in blocks of at most 64 rows (a block's energy is
    exact; it is placed at its energy centroid, so a small bright source keeps its direction),
    for "sky" a 64 × 128 grid of cells; "constant" is exactly πL. Cost: H·W × (cells) × 3
    multiply-adds, about 5·10⁷ at the defaults (tens of ms on a CPU): compute it once per
    environment, outside per-frame loops. Differentiable in ``env.radiance`` and ``env.image``.
    """
    rows, cols = (int(r) for r in resolution)
    if rows < 3 or cols < 4:
        raise ValueError(f"resolution must be at least (3, 4) normals (rows, columns), got {resolution}")
    rad = jnp.asarray(env.radiance)
    if env.kind == "constant":
        return IrradianceMap(values=jnp.broadcast_to(math.pi * rad, (rows, cols, 3)))
    if env.kind not in ("hdr", "sky"):
        raise ValueError(f"unknown environment kind {env.kind!r}; expected constant, hdr or sky")
    energy, dirs = _env_samples(env, 64)
    normals = jnp.asarray(_np_latlong_dirs(np.arange(cols) / cols, np.arange(rows) / (rows - 1)), rad.dtype)
    normals = normals.reshape(-1, 3)
    cosines = jnp.maximum(normals @ dirs.T, 0.0)  # (H·W, P)
    vals = jnp.matmul(cosines, energy, precision=jax.lax.Precision.HIGHEST)
    return IrradianceMap(values=vals.reshape(rows, cols, 3))


def environment_irradiance(table: IrradianceMap, normals: Float[ArrayLike, "... 3"]) -> Float[Array, "... 3"]:
    """Unoccluded environment irradiance (..., 3) at unit normals, bilinear in the map's (u, v).

    The normals' (u, v) are :func:`jshadow.entities.dir_to_latlong`'s, from the polynomial angles
    (:func:`jshadow._numerics.fast_atan2`, within 3.1e-7 rad in float32; exact in float64):
    XLA:CPU's ``atan2`` and ``acos`` were most of this lookup's time for per-vertex normals."""
    vals = table.values
    rows, cols = vals.shape[0], vals.shape[1]
    normals = jnp.asarray(normals)
    v = fast_acos(normals[..., 1]) / jnp.pi
    u = jnp.mod(fast_atan2(-normals[..., 2], normals[..., 0]) / (2.0 * jnp.pi), 1.0)
    a = jnp.clip(v * (rows - 1), 0.0, rows - 1.0)
    i0 = jnp.clip(jnp.floor(a).astype(jnp.int32), 0, rows - 2)
    wa = (a - i0.astype(a.dtype))[..., None]
    b = u * cols
    j0f = jnp.floor(b)
    wb = (b - j0f)[..., None]
    j0 = jnp.mod(j0f.astype(jnp.int32), cols)
    j1 = jnp.mod(j0 + 1, cols)
    top = (1 - wb) * vals[i0, j0] + wb * vals[i0, j1]
    bot = (1 - wb) * vals[i0 + 1, j0] + wb * vals[i0 + 1, j1]
    return (1 - wa) * top + wa * bot
