"""SH triple products (real Gaunt coefficients).

The product of two functions with coefficients a and b, projected back onto n_out bands, is

    (a ⊛ b)_i = Σ_jk G[i, j, k] a_j b_k,     G[i, j, k] = ∫_S² Y_i Y_j Y_k dω,

the operation shadow fields use to multiply the visibilities of occluders into a light's radiance
(Zhou et al. 2005, "Precomputed shadow fields for dynamic scenes", §5; the deformable-shadow-fields
paper reuses it). G is sparse (selection rules: |l_j − l_k| <= l_i <= l_j + l_k, l_i + l_j + l_k
even, and a sign/|m| rule for real harmonics), symmetric in all three indices, and independent of
the data: it is computed once per (n, n_out) by an exact Gauss–Legendre × uniform-φ quadrature in
float64 and cached.

Truncation: the exact product of two n-band functions has 2n − 1 bands; ``n_out < 2n − 1`` drops
the rest (the usual SH triple-product approximation), ``n_out = 2n − 1`` is exact.
"""

from __future__ import annotations

from functools import lru_cache, partial

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._basis import sh_bands_of
from ._grids import _np_sh_basis, _np_sphere_grid

__all__ = ["gaunt_tensor", "sh_product", "sh_product_t", "product_matrix"]

# full float32 accuracy on accelerators too (no TF32/bf16 passes in these small products)
_HIGHEST = jax.lax.Precision.HIGHEST


def _check_bands(n: int, n_out: int | None) -> tuple[int, int]:
    n_out = n if n_out is None else n_out
    if int(n) != n or n < 1 or int(n_out) != n_out or n_out < 1:
        raise ValueError(f"band counts must be positive integers, got n={n}, n_out={n_out}")
    return int(n), int(n_out)


@lru_cache(maxsize=32)
def _gaunt(n: int, n_out: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    deg = (n_out - 1) + 2 * (n - 1)  # polynomial degree of Y_i Y_j Y_k
    dirs, w = _np_sphere_grid(deg // 2 + 1, deg + 1)
    y = _np_sh_basis(dirs, max(n, n_out))
    yi, yj = y[:, : n_out * n_out], y[:, : n * n]
    g = np.einsum("q,qi,qj,qk->ijk", w, yi, yj, yj)
    tol = 1e-12 * float(np.abs(g).max())
    i, j, k = np.nonzero(np.abs(g) > tol)
    vals = g[i, j, k]
    out = (i.astype(np.int32), j.astype(np.int32), k.astype(np.int32), vals)
    for arr in out:
        arr.setflags(write=False)
    return out


def gaunt_tensor(n: int, n_out: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Non-zero real Gaunt coefficients ``G[i, j, k] = ∫ Y_i Y_j Y_k dω`` as sparse triplets.

    Args:
        n: bands of the two factors (j, k run over n² coefficients).
        n_out: bands of the output (i runs over n_out² coefficients); default n.

    Returns:
        ``(i, j, k, values)``: int32 index arrays and float64 values (numpy, read-only), sorted by
        (i, j, k); entries with ``|G| <= 1e-12 · max|G|`` are dropped. n = n_out = 4 has 353
        non-zeros out of 4096. Cached per (n, n_out); computed outside any JAX trace.
    """
    return _gaunt(*_check_bands(n, n_out))


@lru_cache(maxsize=32)
def _product_terms(n: int, n_out: int) -> tuple[tuple[tuple[float, int, int], ...], ...]:
    """Per output i: (G[i, j, k], j, k) with j <= k; the pair (k, j) is merged into the same term."""
    i, j, k, v = _gaunt(n, n_out)
    terms: list[list[tuple[float, int, int]]] = [[] for _ in range(n_out * n_out)]
    for ii, jj, kk, vv in zip(i.tolist(), j.tolist(), k.tolist(), v.tolist()):
        if jj <= kk:
            terms[ii].append((vv, jj, kk))
    return tuple(tuple(t) for t in terms)


def _check_coeffs(name: str, x: Array) -> int:
    if x.ndim < 1:
        raise ValueError(f"{name} must have shape (..., n²), got a scalar")
    return sh_bands_of(x.shape[-1])


@partial(jax.jit, static_argnames=("n_out",))
def sh_product(
    a: Float[ArrayLike, "... n2"], b: Float[ArrayLike, "... n2"], n_out: int | None = None
) -> Float[Array, "... m2"]:
    """Coefficients of the product of two SH-represented functions (triple product).

    Args:
        a, b: (..., n²) coefficients with the same n; batch axes broadcast.
        n_out: bands of the result (default n); ``2n − 1`` makes the product exact.

    Returns:
        (..., n_out²) coefficients ``Σ_jk G[i,j,k] a_j b_k``. Implemented as one unrolled sum over
        the non-zero Gaunt coefficients (symmetric pairs merged), which measured faster on CPU than
        a dense einsum or a gather/segment-sum (see ``benchmarks/bench_sh.py``). For chains of
        products over many receivers, :func:`sh_product_t` (coefficient axis first) is faster.
    """
    a, b = jnp.asarray(a), jnp.asarray(b)
    n = _check_coeffs("a", a)
    if _check_coeffs("b", b) != n:
        raise ValueError(f"a and b must have the same number of SH coefficients, got {a.shape} and {b.shape}")
    n, n_out = _check_bands(n, n_out)
    shape = jnp.broadcast_shapes(a.shape[:-1], b.shape[:-1])
    return jnp.stack(_product_sums(lambda j: a[..., j], lambda j: b[..., j], shape, a, b, n, n_out), axis=-1)


def sh_product_t(
    a: Float[ArrayLike, "n2 ..."], b: Float[ArrayLike, "n2 ..."], n_out: int | None = None
) -> Float[Array, "m2 ..."]:
    """:func:`sh_product` with the coefficient axis *first*: (n², ...) × (n², ...) → (n_out², ...).

    Each term then reads contiguous rows: 2–3× faster than :func:`sh_product` for 1e5 receivers on
    XLA:CPU (``benchmarks/bench_sh.py``), but converting to and from this layout costs about as
    much as it saves for a single product, so it pays off for chains (several occluders'
    visibilities multiplied in turn). Batch axes broadcast.
    """
    a, b = jnp.asarray(a), jnp.asarray(b)
    if a.ndim < 1 or b.ndim < 1:
        raise ValueError(f"a and b must have shape (n², ...), got {a.shape} and {b.shape}")
    n = sh_bands_of(a.shape[0])
    if b.shape[0] != a.shape[0]:
        raise ValueError(f"a and b must have as many SH coefficients on axis 0, got {a.shape}, {b.shape}")
    n, n_out = _check_bands(n, n_out)
    return _product_rows(a, b, n, n_out)


def _product_rows(a: Array, b: Array, n: int, n_out: int) -> Array:
    shape = jnp.broadcast_shapes(a.shape[1:], b.shape[1:])
    return jnp.stack(_product_sums(lambda j: a[j], lambda j: b[j], shape, a, b, n, n_out), axis=0)


def _product_sums(a_at, b_at, shape, a, b, n: int, n_out: int) -> list:
    """The n_out² sums ``Σ_jk G[i,j,k] a_j b_k`` (symmetric pairs merged); ``a_at(j)`` is coefficient j."""
    zero = jnp.zeros(shape, jnp.result_type(a, b))
    out = []
    for terms in _product_terms(n, n_out):
        acc = zero
        for v, j, k in terms:
            if j == k:
                acc = acc + v * (a_at(j) * b_at(j))
            else:
                acc = acc + v * (a_at(j) * b_at(k) + a_at(k) * b_at(j))
        out.append(acc)
    return out


def _sh_product_dense(a: Array, b: Array, n_out: int | None = None) -> Array:
    """Reference: dense einsum with the full Gaunt tensor (for tests and benchmarks)."""
    n, n_out = _check_bands(sh_bands_of(a.shape[-1]), n_out)
    i, j, k, v = _gaunt(n, n_out)
    g = np.zeros((n_out * n_out, n * n, n * n))
    g[i, j, k] = v
    return jnp.einsum("ijk,...j,...k->...i", jnp.asarray(g, dtype=a.dtype), a, b, precision=_HIGHEST)


@partial(jax.jit, static_argnames=("n_out",))
def product_matrix(a: Float[ArrayLike, "... n2"], n_out: int | None = None) -> Float[Array, "... m2 n2"]:
    """Matrix of "multiply by a": ``product_matrix(a) @ b == sh_product(a, b, n_out)``.

    Args:
        a: (..., n²) coefficients.
        n_out: bands of the result (default n).

    Returns:
        (..., n_out², n²) matrices ``M[i, k] = Σ_j G[i, j, k] a_j``. Multiplying several occluders
        into one light is a chain of matrix–vector products with these. Computed as one dense
        matrix product of a with a constant (n², n_out²·n²) table (a plain GEMM; fast to compile).
    """
    a = jnp.asarray(a)
    n, n_out = _check_bands(_check_coeffs("a", a), n_out)
    s = _product_matrix_table(n, n_out)  # (n², n_out² · n²): row j holds G[:, j, :]
    m = jnp.matmul(a, jnp.asarray(s, dtype=a.dtype), precision=_HIGHEST)
    return m.reshape(*a.shape[:-1], n_out * n_out, n * n)


@lru_cache(maxsize=32)
def _product_matrix_table(n: int, n_out: int) -> np.ndarray:
    i, j, k, v = _gaunt(n, n_out)
    s = np.zeros((n * n, n_out * n_out * n * n))
    s[j, i * (n * n) + k] = v
    s.setflags(write=False)
    return s
