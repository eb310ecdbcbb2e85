"""Rotation of real SH coefficient vectors.

Convention: if ``g(ω) = f(Rᵀ ω)`` (the function f carried along by the rotation R, so a feature of
f at direction ω₀ appears in g at ``R ω₀``), then ``coeffs(g) = D(R) @ coeffs(f)``. D is
block-diagonal, one (2l+1)×(2l+1) orthogonal block per band, and ``D(R₁ R₂) = D(R₁) D(R₂)``,
``D(Rᵀ) = D(R)ᵀ``.

Method ("fitting at fixed directions"): for every band, ``Y_l(Rᵀ ω) = D_lᵀ Y_l(ω)`` holds for all
ω. Evaluating it at K = 3n fixed, well-spread directions ω_k (a Fibonacci set; the band matrices
``B_l[k, m] = Y_lm(ω_k)`` have condition numbers below 9 for n <= 12) gives ``A_l = B_l D_l`` with
``A_l[k, j] = Y_lj(Rᵀ ω_k)``, hence ``D_l = B_l⁺ A_l`` with the pseudo-inverse ``B_l⁺`` precomputed in
float64. This is exact (the system is consistent; no sampling error), costs one basis evaluation
at K rotated directions plus one small matrix product per band, and is a polynomial in the entries
of R: values and gradients are finite for every R (poles, axes, R = I). Band 0 is 1 and band 1 is
the permutation ``P R Pᵀ`` of R, since ``Y_1 ∝ (y, z, x)``.

If R is not orthogonal the result is still defined (the same polynomial), but it is a rotation
matrix only for orthogonal R.
"""

from __future__ import annotations

from functools import lru_cache, partial

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._basis import sh_bands_of, sh_basis
from ._grids import _np_sh_basis

__all__ = ["rotation_matrix", "rotate"]

_PERM = (1, 2, 0)  # band 1 order (Y_1-1, Y_10, Y_11) ∝ (y, z, x)


@lru_cache(maxsize=32)
def _fit_tables(n: int) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """float64 fitting directions (K, 3) and per-band pseudo-inverses B_l⁺ (2l+1, K), l = 0..n-1."""
    k = 3 * n
    i = np.arange(k) + 0.5
    z = 1.0 - 2.0 * i / k
    phi = np.pi * (1.0 + np.sqrt(5.0)) * i  # golden-angle spiral
    s = np.sqrt(1.0 - z * z)
    w = np.stack([s * np.cos(phi), s * np.sin(phi), z], -1)
    b = _np_sh_basis(w, n)
    pinvs = tuple(np.linalg.pinv(b[:, l * l : (l + 1) ** 2]) for l in range(n))
    return w, pinvs


def _check_rot(R: Array) -> None:
    if R.ndim < 2 or R.shape[-2:] != (3, 3):
        raise ValueError(f"R must have shape (..., 3, 3), got {R.shape}")
    if not jnp.issubdtype(R.dtype, jnp.floating):
        raise ValueError(f"R must be a floating-point array, got dtype {R.dtype}")


def _band1(R: Array) -> Array:
    """D_1 = P R Pᵀ: D_1[a, b] = R[p(a), p(b)]."""
    p = jnp.asarray(_PERM)
    return R[..., p[:, None], p[None, :]]


def _rotated_basis(R: Array, n: int) -> Array:
    """A[..., k, j] = Y_j(Rᵀ ω_k) at the fitting directions, (..., K, n²)."""
    w, _ = _fit_tables(n)
    rw = jnp.einsum("...ba,kb->...ka", R, jnp.asarray(w, dtype=R.dtype))  # Rᵀ ω_k
    return sh_basis(rw, n)


def _band_blocks(R: Array, n: int) -> list[Array]:
    """The diagonal blocks D_l (..., 2l+1, 2l+1), l = 0..n-1."""
    blocks = [jnp.ones((*R.shape[:-2], 1, 1), R.dtype)]
    if n > 1:
        blocks.append(_band1(R))
    if n > 2:
        a = _rotated_basis(R, n)
        _, pinvs = _fit_tables(n)
        for l in range(2, n):
            pl = jnp.asarray(pinvs[l], dtype=R.dtype)
            blocks.append(jnp.einsum("ik,...kj->...ij", pl, a[..., l * l : (l + 1) ** 2]))
    return blocks


@partial(jax.jit, static_argnames=("n",))
def rotation_matrix(R: Float[ArrayLike, "... 3 3"], n: int) -> Float[Array, "... n2 n2"]:
    """SH rotation matrix D(R) of n bands (block-diagonal per band).

    Args:
        R: (..., 3, 3) rotation matrices (orthogonal, det +1).
        n: number of SH bands (>= 1).

    Returns:
        (..., n², n²) matrices with ``coeffs(f ∘ Rᵀ) = D(R) @ coeffs(f)``. Exact (no sampling
        error) for any n; see the module docstring for the method. Use :func:`rotate` to apply a
        rotation without forming D.
    """
    if int(n) != n or n < 1:
        raise ValueError(f"n (number of SH bands) must be a positive integer, got {n}")
    R = jnp.asarray(R)
    _check_rot(R)
    blocks = _band_blocks(R, n)
    batch = R.shape[:-2]
    rows = []
    for l, blk in enumerate(blocks):
        left = jnp.zeros((*batch, 2 * l + 1, l * l), R.dtype)
        right = jnp.zeros((*batch, 2 * l + 1, n * n - (l + 1) ** 2), R.dtype)
        rows.append(jnp.concatenate([left, blk, right], axis=-1))
    return jnp.concatenate(rows, axis=-2)


@jax.jit
def rotate(coeffs: Float[ArrayLike, "... n2"], R: Float[ArrayLike, "... 3 3"]) -> Float[Array, "... n2"]:
    """Rotate SH coefficients: ``coeffs(f ∘ Rᵀ) = D(R) @ coeffs``, without forming D.

    Args:
        coeffs: (..., n²) coefficients of f.
        R: (..., 3, 3) rotation matrices; batch axes broadcast against those of ``coeffs``.

    Returns:
        (..., n²) coefficients of the rotated function. For bands l >= 2 this evaluates the band-l
        part of f at the K rotated fitting directions and applies ``B_l⁺`` (same method as
        :func:`rotation_matrix`).
    """
    coeffs, R = jnp.asarray(coeffs), jnp.asarray(R)
    _check_rot(R)
    n = sh_bands_of(coeffs.shape[-1])
    out = [coeffs[..., :1] + jnp.zeros(R.shape[:-2] + (1,), R.dtype)]
    if n > 1:
        out.append(jnp.einsum("...ij,...j->...i", _band1(R), coeffs[..., 1:4]))
    if n > 2:
        a = _rotated_basis(R, n)  # (..., K, n²)
        _, pinvs = _fit_tables(n)
        for l in range(2, n):
            sl = slice(l * l, (l + 1) ** 2)
            f_k = jnp.einsum("...kj,...j->...k", a[..., sl], coeffs[..., sl])  # f_l(Rᵀ ω_k)
            out.append(jnp.einsum("ik,...k->...i", jnp.asarray(pinvs[l], dtype=R.dtype), f_k))
    return jnp.concatenate(out, axis=-1)
