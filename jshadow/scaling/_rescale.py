"""Angular rescaling of visibility between radial distances (the deformable-shadow-fields paper, Sec. 4.1).

A receiver at distance d from an entity's centre, in direction (θ, φ) of the local frame whose +z
axis points to the centre, is assumed to see the entity like the point at the same direction on
the sampling shell of radius r, with the polar angle remapped. With k = r/d:

* ``model="paper"``: the square-silhouette model of the paper,
  ``f_k(θ) = atan(k·T / (1 + T − k·T))`` (+π where negative), T = tan θ. It is evaluated here as
  ``atan2(k·sin θ, cos θ + (1 − k)·sin θ)`` — the same function without the blow-ups at θ = π/2
  and at a zero denominator. Its derivative is ``f_k'(θ) = k / ρ²`` with
  ``ρ² = k² sin² θ + (cos θ + (1 − k) sin θ)²``.
* ``model="sphere"``: the concentric-sphere model ``g_k(θ) = asin(k·sin θ)``, exact for a sphere
  centred on the shell's centre (a silhouette at angle θ from radius r is a sphere of radius
  r·sin θ, seen at asin(k sin θ) from d). It is used on ``θ ∈ [0, θ_a]`` with θ_a = π/2 for
  k <= 1 and θ_a = asin(1/k) for k > 1 (beyond θ_a the receiver would be inside that sphere); on
  ``[θ_a, π]`` it continues linearly to ``g_k(π) = π``. This continuation makes g_k monotone on
  [0, π] and ``g_{1/k} = g_k⁻¹`` exactly, for k <= 1 and k > 1 alike. It only remaps directions
  that are unoccluded on the shell (θ > π/2 there: the hemisphere facing away from the entity),
  so it matters only for the ringing of band-limited functions.

Both maps satisfy ``map_k(0) = 0``, ``map_k(π) = π``, ``map_1 = id`` and ``map_k⁻¹ = map_{1/k}``.
Since ``f_k`` maps a silhouette angle seen from radius r to the angle seen from d, visibility at d
is ``V_d(θ, φ) = V_r(f_{1/k}(θ), φ)`` (Sec. 4.1/4.2 of the paper write f_k there; its geometry and
Appendix B need the inverse — DESIGN.md §2).

Angles in radians, θ ∈ [0, π] measured from the local +z axis; k > 0 (k → 0 is handled without
NaN but is degenerate: the entity shrinks to a point).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._numerics import safe_atan2, safe_div, safe_sqrt

__all__ = ["MODELS", "f_k", "f_k_inverse", "srf_jacobian"]

MODELS = ("paper", "sphere")


def _check_model(model: str) -> None:
    if model not in MODELS:
        raise ValueError(f"rescaling model must be one of {MODELS}, got {model!r}")


def _sin_cos(theta):
    """(sin θ, cos θ) with sin θ >= 0 at θ = π in float32 too (sin(float32(π)) < 0 otherwise)."""
    upper = theta > 0.5 * math.pi
    s = jnp.sin(jnp.where(upper, math.pi - theta, theta))  # both branches smooth: single where is fine
    return s, jnp.cos(theta)


def _safe_asin(x):
    """asin(clip(x, -1, 1)) as atan2(x, sqrt(1 - x²)): finite value and gradient at ±1."""
    x = jnp.clip(x, -1.0, 1.0)
    return safe_atan2(x, safe_sqrt(1.0 - x * x))


def _sphere_knots(k):
    """(θ_a, g_a): end of the asin segment of g_k and its value there."""
    q = jnp.where(k <= 1.0, k, safe_div(1.0, k, fill=0.0))  # min(k, 1/k) in [0, 1]
    asin_q = _safe_asin(q)
    half_pi = jnp.full_like(q, 0.5 * math.pi)
    theta_a = jnp.where(k <= 1.0, half_pi, asin_q)
    g_a = jnp.where(k <= 1.0, asin_q, half_pi)
    return theta_a, g_a


def f_k(
    theta: Float[ArrayLike, "..."], k: Float[ArrayLike, "..."], model: str = "paper"
) -> Float[Array, "..."]:
    """Angular rescaling ``f_k(θ)`` (radians), broadcast over θ and k.

    Args:
        theta: (...) polar angles in [0, π] (radians) seen from the sampling shell (radius r).
        k: (...) ratio r/d > 0 (k < 1: receiver outside the shell, shrinks; k > 1: inside, expands).
        model: "paper" (square silhouette, the default) or "sphere" (concentric spheres); see the
            module docstring.

    Returns:
        (...) the polar angle at which the same silhouette is seen from distance d = r/k.

    Value and gradient are finite at θ = 0, π/2, π, at k = 1 and for k → 0. For the sphere model
    the derivative is unbounded where ``k sin θ → 1`` (a square-root singularity); at the point
    itself the gradient is 0 by construction.
    """
    _check_model(model)
    theta, k = jnp.asarray(theta), jnp.asarray(k)
    s, c = _sin_cos(theta)
    if model == "paper":
        return safe_atan2(k * s, c + (1.0 - k) * s)
    theta_a, g_a = _sphere_knots(k)
    on_asin = theta <= theta_a
    s1 = jnp.where(on_asin, s, 0.0)  # double where: the asin branch never sees k·sin θ > 1
    g1 = _safe_asin(k * s1)
    slope = (math.pi - g_a) / (math.pi - theta_a)  # π − θ_a >= π/2
    g2 = g_a + (theta - theta_a) * slope
    return jnp.where(on_asin, g1, g2)


def f_k_inverse(
    theta: Float[ArrayLike, "..."], k: Float[ArrayLike, "..."], model: str = "paper"
) -> Float[Array, "..."]:
    """Inverse of :func:`f_k` in θ: ``f_k⁻¹ = f_{1/k}`` (both models). k > 0."""
    k = jnp.asarray(k)
    return f_k(theta, safe_div(1.0, k, fill=0.0), model)


def srf_jacobian(
    theta: Float[ArrayLike, "..."], k: Float[ArrayLike, "..."], model: str = "paper"
) -> Float[Array, "..."]:
    """The paper's SRF factor ``f_k'(θ) · sin f_k(θ) / sin θ`` (Appendix A), broadcast over θ, k.

    It is the solid-angle Jacobian of the map θ ↦ f_k(θ): ``∫ V(f_k(θ)) J(θ) dω = ∫ V dω``. For the
    paper's model it simplifies to ``k² / ρ³`` (ρ as in the module docstring), which is smooth on
    [0, π] (``k²`` at θ = 0 and at θ = π). For the sphere model it is ``k² cos θ / cos g_k``
    on the asin segment (an integrable singularity at θ_a when k > 1; the value there is 0 by
    construction) and ``slope · sin g_k / sin θ`` on the linear segment (``slope²`` at θ = π).

    Multiplying rescaled *radiance* by this factor keeps the radiant energy ∫ L dω constant, so a
    light does not dim with distance: it reproduces the paper only (DESIGN.md §1.3).
    """
    _check_model(model)
    theta, k = jnp.asarray(theta), jnp.asarray(k)
    s, c = _sin_cos(theta)
    if model == "paper":
        x = c + (1.0 - k) * s
        rho2 = (k * s) ** 2 + x * x
        return safe_div(k * k, rho2 * safe_sqrt(rho2))
    theta_a, g_a = _sphere_knots(k)
    on_asin = theta <= theta_a
    s1 = jnp.where(on_asin, s, 0.0)
    ks = jnp.clip(k * s1, -1.0, 1.0)
    j1 = safe_div(k * k * c, safe_sqrt(1.0 - ks * ks))
    slope = (math.pi - g_a) / (math.pi - theta_a)
    u = jnp.where(on_asin, 0.5 * math.pi, math.pi - theta)  # π − θ on the linear segment
    near_pi = u < 1e-3
    u_safe = jnp.where(near_pi, 1.0, u)  # double where: sin g / sin θ = sin(slope·u)/sin(u) → slope
    ratio = jnp.where(near_pi, slope, jnp.sin(slope * u_safe) / jnp.sin(u_safe))
    return jnp.where(on_asin, j1, slope * ratio)


# ---- float64 numpy versions, used to build M_k tables outside any JAX trace ------------------------


def _np_knots(k: float) -> tuple[float, float]:
    if k <= 1.0:
        return 0.5 * math.pi, math.asin(k)
    return math.asin(1.0 / k), 0.5 * math.pi


def _np_map(theta: np.ndarray, k: float, model: str) -> np.ndarray:
    """float64 f_k(θ) for one k (numpy)."""
    s, c = np.sin(theta), np.cos(theta)
    s = np.where(theta > 0.5 * math.pi, np.sin(math.pi - theta), s)
    if model == "paper":
        return np.arctan2(k * s, c + (1.0 - k) * s)
    ta, ga = _np_knots(k)
    g1 = np.arcsin(np.clip(k * s, -1.0, 1.0))
    g2 = ga + (theta - ta) * (math.pi - ga) / (math.pi - ta)
    return np.where(theta <= ta, g1, g2)


def _np_jacobian(theta: np.ndarray, k: float, model: str) -> np.ndarray:
    """float64 f_k'(θ)·sin f_k(θ)/sin θ for one k (numpy); 0 at an integrable singular point."""
    s, c = np.sin(theta), np.cos(theta)
    s = np.where(theta > 0.5 * math.pi, np.sin(math.pi - theta), s)
    if model == "paper":
        rho2 = (k * s) ** 2 + (c + (1.0 - k) * s) ** 2
        return k * k / rho2**1.5
    ta, ga = _np_knots(k)
    slope = (math.pi - ga) / (math.pi - ta)
    with np.errstate(divide="ignore", invalid="ignore"):
        den = np.sqrt(np.clip(1.0 - (k * s) ** 2, 0.0, None))
        j1 = np.where(den > 0, k * k * c / np.where(den > 0, den, 1.0), 0.0)
        u = np.clip(math.pi - theta, 1e-300, None)
        ratio = np.where(u < 1e-8, slope, np.sin(slope * u) / np.sin(u))
    return np.where(theta <= ta, j1, slope * ratio)
