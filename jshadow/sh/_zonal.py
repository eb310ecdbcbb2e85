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
from functools import partial

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._basis import sh_basis

__all__ = ["zonal_cap", "zonal_clamped_cosine", "zonal_rotate", "cap", "clamped_cosine"]


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


@partial(jax.jit, static_argnames=("n",))
def zonal_cap(cos_alpha: Float[ArrayLike, "..."], n: int) -> Float[Array, "... n"]:
    """Zonal coefficients of the indicator of the cap ``{ω : ω·ẑ >= cos α}``.

    Args:
        cos_alpha: (...) cosine of the cap's angular radius, in [−1, 1] (−1: whole sphere, 1: empty).
        n: number of SH bands.

    Returns:
        (..., n) coefficients ``z_l = sqrt(π/(2l+1)) (P_{l-1}(t) − P_{l+1}(t))``; a polynomial in t,
        so finite with finite gradients at t = ±1.
    """
    n = _check_n(n)
    t = jnp.asarray(cos_alpha)
    if not jnp.issubdtype(t.dtype, jnp.floating):
        raise ValueError(f"cos_alpha must be a floating-point array, got dtype {t.dtype}")
    p = _legendre_list(t, n + 1)
    out = [math.sqrt(math.pi) * (1.0 - t)]
    for l in range(1, n):
        out.append(math.sqrt(math.pi / (2 * l + 1)) * (p[l - 1] - p[l + 1]))
    return jnp.stack(out, axis=-1)


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
