"""Shadow-field evaluation at receivers: base sphere visibility (BSV) → visibility SH in world frame.

For an occluder with bounding sphere (c, r), sampling shell R = shell·r and BSV coefficients
``S_r[i, j]`` at the T×P shell points (see :mod:`jshadow.visibility`), the occlusion field at a
receiver x is (deformable-shadow-fields paper, Sec. 4.3; DESIGN.md §1.4):

1. ``u = (x − c)/|x − c|``, ``d = |x − c|``, spherical angles (θ, φ) of u about world +z;
2. ``S_r(θ, φ)``: bilinear interpolation of the BSV (φ periodic; θ clamped to the outermost rows,
   so the caps around the poles reuse the nearest ring — a limitation of any θ×φ grid);
3. ``S_d = M_k · S_r`` with ``k = R/d`` and ``M_k`` interpolated linearly in k from the table;
4. rotation from the local frame at (θ, φ) (z toward the centre) to world: ``D(frame) · S_d``.
   The frame (:func:`jshadow.visibility.bsv_frames`) is ``R_z(φ) R_y(θ) F₀`` with
   ``F₀ = diag(1, −1, −1)`` (y → −y, z → −z), which multiplies Y_lm by ``(−1)^(l+|m|)`` (the
   parity of P_l^|m| in z) and by −1 for m < 0 (sin(|m|φ) is odd in y); the rest is applied by
   Euler angles (:func:`jshadow.sh.rotate_zyz`) instead of by fitting at rotated directions.

Receivers farther than the largest tabulated distance see no occlusion (visibility 1 = √(4π)·e0);
those nearer than the smallest use the nearest table entry. Sphere occluders also have an exact
analytic path (:func:`sphere_visibility_sh`): from distance d > r a sphere blocks the cap of
half-angle asin(r/d) around the direction to its centre.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from . import sh
from ._numerics import safe_acos, safe_atan2, safe_norm, safe_normalize, safe_sqrt
from .scaling import MkTable, mk_apply, mk_in_range
from .visibility import BSV

__all__ = [
    "unit_visibility",
    "interpolate_bsv",
    "bsv_visibility_sh",
    "frame_to_world",
    "sphere_visibility_sh",
    "sphere_light_blocked",
]


def unit_visibility(shape: tuple[int, ...], n: int, dtype) -> Float[Array, "... n2"]:
    """SH coefficients of V ≡ 1 (no occlusion): √(4π) on e0."""
    return jnp.zeros((*shape, n * n), dtype).at[..., 0].set(math.sqrt(4.0 * math.pi))


def interpolate_bsv(coeffs: Float[Array, "T P n2"], theta, phi) -> Float[Array, "... n2"]:
    """Bilinear interpolation of BSV coefficients at angles (θ, φ) of the sampling sphere.

    Grid convention: ``θ_i = π(i + 0.5)/T``, ``φ_j = 2πj/P``. φ wraps; θ is clamped to
    [θ_0, θ_{T−1}]. Differentiable in θ, φ and the coefficients.
    """
    t_n, p_n = coeffs.shape[0], coeffs.shape[1]
    a = jnp.clip(theta * (t_n / math.pi) - 0.5, 0.0, t_n - 1.0)
    i0 = jnp.clip(jnp.floor(a).astype(jnp.int32), 0, max(t_n - 2, 0))
    wa = (a - i0.astype(a.dtype))[..., None]
    i1 = jnp.minimum(i0 + 1, t_n - 1)
    b = jnp.mod(phi * (p_n / (2.0 * math.pi)), float(p_n))
    j0f = jnp.floor(b)
    wb = (b - j0f)[..., None]
    j0 = jnp.mod(j0f.astype(jnp.int32), p_n)
    j1 = jnp.mod(j0 + 1, p_n)
    c00, c01 = coeffs[i0, j0], coeffs[i0, j1]
    c10, c11 = coeffs[i1, j0], coeffs[i1, j1]
    return (1 - wa) * ((1 - wb) * c00 + wb * c01) + wa * ((1 - wb) * c10 + wb * c11)


def bsv_visibility_sh(
    bsv: BSV, table: MkTable, points: Float[Array, "... 3"], bands: int | None = None
) -> Float[Array, "... n2"]:
    """World-frame visibility SH of one BSV occluder at receiver points (..., 3) → (..., n²).

    ``table`` is an occlusion-kind M_k table whose distances are in units of the sampling-shell
    radius ``bsv.shell_radius`` (k = R/d). The BSV's bands are taken from its coefficients; the
    table must have at least as many. ``bands`` (default: the BSV's) truncates the result after
    M_k and before the rotation (rotations do not mix bands, so this equals truncating at the
    end): a BSV sampled with more bands than the lighting is extrapolated at full resolution.
    """
    n = sh.sh_bands_of(bsv.coeffs.shape[-1]) if bands is None else int(bands)
    rel = points - bsv.center
    d = safe_norm(rel)
    u = safe_normalize(rel)
    theta = safe_acos(u[..., 2])
    phi = safe_atan2(u[..., 1], u[..., 0])
    s_r = interpolate_bsv(bsv.coeffs, theta, phi)
    big = jnp.asarray(1e6, d.dtype)
    k = jnp.where(d > 0, bsv.shell_radius / jnp.where(d > 0, d, 1.0), big)
    s_d = mk_apply(table, k, s_r)[..., : n * n]
    s_w = frame_to_world(s_d, theta, phi)
    return jnp.where(mk_in_range(table, k)[..., None], s_w, unit_visibility(d.shape, n, s_w.dtype))


def frame_to_world(
    coeffs: Float[Array, "... n2"], theta: Float[Array, "..."], phi: Float[Array, "..."]
) -> Float[Array, "... n2"]:
    """``D(bsv_frames(θ, φ)[1]) @ coeffs``: SH in the local BSV frame at (θ, φ) → world (module docstring)."""
    n = sh.sh_bands_of(coeffs.shape[-1])
    lm = [sh.sh_lm(i) for i in range(n * n)]
    sign = np.asarray([(-1.0) ** (l + abs(m)) * (-1.0 if m < 0 else 1.0) for l, m in lm])  # D(F₀)
    return sh.rotate_zyz(coeffs * jnp.asarray(sign, coeffs.dtype), phi, theta)


def sphere_visibility_sh(
    center: Float[Array, "3"], radius: Float[Array, ""], points: Float[Array, "... 3"], n: int
) -> Float[Array, "... n2"]:
    """Exact visibility SH of a sphere occluder: 1 − cap(axis toward the centre, half-angle asin(r/d)).

    Receivers inside the sphere (d <= r) are fully occluded (all zeros).
    """
    rel = center - points
    d = safe_norm(rel)
    axis = safe_normalize(rel)
    s = jnp.clip(radius / jnp.maximum(d, radius), 0.0, 1.0)  # sin α
    cos_alpha = safe_sqrt(1.0 - s * s)
    vis = unit_visibility(d.shape, n, points.dtype) - sh.cap(axis, cos_alpha, n)
    return jnp.where((d > radius)[..., None], vis, 0.0)


def _cap_angle(radius, d):
    """Half-angle asin(r/d) of a sphere of radius r seen from distance d (π/2 from inside)."""
    s = jnp.clip(radius / jnp.maximum(d, radius), 0.0, 1.0)
    return safe_atan2(s, safe_sqrt(1.0 - s * s))


def sphere_light_blocked(
    occ_center: Float[Array, "3"],
    occ_radius: Float[Array, ""],
    light_center: Float[Array, "3"],
    light_radius: Float[Array, ""],
    points: Float[Array, "... 3"],
) -> Float[Array, "..."]:
    """Fraction (...,) of a spherical light's solid angle hidden by a sphere occluder, exactly.

    Seen from a receiver, the occluder and the light are caps of half-angles a = asin(r_o/d_o) and
    b = asin(r_l/d_l) whose axes are γ apart. Their overlap is 0 for γ >= a + b, the smaller cap for
    γ <= |a − b|, and otherwise

        Ω∩ = 2 [π − cos a · acos((cos b − cos a cos γ)/(sin a sin γ))
                  − cos b · acos((cos a − cos b cos γ)/(sin b sin γ))
                  − acos((cos γ − cos a cos b)/(sin a sin b))]

    (the area of the intersection of two spherical caps; checked against Monte Carlo in the
    tests). The result is Ω∩ / (2π(1 − cos b)). It ignores the cosine weighting inside the light's
    cap (exact for the light's solid angle; for the irradiance the error is the variation of cos
    over the part hidden, small for small lights) and does not check whether the occluder is in
    front of the light — the caller masks occluders farther than the light. Receivers inside the
    occluder see the light fully hidden.
    """
    rel_o, rel_l = occ_center - points, light_center - points
    d_o, d_l = safe_norm(rel_o), safe_norm(rel_l)
    a, b = _cap_angle(occ_radius, d_o), _cap_angle(light_radius, d_l)
    cos_g = jnp.clip(jnp.sum(safe_normalize(rel_o) * safe_normalize(rel_l), -1), -1.0, 1.0)
    g = safe_acos(cos_g)
    omega_b = 2.0 * math.pi * (1.0 - jnp.cos(b))
    omega_a = 2.0 * math.pi * (1.0 - jnp.cos(a))
    part = (g < a + b) & (g > jnp.abs(a - b))
    # double where: the partial-overlap formula only ever sees angles where it is regular
    a_p, b_p, g_p = (jnp.where(part, x, y) for x, y in ((a, 0.3), (b, 0.2), (g, 0.4)))
    ca, cb, cg = jnp.cos(a_p), jnp.cos(b_p), jnp.cos(g_p)
    sa, sb, sg = jnp.sin(a_p), jnp.sin(b_p), jnp.sin(g_p)
    lens = 2.0 * (
        math.pi
        - ca * safe_acos(jnp.clip((cb - ca * cg) / (sa * sg), -1.0, 1.0))
        - cb * safe_acos(jnp.clip((ca - cb * cg) / (sb * sg), -1.0, 1.0))
        - safe_acos(jnp.clip((cg - ca * cb) / (sa * sb), -1.0, 1.0))
    )
    overlap = jnp.where(part, lens, jnp.where(g <= a - b, omega_b, jnp.where(g <= b - a, omega_a, 0.0)))
    frac = jnp.clip(overlap / jnp.where(omega_b > 0, omega_b, 1.0), 0.0, 1.0)
    return jnp.where(d_o > occ_radius, jnp.where(omega_b > 0, frac, 0.0), 1.0)
