"""Real, orthonormal spherical harmonics.

Convention (used everywhere in jshadow)
---------------------------------------
* Coefficient index ``i = l² + l + m`` for band ``l = 0..n-1`` and ``-l <= m <= l``; n bands give n²
  coefficients (default n = 4 -> 16).
* Polar axis is +z of whatever frame the directions are given in: ``cos θ = z``,
  ``φ = atan2(y, x)``. (The *world* is y-up, but the SH basis is defined on raw (x, y, z) components;
  a world-frame SH vector simply uses world xyz.)
* No Condon–Shortley phase::

      Y_l0  = K_l0 P_l(cos θ)
      Y_lm  = √2 K_lm P_l^m(cos θ) cos(mφ)      (m > 0)
      Y_l-m = √2 K_lm P_l^m(cos θ) sin(mφ)      (m > 0)
      K_lm  = sqrt((2l+1)/(4π) · (l-m)!/(l+m)!)

  so band 1 is ``(Y_1-1, Y_10, Y_11) = sqrt(3/4π) · (y, z, x)``.

Everything is evaluated as polynomials in (x, y, z): ``sin^m θ cos(mφ) = Re (x+iy)^m`` and
``P_l^m / sin^m θ`` is a polynomial in z. There is no atan2, acos or division, so values and
gradients are finite at the poles and along the axes. The Python loops run at trace time, so a
jitted call is one fused closed-form polynomial per coefficient.
"""

from __future__ import annotations

import math
from functools import partial

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

__all__ = ["num_coeffs", "sh_index", "sh_lm", "sh_basis", "sh_eval", "sh_basis_spherical", "sh_bands_of"]


def num_coeffs(n: int) -> int:
    """Number of coefficients of n bands: n²."""
    return n * n


def sh_index(l: int, m: int) -> int:
    """Flat index of (l, m): l² + l + m."""
    if not (l >= 0 and -l <= m <= l):
        raise ValueError(f"invalid SH index (l={l}, m={m}); need l >= 0 and -l <= m <= l")
    return l * l + l + m


def sh_lm(i: int) -> tuple[int, int]:
    """Inverse of :func:`sh_index`."""
    l = math.isqrt(i)
    return l, i - l * l - l


def sh_bands_of(n2: int) -> int:
    """Number of bands n of a coefficient vector of length n²; raises if n2 is not a square."""
    n = math.isqrt(n2)
    if n * n != n2 or n < 1:
        raise ValueError(f"SH coefficient axis has length {n2}, which is not a square n² (n >= 1)")
    return n


def _k(l: int, m: int) -> float:
    return math.sqrt((2 * l + 1) / (4 * math.pi) * math.factorial(l - m) / math.factorial(l + m))


def _basis_list(x, y, z, n: int) -> list:
    """The n² basis functions as a list of arrays (trace-time unrolled recurrences)."""
    # C_m + i S_m = (x + i y)^m   (= sin^m θ · e^{imφ})
    cs = [(jnp.ones_like(x), jnp.zeros_like(x))]
    for _ in range(1, n):
        c, s = cs[-1]
        cs.append((x * c - y * s, x * s + y * c))
    out = [None] * (n * n)
    for m in range(n):
        # Q_l^m(z) = P_l^m(z) / sin^m θ, without the Condon–Shortley phase.
        q_prev2 = None
        q_prev = jnp.full_like(z, float(math.prod(range(2 * m - 1, 0, -2))))  # (2m-1)!!
        for l in range(m, n):
            if l == m:
                q = q_prev
            elif l == m + 1:
                q = z * (2 * m + 1) * q_prev
            else:
                q = ((2 * l - 1) * z * q_prev - (l + m - 1) * q_prev2) / (l - m)
            if l > m:
                q_prev2, q_prev = q_prev, q
            if m == 0:
                out[l * l + l] = _k(l, 0) * q
            else:
                a = math.sqrt(2.0) * _k(l, m)
                c, s = cs[m]
                out[l * l + l + m] = a * q * c
                out[l * l + l - m] = a * q * s
    return out


@partial(jax.jit, static_argnames=("n",))
def sh_basis(dirs: Float[ArrayLike, "... 3"], n: int = 4) -> Float[Array, "... n2"]:
    """Real orthonormal SH basis at unit directions.

    Args:
        dirs: (..., 3) unit vectors (not renormalised: pass unit vectors).
        n: number of bands (>= 1).

    Returns:
        (..., n²) basis values, index ``l² + l + m``.
    """
    if n < 1:
        raise ValueError(f"n (number of SH bands) must be >= 1, got {n}")
    dirs = jnp.asarray(dirs)
    if dirs.shape[-1:] != (3,):
        raise ValueError(f"dirs must have a trailing axis of length 3, got shape {dirs.shape}")
    x, y, z = dirs[..., 0], dirs[..., 1], dirs[..., 2]
    return jnp.stack(_basis_list(x, y, z, n), axis=-1)


@jax.jit
def sh_eval(coeffs: Float[ArrayLike, "... n2"], dirs: Float[ArrayLike, "... 3"]) -> Float[Array, "..."]:
    """Evaluate Σ_i c_i Y_i(ω) without forming the (..., n²) basis array.

    Args:
        coeffs: (..., n²) coefficients; broadcast against the batch axes of ``dirs``.
        dirs: (..., 3) unit directions.

    Returns:
        (...) function values.
    """
    coeffs, dirs = jnp.asarray(coeffs), jnp.asarray(dirs)
    n = sh_bands_of(coeffs.shape[-1])
    ys = _basis_list(dirs[..., 0], dirs[..., 1], dirs[..., 2], n)
    acc = coeffs[..., 0] * ys[0]
    for i in range(1, n * n):
        acc = acc + coeffs[..., i] * ys[i]
    return acc


def sh_basis_spherical(
    theta: Float[ArrayLike, "..."], phi: Float[ArrayLike, "..."], n: int = 4
) -> Float[Array, "... n2"]:
    """SH basis at spherical angles (θ from +z, φ from +x toward +y), radians."""
    theta, phi = jnp.asarray(theta), jnp.asarray(phi)
    st = jnp.sin(theta)
    d = jnp.stack([st * jnp.cos(phi), st * jnp.sin(phi), jnp.cos(theta)], axis=-1)
    return sh_basis(d, n)
