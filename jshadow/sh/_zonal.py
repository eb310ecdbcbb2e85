"""Zonal harmonics: spherical caps, the clamped cosine, and rotating a zonal function to an axis.

A zonal function about +z, ``f(ω) = g(ω·ẑ)``, has only m = 0 coefficients; we call them its
*zonal coefficients* ``z_l = ∫ f Y_l0 dω`` (l = 0..n-1). The same profile about a unit axis ``a``
has the SH coefficients (addition theorem)

    c_lm = sqrt(4π / (2l+1)) · z_l · Y_lm(a).

Closed forms, with ``t = cos α`` and the Legendre polynomials P_l (``P_{-1} := 1``):

* cap indicator ``1[ω·ẑ >= t]``: ``z_l = sqrt(π / (2l+1)) · (P_{l-1}(t) − P_{l+1}(t))`` (from
  ``∫_t^1 P_l = (P_{l-1}(t) − P_{l+1}(t)) / (2l+1)``); this gives ``z_0 = sqrt(π)(1 − t)``.
* clamped cosine ``max(0, ω·ẑ)``: ``z_l = 2π K_l0 ∫_0^1 x P_l(x) dx`` with
  ``K_l0 = sqrt((2l+1)/4π)``: ``z_0 = sqrt(π)/2``, ``z_1 = sqrt(π/3)``, odd l >= 3 vanish.

A spherical light of angular radius α seen from a receiver is a cap (Zhou et al. 2005 represent
source radiance the same way); the clamped cosine is a diffuse receiver's transfer. Everything is a
polynomial in t and in the axis components, so values and gradients are finite at ``t = ±1`` and
for axes along ±x, ±y, ±z. ``cos_alpha`` is not clipped: pass values in [−1, 1].
"""

from __future__ import annotations

import math
from functools import lru_cache, partial

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._basis import _basis_list, sh_basis

__all__ = [
    "zonal_cap",
    "zonal_cap_versine",
    "zonal_clamped_cosine",
    "zonal_rotate",
    "zonal_dot",
    "cap",
    "clamped_cosine",
]


def _check_n(n) -> int:
    if int(n) != n or n < 1:
        raise ValueError(f"n (number of SH bands) must be a positive integer, got {n}")
    return int(n)


def _legendre_list(t: Array, n: int) -> list[Array]:
    """[P_0(t), ..., P_{n-1}(t)] by Bonnet's recurrence (n >= 1)."""
    p = [jnp.ones_like(t), t]
    for l in range(1, n - 1):
        p.append(((2 * l + 1) * t * p[l] - l * p[l - 1]) / (l + 1))
    return p[:n]


# Near t = 1 (small caps) P_{l-1}(t) − P_{l+1}(t) cancels; there the coefficients are evaluated as
# polynomials in the versine u = 1 − t, whose constant terms vanish exactly. The switch is at
# t = 0.9 (u <= 0.1): below it the Bonnet recurrence is accurate, above it the u-series is.
_SERIES_FROM_T = 0.9


@lru_cache(maxsize=32)
def _versine_coeffs(n: int) -> tuple[tuple[int, ...], ...]:
    """Integer coefficients d_{l,k} of P_{l-1}(1−u) − P_{l+1}(1−u) = Σ_{k>=1} d_{l,k} (u/2)^k.

    From P_m(1−u) = Σ_k (−1)^k C(m,k) C(m+k,k) (u/2)^k; index 0 of each tuple is k = 1.
    """

    def c(m: int, k: int) -> int:
        return (-1) ** k * math.comb(m, k) * math.comb(m + k, k) if k <= m else 0

    return tuple(tuple(c(l - 1, k) - c(l + 1, k) for k in range(1, l + 2)) for l in range(1, n))


def _cap_from_versine(u: Array, n: int) -> list[Array]:
    s = 0.5 * u
    out = [math.sqrt(math.pi) * u]
    for l, d in enumerate(_versine_coeffs(n), start=1):
        acc = jnp.full_like(s, float(d[-1]))
        for dk in reversed(d[:-1]):  # Horner in s, then the common factor s (k >= 1)
            acc = acc * s + float(dk)
        out.append(math.sqrt(math.pi / (2 * l + 1)) * (acc * s))
    return out


def _check_float(name: str, x: Array) -> None:
    if not jnp.issubdtype(x.dtype, jnp.floating):
        raise ValueError(f"{name} must be a floating-point array, got dtype {x.dtype}")


@partial(jax.jit, static_argnames=("n",))
def zonal_cap(cos_alpha: Float[ArrayLike, "..."], n: int) -> Float[Array, "... n"]:
    """Zonal coefficients of the indicator of the cap ``{ω : ω·ẑ >= cos α}``.

    Args:
        cos_alpha: (...) cosine of the cap's angular radius, in [−1, 1] (−1: whole sphere, 1: empty).
        n: number of SH bands.

    Returns:
        (..., n) coefficients ``z_l = sqrt(π/(2l+1)) (P_{l-1}(t) − P_{l+1}(t))``. For t >= 0.9 they
        are evaluated as polynomials in ``u = 1 − t`` (exact subtraction there), which avoids the
        cancellation of the Legendre difference for small caps: in float32 the relative error stays
        about 1e-7 down to α = 0.003 (the recurrence alone gives 1e-2 there). Piecewise polynomial,
        so finite with finite gradients everywhere, including t = ±1. If you have ``1 − cos α``
        more accurately than cos α (tiny caps), call :func:`zonal_cap_versine`.
    """
    n = _check_n(n)
    t = jnp.asarray(cos_alpha)
    _check_float("cos_alpha", t)
    p = _legendre_list(t, n + 1)
    rec = [math.sqrt(math.pi) * (1.0 - t)]
    for l in range(1, n):
        rec.append(math.sqrt(math.pi / (2 * l + 1)) * (p[l - 1] - p[l + 1]))
    ser = _cap_from_versine(1.0 - t, n)
    near_one = (t >= _SERIES_FROM_T)[..., None]  # both branches are finite polynomials
    return jnp.where(near_one, jnp.stack(ser, axis=-1), jnp.stack(rec, axis=-1))


@partial(jax.jit, static_argnames=("n",))
def zonal_cap_versine(one_minus_cos_alpha: Float[ArrayLike, "..."], n: int) -> Float[Array, "... n"]:
    """:func:`zonal_cap` from the versine ``u = 1 − cos α`` (...), accurate for tiny caps.

    For a sphere of radius r at distance d, ``u = s² / (1 + sqrt(1 − s²))`` with s = r/d is exact
    in floating point where ``1 − sqrt(1 − s²)`` is not. Uses the u-series for u <= 0.1 and the
    Legendre recurrence at t = 1 − u beyond. Returns (..., n).
    """
    n = _check_n(n)
    u = jnp.asarray(one_minus_cos_alpha)
    _check_float("one_minus_cos_alpha", u)
    t = 1.0 - u
    p = _legendre_list(t, n + 1)
    rec = [math.sqrt(math.pi) * u]
    for l in range(1, n):
        rec.append(math.sqrt(math.pi / (2 * l + 1)) * (p[l - 1] - p[l + 1]))
    ser = _cap_from_versine(u, n)
    small = (u <= 1.0 - _SERIES_FROM_T)[..., None]
    return jnp.where(small, jnp.stack(ser, axis=-1), jnp.stack(rec, axis=-1))


def _clamped_cosine_values(n: int) -> list[float]:
    # ∫_0^1 P_l = (P_{l-1}(0) − P_{l+1}(0)) / (2l+1) for l >= 1, and
    # x P_l = ((l+1) P_{l+1} + l P_{l-1}) / (2l+1).
    p0 = [1.0, 0.0]
    for l in range(1, n + 1):
        p0.append(-l * p0[l - 1] / (l + 1))  # P_{l+1}(0) = −l/(l+1) · P_{l-1}(0)

    def int_p(l: int) -> float:  # ∫_0^1 P_l(x) dx
        return 1.0 if l == 0 else (p0[l - 1] - p0[l + 1]) / (2 * l + 1)

    out = []
    for l in range(n):
        int_xp = ((l + 1) * int_p(l + 1) + (l * int_p(l - 1) if l > 0 else 0.0)) / (2 * l + 1)
        out.append(2.0 * math.pi * math.sqrt((2 * l + 1) / (4 * math.pi)) * int_xp)
    return out


def zonal_clamped_cosine(n: int, dtype=None) -> Float[Array, " n"]:
    """Zonal coefficients (n,) of ``max(0, cos θ)``: sqrt(π)/2, sqrt(π/3), sqrt(5π)/8, 0, ...

    Odd bands l >= 3 are zero and even bands decay slowly; truncating to n bands is the usual
    low-frequency approximation of the diffuse transfer. ``dtype`` defaults to JAX's default float.
    """
    n = _check_n(n)
    dt = jnp.result_type(float) if dtype is None else jnp.dtype(dtype)
    return jnp.asarray(_clamped_cosine_values(n), dtype=dt)


@jax.jit
def zonal_rotate(z: Float[ArrayLike, "... n"], axis: Float[ArrayLike, "... 3"]) -> Float[Array, "... n2"]:
    """SH coefficients of the zonal function with zonal coefficients z about ``axis``.

    Args:
        z: (..., n) zonal coefficients (about +z).
        axis: (..., 3) unit axes (not renormalised); batch axes broadcast against those of z.

    Returns:
        (..., n²) coefficients ``c_lm = sqrt(4π/(2l+1)) z_l Y_lm(axis)``.
    """
    z, axis = jnp.asarray(z), jnp.asarray(axis)
    if z.ndim < 1:
        raise ValueError("z must have shape (..., n), got a scalar")
    if not (jnp.issubdtype(z.dtype, jnp.floating) and jnp.issubdtype(axis.dtype, jnp.floating)):
        raise ValueError(f"z and axis must be floating-point arrays, got {z.dtype} and {axis.dtype}")
    n = z.shape[-1]
    y = sh_basis(axis, n)  # validates axis' trailing length
    per_band = [math.sqrt(4.0 * math.pi / (2 * l + 1)) * z[..., l : l + 1] for l in range(n)]
    scale = jnp.concatenate(
        [jnp.broadcast_to(s, (*s.shape[:-1], 2 * l + 1)) for l, s in enumerate(per_band)], axis=-1
    )
    return scale * y


def zonal_dot(
    z: Float[ArrayLike, "... n"], axis: Float[ArrayLike, "... 3"], w: Float[ArrayLike, "... n2"]
) -> Float[Array, "..."]:
    """Inner product ``Σ_lm c_lm w_lm`` of :func:`zonal_rotate` ``(z, axis)`` with coefficients w.

    Args:
        z: (..., n) zonal coefficients (about +z).
        axis: (..., 3) unit axes (not renormalised).
        w: (..., n²) coefficients; the batch axes of all three broadcast against each other.

    Returns:
        (...) ``Σ_l sqrt(4π/(2l+1)) z_l Σ_m w_lm Y_lm(axis)``.

    The same number as ``jnp.sum(zonal_rotate(z, axis) * w, -1)``, but written as one polynomial
    per element, so that XLA evaluates it in a single fused pass without the (..., n²) rotated
    coefficients (or the basis) ever stored: on XLA:CPU the basis of 16384 axes alone is 16
    per-coefficient passes and a concatenation (BENCHMARKS.md, "Rendering").
    """
    z, axis, w = jnp.asarray(z), jnp.asarray(axis), jnp.asarray(w)
    if z.ndim < 1 or axis.shape[-1:] != (3,):
        raise ValueError(f"need z (..., n) and axis (..., 3), got shapes {z.shape} and {axis.shape}")
    n = z.shape[-1]
    if w.shape[-1:] != (n * n,):
        raise ValueError(f"w must have a trailing axis of n² = {n * n} for n = {n} bands, got {w.shape}")
    ys = _basis_list(axis[..., 0], axis[..., 1], axis[..., 2], n)
    acc = None
    for l in range(n):
        band = sum(w[..., i] * ys[i] for i in range(l * l, (l + 1) * (l + 1)))
        term = (math.sqrt(4.0 * math.pi / (2 * l + 1)) * z[..., l]) * band
        acc = term if acc is None else acc + term
    return acc


def cap(
    axis: Float[ArrayLike, "... 3"], cos_alpha: Float[ArrayLike, "..."], n: int
) -> Float[Array, "... n2"]:
    """SH coefficients (..., n²) of the indicator of the cap ``{ω : ω·axis >= cos α}``.

    ``axis`` (..., 3) unit vectors and ``cos_alpha`` (...) broadcast against each other.
    """
    axis = jnp.asarray(axis)
    if isinstance(cos_alpha, int | float):  # a Python number takes the axes' dtype
        cos_alpha = jnp.asarray(cos_alpha, dtype=axis.dtype)
    return zonal_rotate(zonal_cap(cos_alpha, n), axis)


def clamped_cosine(normal: Float[ArrayLike, "... 3"], n: int) -> Float[Array, "... n2"]:
    """SH coefficients (..., n²) of ``max(0, ω·normal)`` for unit normals (..., 3)."""
    normal = jnp.asarray(normal)
    return zonal_rotate(zonal_clamped_cosine(n, normal.dtype), normal)
