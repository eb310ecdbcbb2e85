"""Projected-spherical-cap sampling of sphere lights (Peters & Dachsbacher 2019).

C. Peters and C. Dachsbacher, "Sampling Projected Spherical Caps in Real Time", PACMCGIT 2(1),
2019. Directions toward a sphere light are drawn with density proportional to ``max(0, n·ω)`` over
the light's spherical cap (projected solid angle), so that the estimator of the unoccluded
irradiance of a constant-radiance sphere has zero variance whenever the cap is entirely above the
horizon or clipped by it with its centre above it.

Local frame (all formulas): ``ẑ = n``, ``x̂`` the tangent direction toward the light centre,
``ŷ = n × x̂``. By the Nusselt analogy, projected solid angle is area in the unit disk of the
tangent plane. Three non-empty cases:

* FULL: cap above the horizon; its projection is the ellipse E (centre (c_x, 0), half-axes |r_x|,
  r_y), sampled uniformly: ``p⊥ = 1/(π r_x r_y)``.
* CLIP_ABOVE: centre above, cap clipped by the horizon; the projection is the cut ellipse left of
  ``x = t_x`` united with the unit disk right of ``t_x``; both sampled uniformly, ``p⊥ = 1/Ω⊥``.
* CLIP_BELOW: centre below, cap clipped; the cut disk right of ``t_x`` is sampled uniformly and
  warped onto the visible part of the cap. The density is not exactly constant; its max/min ratio
  is bounded (supplement, Eq. 4; ≤ √2 once the receiver is one light radius from the surface).

The erratum of the paper (the cut-disk area is measured from x = −1, so π/2 must be subtracted
before inverting the signed area) is built in: everything here inverts the segment area
``R(x) = acos x − x√(1 − x²)`` (area of the unit disk right of x) directly. The y half-extent uses
``√(1 − r_y²)``, and the warp's horizontal scale uses a closed form with no 0/0 and no clamp.

Densities: ``pdf`` is with respect to solid angle, ``pdf_proj`` (p⊥) with respect to projected solid
angle, ``pdf = (n·ω) · pdf_proj``. For an integrand ``f(ω) max(0, n·ω)`` use ``f / pdf_proj``.
"""

from __future__ import annotations

import math
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PRNGKeyArray

from .._numerics import eps, safe_div, safe_normalize, safe_sqrt

__all__ = [
    "CapSample",
    "CapCase",
    "segment_area",
    "segment_area_inverse",
    "projected_cap_frame",
    "projected_cap_case",
    "sample_projected_cap",
    "random_projected_cap",
    "projected_cap_pdf",
    "projected_solid_angle",
    "projected_cap_density_bound",
]


class CapCase:
    """Case labels returned by :func:`projected_cap_case`."""

    INSIDE = 0  # receiver inside the light: nothing to sample
    EMPTY = 1  # cap entirely below the horizon
    FULL = 2  # cap entirely above the horizon: ellipse
    CLIP_ABOVE = 3  # clipped, centre above: cut ellipse ∪ cut disk
    CLIP_BELOW = 4  # clipped, centre below: cut disk, warped


class CapSample(NamedTuple):
    """Directions drawn by :func:`sample_projected_cap` (or the cone/hemisphere samplers).

    ``direction`` (..., 3) unit world vectors; ``pdf`` (...) density per steradian; ``pdf_proj``
    (...) density per unit projected solid angle (``pdf / (n·ω)``; equal to ``pdf`` for samplers
    that have no normal); ``valid`` (...) False where nothing can be sampled (then both pdfs are 0
    and the sample must get weight 0).
    """

    direction: Float[Array, "... 3"]
    pdf: Float[Array, "..."]
    pdf_proj: Float[Array, "..."]
    valid: Bool[Array, "..."]


# --------------------------------------------------------------------------------------------
# The segment-area function and its inverse
# --------------------------------------------------------------------------------------------

# R(x) near x = 1 as a series in the half chord y = √(1 − x²): Σ 2·C(2m, m)/(4^m (2m + 3)) y^(2m+3)
_SERIES = tuple(2.0 * math.comb(2 * m, m) / (4.0**m * (2 * m + 3)) for m in range(8))
# fit of R⁻¹ near 1: ε = 1 − x ≈ s·P(s), s = w^(2/3), ascending powers (max |x error| 1.6e-6)
_FIT = (0.65512094, 0.04376721, 0.00524170, 0.00926736, -0.00543246, 0.00254099)


@jax.jit
def segment_area(x: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
    """``R(x) = acos x − x√(1 − x²)``: area of the unit disk right of the vertical line at x.

    x in [−1, 1] (clipped); R(−1) = π, R(0) = π/2, R(1) = 0, R(−x) = π − R(x). Near |x| = 1 a
    series in the half chord replaces the direct formula, which cancels there.
    """
    x = jnp.clip(jnp.asarray(x), -1.0, 1.0)
    ax = jnp.abs(x)
    y = safe_sqrt((1.0 - ax) * (1.0 + ax))  # half chord; (1 − x)(1 + x) keeps precision near 1
    direct = jnp.arctan2(y, ax) - ax * y
    y2 = y * y
    poly = jnp.zeros_like(y)
    for c in reversed(_SERIES):
        poly = poly * y2 + c
    series = poly * y2 * y
    right = jnp.where(y < 0.1, series, direct)  # R(|x|)
    return jnp.where(x >= 0, right, jnp.pi - right)


@jax.jit
def segment_area_inverse(w: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
    """``R⁻¹(w)`` for w in [0, π] (clipped): the x whose right segment has area w.

    Fold to w ≤ π/2 with ``R⁻¹(w) = −R⁻¹(π − w)``, start from a quintic fit in ``s = w^(2/3)`` and
    polish with two Newton steps (machine precision; the start matters because R' vanishes at
    |x| = 1). One Newton step in float32, two in float64.
    """
    w = jnp.clip(jnp.asarray(w), 0.0, jnp.pi)
    upper = w > 0.5 * jnp.pi
    wf = jnp.where(upper, jnp.pi - w, w)
    pos = wf > 0
    s = jnp.where(pos, jnp.power(jnp.where(pos, wf, 1.0), 2.0 / 3.0), 0.0)  # double where at w = 0
    poly = jnp.zeros_like(s)
    for c in reversed(_FIT):
        poly = poly * s + c
    x = jnp.clip(1.0 - s * poly, 0.0, 1.0)
    # the fit is good to 1.6e-6 in x; one Newton step reaches 2e-11 (enough for float32), two reach
    # the rounding limit of float64
    for _ in range(1 if jnp.finfo(x.dtype).bits <= 32 else 2):
        chord = 2.0 * safe_sqrt((1.0 - x) * (1.0 + x))
        x = jnp.clip(x + safe_div(segment_area(x) - wf, chord), 0.0, 1.0)
    return jnp.where(upper, -x, x)


# --------------------------------------------------------------------------------------------
# Geometry of the cap in the local frame
# --------------------------------------------------------------------------------------------


class _Cap(NamedTuple):
    xhat: Array  # (..., 3) tangent toward the light centre
    yhat: Array  # (..., 3) n × x̂
    n: Array  # (..., 3) unit normal
    wd: Array  # (..., 3) unit direction to the centre, ω_d
    wdx: Array  # ω_d · x̂ = cos e ≥ 0
    wdz: Array  # ω_d · n = sin e = cos β
    ry: Array  # r/|c| = sin α
    v: Array  # cos α
    one_m_cos: Array  # 1 − cos α = r_y²/(1 + v)
    cx: Array  # ellipse centre x = v ω_dx
    cz: Array  # circle centre height v ω_dz
    rx: Array  # signed x half-axis r_y ω_dz
    rz: Array  # z half-extent r_y ω_dx
    tx: Array  # horizon line x = t_x (clipped cases)
    ty: Array  # tangent points (t_x, ±t_y)
    case: Array  # CapCase label


def _tangent(n):
    """Some unit tangent of the unit vector n (branchless; Duff et al. 2017)."""
    x, y, z = n[..., 0], n[..., 1], n[..., 2]
    s = jnp.where(z >= 0, 1.0, -1.0).astype(n.dtype)
    a = -1.0 / (s + z)
    b = x * y * a
    return jnp.stack([1.0 + s * x * x * a, s * b, -s * x], axis=-1)


def _check3(name, a):
    a = jnp.asarray(a)
    if a.ndim < 1 or a.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3), got {a.shape}")
    return a


def projected_cap_frame(normal, to_center, radius) -> _Cap:
    """Local frame and boundary-circle quantities of the cap (algorithm description §1–§3).

    normal (..., 3) unit receiver normal; to_center (..., 3) vector from the receiver to the light
    centre; radius (...) light radius (same units). Leading axes broadcast.
    """
    n = _check3("normal", normal)
    c = _check3("to_center", to_center)
    dtype = jnp.result_type(n, c)
    r = jnp.asarray(radius, dtype)
    batch = jnp.broadcast_shapes(n.shape[:-1], c.shape[:-1], r.shape)
    n = jnp.broadcast_to(n.astype(dtype), (*batch, 3))
    c = jnp.broadcast_to(c.astype(dtype), (*batch, 3))
    r = jnp.broadcast_to(r, batch)
    n = safe_normalize(n)
    dist2 = jnp.sum(c * c, axis=-1)
    dist = safe_sqrt(dist2)
    wd = safe_normalize(c)
    wdz = jnp.clip(jnp.sum(n * wd, axis=-1), -1.0, 1.0)
    t = wd - wdz[..., None] * n
    tlen = safe_sqrt(jnp.sum(t * t, axis=-1))
    degenerate = tlen <= eps(dtype)  # light straight above/below: symmetric, any tangent will do
    xhat = jnp.where(degenerate[..., None], _tangent(n), safe_normalize(t))
    wdx = jnp.where(degenerate, 0.0, tlen)
    yhat = jnp.cross(n, xhat)
    inside = r >= dist
    ry = jnp.where(inside, 1.0, safe_div(r, dist, fill=1.0))
    ry = jnp.clip(ry, 0.0, 1.0)
    v = safe_sqrt((1.0 - ry) * (1.0 + ry))
    one_m_cos = ry * ry / (1.0 + v)
    cx, cz = v * wdx, v * wdz
    rx, rz = ry * wdz, ry * wdx
    clipped = (wdz * wdz < ry * ry) & ~inside
    tx = jnp.where(clipped, safe_div(v, wdx, fill=1.0), 1.0)
    ty = jnp.where(clipped, safe_div(safe_sqrt((ry - wdz) * (ry + wdz)), wdx), 0.0)
    case = jnp.where(
        inside,
        CapCase.INSIDE,
        jnp.where(
            clipped,
            jnp.where(wdz > 0, CapCase.CLIP_ABOVE, CapCase.CLIP_BELOW),
            jnp.where(wdz > 0, CapCase.FULL, CapCase.EMPTY),
        ),
    ).astype(jnp.int32)
    return _Cap(xhat, yhat, n, wd, wdx, wdz, ry, v, one_m_cos, cx, cz, rx, rz, tx, ty, case)


@jax.jit
def projected_cap_case(normal, to_center, radius) -> Int[Array, "..."]:
    """The :class:`CapCase` label (int32, shape (...)) of each receiver/light configuration."""
    return projected_cap_frame(normal, to_center, radius).case


def _clip_above_areas(g: _Cap):
    q = jnp.clip(safe_div(g.tx - g.cx, g.rx, fill=1.0), 0.0, 1.0)
    area_e = g.rx * g.ry * (jnp.pi - segment_area(q))  # cut ellipse left of t_x
    area_d = segment_area(g.tx)  # unit disk right of t_x
    return q, area_e, area_d


def _warp_params(g: _Cap):
    area_d = segment_area(g.tx)
    h = g.cz + g.rz  # top of the visible cap, sin(α + e)
    k = safe_div(h, g.ty, fill=1.0)  # vertical scale
    return area_d, k


def _warp_scale(g: _Cap, z):
    """s_y(z): horizontal scale of the CLIP_BELOW warp at source height z (closed form, no 0/0)."""
    a = g.rz - g.cz  # > 0 since c_z ≤ 0
    num = g.ty * a + (g.rz + g.cz) * z
    den = a * (g.ty + z)
    return safe_sqrt(safe_div(num, den, fill=1.0))


@jax.jit
def projected_solid_angle(normal, to_center, radius) -> Float[Array, "..."]:
    """``Ω⊥ = ∫_cap max(0, n·ω) dω`` of a sphere light (closed form; the cap's unoccluded
    irradiance per unit radiance). FULL: ``π sin²α cos β``. CLIP_BELOW uses
    ``A_D − |r_x| r_y R((t_x − c_x)/|r_x|)``, which cancels catastrophically for caps nearly tangent
    to the horizon (relative error ~1e-3 at Ω⊥ ~ 1e-15 in float64).
    """
    g = projected_cap_frame(normal, to_center, radius)
    full = jnp.pi * g.rx * g.ry
    _, area_e, area_d = _clip_above_areas(g)
    arx = jnp.abs(g.rx)
    q_below = jnp.clip(safe_div(g.tx - g.cx, arx, fill=1.0), -1.0, 1.0)
    below = jnp.maximum(area_d - arx * g.ry * segment_area(q_below), 0.0)
    out = jnp.select(
        [g.case == CapCase.FULL, g.case == CapCase.CLIP_ABOVE, g.case == CapCase.CLIP_BELOW],
        [full, area_e + area_d, below],
        0.0,
    )
    return out


@jax.jit
def sample_projected_cap(
    u: Float[ArrayLike, "... 2"],
    normal: Float[ArrayLike, "... 3"],
    to_center: Float[ArrayLike, "... 3"],
    radius: Float[ArrayLike, "..."] | float,
) -> CapSample:
    """Directions toward a sphere light, distributed in proportion to projected solid angle.

    Args:
        u: (..., 2) uniform numbers in [0, 1).
        normal: (..., 3) unit receiver normal n.
        to_center: (..., 3) vector from the receiver to the light centre (scene units).
        radius: (...) light radius (scene units).
        All leading axes broadcast.

    Returns:
        :class:`CapSample`. FULL and CLIP_ABOVE: ``pdf_proj = 1/Ω⊥`` exactly. CLIP_BELOW: the warped
        cut disk (Peters & Dachsbacher 2019, supplement Sec. 3), density bounded but not constant.
        INSIDE (receiver inside the light) and EMPTY (cap below the horizon): ``valid`` False,
        direction n, pdfs 0. Samples lie in the cap and have ``n·ω ≥ 0`` (up to rounding).
        Not intended for differentiation (gradients through the sampling map are not tested).
    """
    u = jnp.asarray(u)
    if u.ndim < 1 or u.shape[-1] != 2:
        raise ValueError(f"u must have shape (..., 2) of uniform numbers, got {u.shape}")
    g = projected_cap_frame(normal, to_center, radius)
    dtype = g.n.dtype
    u = u.astype(dtype)
    xi0, xi1 = jnp.broadcast_arrays(u[..., 0], u[..., 1])
    batch = jnp.broadcast_shapes(xi0.shape, g.case.shape)
    g = jax.tree.map(lambda a: jnp.broadcast_to(a, (*batch, *a.shape[len(g.case.shape) :])), g)
    xi0, xi1 = jnp.broadcast_to(xi0, batch), jnp.broadcast_to(xi1, batch)
    ys = 2.0 * xi1 - 1.0

    def chord(x):
        return safe_sqrt((1.0 - x) * (1.0 + x))

    case = g.case
    is_full, is_ca, is_cb = case == CapCase.FULL, case == CapCase.CLIP_ABOVE, case == CapCase.CLIP_BELOW

    # Every case inverts the segment area R once; select the argument per case so that the costly
    # inverse (fit + 2 Newton steps) runs once per sample, not once per case.
    q, area_e, area_d = _clip_above_areas(g)  # area_d = R(t_x): the cut disk, both clipped cases
    total = area_e + area_d
    p_e = safe_div(area_e, total)
    in_e = is_ca & (xi0 < p_e)  # CLIP_ABOVE: ξ0 picks the cut ellipse (else the cut disk)
    xi_e = safe_div(xi0, p_e)
    xi_d = jnp.clip(safe_div(xi0 - p_e, 1.0 - p_e), 0.0, 1.0)
    w = jnp.select(
        [is_full, in_e, is_ca],
        [
            jnp.pi * xi0,  # FULL: x_u = −R⁻¹(π ξ0), area πξ0 left of x_u
            xi_e * (jnp.pi - segment_area(q)),  # cut ellipse: x_u = −R⁻¹(ξ′(π − R(q))) ≤ q
            area_d * (1.0 - xi_d),  # cut disk: x = R⁻¹(A_D(1 − ξ′)) ≥ t_x, continuous at the switch
        ],
        area_d * (1.0 - xi0),  # CLIP_BELOW: d_x = R⁻¹(A_D(1 − ξ0)) ≥ t_x
    )
    xr = segment_area_inverse(w)
    xr = jnp.where(is_full | in_e, -xr, xr)

    # FULL and the cut-ellipse part: affine map of the unit disk onto E (x_u ≤ q clamps overshoot)
    xu = jnp.where(in_e, jnp.minimum(q, xr), xr)
    ell_x = g.cx + g.rx * xu
    ell_y = g.ry * chord(xu) * ys
    # cut-disk part (CLIP_ABOVE) and the source point of the warp (CLIP_BELOW)
    dx = jnp.maximum(g.tx, xr)
    dy = chord(dx) * ys

    # CLIP_BELOW: the warp (y, z) → (s_y(z) y, k z) of the lifted cut disk
    _, k = _warp_params(g)
    dz = jnp.minimum(safe_sqrt((1.0 - dx) * (1.0 + dx) - dy * dy), g.ty)
    sy = _warp_scale(g, dz)
    cb_z = k * dz
    cb_y = sy * dy
    cb_x = safe_sqrt(1.0 - cb_y * cb_y - cb_z * cb_z)

    full_pp = safe_div(1.0, jnp.pi * g.rx * g.ry)
    ca_pp = safe_div(1.0, total)
    cb_pp = safe_div(cb_x, k * k * area_d * dx * sy)

    valid = is_full | is_ca | is_cb
    on_ellipse = is_full | in_e
    wx = jnp.select([on_ellipse, is_ca], [ell_x, dx], cb_x)
    wy = jnp.select([on_ellipse, is_ca], [ell_y, dy], cb_y)
    wz = jnp.where(is_cb, cb_z, safe_sqrt(1.0 - wx * wx - wy * wy))
    pdf_proj = jnp.where(valid, jnp.select([is_full, is_ca], [full_pp, ca_pp], cb_pp), 0.0)
    d = wx[..., None] * g.xhat + wy[..., None] * g.yhat + wz[..., None] * g.n
    d = jnp.where(valid[..., None], safe_normalize(d), g.n)
    pdf = jnp.where(valid, wz * pdf_proj, 0.0)
    return CapSample(d, pdf, pdf_proj, valid)


@partial(jax.jit, static_argnames="num")
def random_projected_cap(
    key: PRNGKeyArray,
    normal: Float[ArrayLike, "... 3"],
    to_center: Float[ArrayLike, "... 3"],
    radius: Float[ArrayLike, "..."] | float,
    num: int,
) -> CapSample:
    """``num`` samples per configuration: :func:`sample_projected_cap` with ``u`` drawn from
    ``key``; outputs have shape (..., num[, 3]). Deterministic for a key."""
    n = jnp.asarray(normal)
    c = jnp.asarray(to_center)
    dtype = jnp.result_type(n, c)
    batch = jnp.broadcast_shapes(n.shape[:-1], c.shape[:-1], jnp.shape(radius))
    u = jax.random.uniform(key, (*batch, num, 2), dtype)
    return sample_projected_cap(u, n[..., None, :], c[..., None, :], jnp.asarray(radius, dtype)[..., None])


@jax.jit
def projected_cap_pdf(
    direction: Float[ArrayLike, "... 3"],
    normal: Float[ArrayLike, "... 3"],
    to_center: Float[ArrayLike, "... 3"],
    radius: Float[ArrayLike, "..."] | float,
) -> Float[Array, "..."]:
    """Solid-angle density with which :func:`sample_projected_cap` produces the unit ``direction``.

    0 outside the cap, below the horizon, and in the EMPTY/INSIDE cases. For CLIP_BELOW the warp is
    inverted (``d_z = ω_z/k``, ``d_y = ω_y/s_y(d_z)``). Directions exactly on the cap boundary may
    be classified either way by rounding. Use with multiple importance sampling.
    """
    w = _check3("direction", direction)
    g = projected_cap_frame(normal, to_center, radius)
    w = w.astype(g.n.dtype)
    wx = jnp.sum(w * g.xhat, axis=-1)
    wy = jnp.sum(w * g.yhat, axis=-1)
    wz = jnp.sum(w * g.n, axis=-1)
    dd = w - g.wd
    in_cap = jnp.sum(dd * dd, axis=-1) <= 2.0 * g.one_m_cos  # |ω − ω_d|² ≤ 2(1 − cos α), stable
    ok = in_cap & (wz >= 0)
    _, area_e, area_d = _clip_above_areas(g)
    full = jnp.pi * g.rx * g.ry
    area_db, k = _warp_params(g)
    dz = jnp.minimum(safe_div(wz, k), g.ty)
    sy = _warp_scale(g, dz)
    dy = safe_div(wy, sy)
    dx = safe_sqrt(1.0 - dy * dy - dz * dz)
    below = safe_div(wz * wx, k * k * area_db * dx * sy)
    pdf = jnp.select(
        [g.case == CapCase.FULL, g.case == CapCase.CLIP_ABOVE, g.case == CapCase.CLIP_BELOW],
        [safe_div(wz, full), safe_div(wz, area_e + area_d), below],
        0.0,
    )
    return jnp.where(ok, pdf, 0.0)


@jax.jit
def projected_cap_density_bound(normal, to_center, radius) -> Float[Array, "..."]:
    """Upper bound (supplement Eq. 4, attained) on max/min of ``pdf_proj`` over the cap:
    ``(c_x − r_x)/t_x · √((r_z − c_z)/r_z)`` in the CLIP_BELOW case, 1 in FULL and CLIP_ABOVE
    (constant density), NaN-free 1 where nothing is sampled."""
    g = projected_cap_frame(normal, to_center, radius)
    bound = safe_div(g.cx - g.rx, g.tx, fill=1.0) * safe_sqrt(safe_div(g.rz - g.cz, g.rz, fill=1.0))
    return jnp.where(g.case == CapCase.CLIP_BELOW, bound, 1.0)
