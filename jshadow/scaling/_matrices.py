"""Extrapolation matrices M_k of SH coefficients between radial distances, tabulated in k.

The deformable-shadow-fields paper (Sec. 4.2, Appendix B) extrapolates a function sampled on the
sampling shell (radius r) to distance d = r/k with a linear map of its SH coefficients:

    M_k[i, j] = ∫_S² Y_j(w(θ), φ) · Y_i(θ, φ) · J(θ) dω,        dω = sin θ dθ dφ,

with the warp ``w = f_{1/k} = f_k⁻¹`` (:mod:`jshadow.scaling._rescale`; the paper's Sec. 4.2
writes f_k and drops the sin θ: DESIGN.md §2) and, per ``kind``:

* ``"occlusion"`` (OOF) and ``"radiance"`` (SRF, plain warp): J = 1. A constant stays constant,
  so column 0 is e0 (``M e0 = e0``): unoccluded stays unoccluded and a radiance value is kept. The
  integral ∫ f dω of a non-constant function is *not* kept (row 0 is not e0ᵀ): a lit cap shrinks
  with distance, as it should. The two kinds have identical numbers; the kind records intent.
* ``"radiance_jacobian"``: J = the paper's Appendix A factor ``w'·sin w / sin θ``. Then row 0 is
  e0ᵀ: ∫ f dω is preserved exactly, and a constant does not stay constant (column 0 is not e0).
  A sphere light then does not dim with distance; kept only to reproduce the paper.

The φ integral is analytic (Y_j∘w keeps its φ-dependence), so only equal m couple, with the same
θ-block for m and −m: Σ_m (n − |m|)² *positions* (44 for n = 4; the paper's (q+1)(2q²+4q+3)/3
with q = n − 1), for every k. Of these, n − 1 are zero for every k (column 0 below the diagonal
for J = 1; row 0 right of the diagonal for the Jacobian kind), so a table stores Σ_m (n − |m|)² −
(n − 1) non-zero entries per k (41 for n = 4). The θ integral is computed in float64 numpy by
Gauss–Legendre quadrature on pieces split where w passes through multiples of π/16 and at the
kink of the sphere model, which resolves the fast variation of w for small k.
"""

from __future__ import annotations

import math
from functools import lru_cache

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._numerics import eps
from ..sh import sh_bands_of, sh_lm
from ._rescale import MODELS, _np_knots, _np_map

__all__ = [
    "KINDS",
    "MkTable",
    "mk_pattern",
    "mk_matrix",
    "mk_table",
    "mk_interpolate",
    "mk_apply",
    "mk_in_range",
]

KINDS = ("occlusion", "radiance", "radiance_jacobian")


def _check(n: int, kind: str, model: str) -> None:
    if int(n) != n or not 1 <= n <= 16:
        raise ValueError(f"n (number of SH bands) must be an integer in 1..16, got {n}")
    if kind not in KINDS:
        raise ValueError(f"M_k kind must be one of {KINDS}, got {kind!r}")
    if model not in MODELS:
        raise ValueError(f"rescaling model must be one of {MODELS}, got {model!r}")


def mk_pattern(n: int, kind: str | None = None) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """(rows, cols) of the entries of M_k that can be non-zero, row-major.

    With ``kind=None``: all equal-m positions, Σ_m (n − |m|)² of them (44 for n = 4). With a kind:
    the positions that are non-zero for k ≠ 1 (the structural zeros of column 0 or row 0 removed;
    41 for n = 4). The pattern does not depend on k or on the model.
    """
    if kind is not None:
        _check(n, kind, "paper")
    rows, cols = [], []
    for i in range(n * n):
        for j in range(n * n):
            if sh_lm(i)[1] != sh_lm(j)[1]:
                continue
            if kind in ("occlusion", "radiance") and j == 0 and i != 0:
                continue
            if kind == "radiance_jacobian" and i == 0 and j != 0:
                continue
            rows.append(i)
            cols.append(j)
    return tuple(rows), tuple(cols)


def _legendre_theta(x: np.ndarray, n: int) -> np.ndarray:
    """θ-parts y_lm (n, n, ...) with ∫_0^π y_lm y_l'm sin θ dθ = δ_ll' (index [m, l]); x = cos θ."""
    out = np.zeros((n, n, *x.shape))
    s = np.sqrt(np.clip(1.0 - x * x, 0.0, None))
    for m in range(n):
        p_mm = math.prod(range(2 * m - 1, 0, -2)) * s**m  # P_m^m without the Condon–Shortley phase
        p_prev2, p_prev = None, p_mm
        for l in range(m, n):
            if l == m:
                p = p_mm
            elif l == m + 1:
                p = x * (2 * m + 1) * p_mm
            else:
                p = ((2 * l - 1) * x * p_prev - (l + m - 1) * p_prev2) / (l - m)
            if l > m:
                p_prev2, p_prev = p_prev, p
            norm = math.sqrt((2 * l + 1) / 2.0 * math.factorial(l - m) / math.factorial(l + m))
            out[m, l] = norm * p
    return out


def _nodes(k: float, model: str, nodes: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Legendre nodes and weights on [0, π], split where f_{1/k} crosses jπ/16 and at its kink."""
    u = np.linspace(0.0, math.pi, 17)
    breaks = [*_np_map(u, k, model)]  # f_{1/k}(θ_b) = u_b  ⟺  θ_b = f_k(u_b)
    if model == "sphere":
        breaks.append(_np_knots(1.0 / k)[0])
    breaks = np.unique(np.clip(np.asarray(breaks), 0.0, math.pi))
    x, wq = np.polynomial.legendre.leggauss(nodes)
    th, wt = [], []
    for a, b in zip(breaks[:-1], breaks[1:]):
        if b - a <= 0.0:
            continue
        th.append(0.5 * (b - a) * x + 0.5 * (a + b))
        wt.append(0.5 * (b - a) * wq)
    return np.concatenate(th), np.concatenate(wt)


@lru_cache(maxsize=256)
def _blocks(k: float, n: int, kind: str, model: str, nodes: int) -> tuple[np.ndarray, ...]:
    """Per-m θ-blocks B_m[l, l'] (l, l' = m..n−1) of M_k in float64.

    J = 1: ``∫ y_l(θ) y_l'(w(θ)) sin θ dθ`` with w = f_{1/k}. Jacobian kind: substituting u = w(θ)
    (J sin θ dθ = sin u du) gives ``∫ y_l(f_k(u)) y_l'(u) sin u du``, which has no singular factor.
    """
    if kind == "radiance_jacobian":
        u, wt = _nodes(1.0 / k, model, nodes)
        y_i = _legendre_theta(np.cos(_np_map(u, k, model)), n)
        y_j = _legendre_theta(np.cos(u), n)
        weight = wt * np.sin(u)
    else:
        theta, wt = _nodes(k, model, nodes)
        y_i = _legendre_theta(np.cos(theta), n)
        y_j = _legendre_theta(np.cos(_np_map(theta, 1.0 / k, model)), n)
        weight = wt * np.sin(theta)
    return tuple(np.einsum("aq,bq,q->ab", y_i[m, m:], y_j[m, m:], weight) for m in range(n))


def mk_matrix(
    k: float, n: int = 4, kind: str = "occlusion", model: str = "paper", nodes: int = 64
) -> np.ndarray:
    """Dense float64 M_k (n², n²) for one ratio k = r/d > 0 (numpy, for tables, tests and figures).

    ``nodes`` Gauss–Legendre nodes per piece (see the module docstring); 64 gives about 1e-13.
    """
    _check(n, kind, model)
    if not (np.isfinite(k) and k > 0):
        raise ValueError(f"k = r/d must be a positive finite number, got {k}")
    blocks = _blocks(float(k), n, kind, model, int(nodes))
    out = np.zeros((n * n, n * n))
    for m in range(-(n - 1), n):
        idx = [l * l + l + m for l in range(abs(m), n)]
        out[np.ix_(idx, idx)] = blocks[abs(m)]
    if kind in ("occlusion", "radiance"):  # exact structure: column 0 is e0
        out[:, 0] = 0.0
        out[0, 0] = 1.0
    else:  # row 0 is e0ᵀ
        out[0, :] = 0.0
        out[0, 0] = 1.0
    return out


class MkTable(eqx.Module):
    """M_k tabulated at ratios ``ks`` (ascending), non-zero entries only.

    ``values[t, e]`` is ``M_{ks[t]}[rows[e], cols[e]]`` (pattern from :func:`mk_pattern` with the
    table's kind). Distances are in units of the sampling-shell radius: k = 1/d.
    """

    ks: Float[Array, " K"]  # k_t = r/d_t, ascending (d descending)
    values: Float[Array, "K nnz"]  # M_{k_t}[rows[e], cols[e]]
    rows: tuple[int, ...] = eqx.field(static=True)
    cols: tuple[int, ...] = eqx.field(static=True)
    n: int = eqx.field(static=True)  # SH bands
    kind: str = eqx.field(static=True, default="occlusion")
    model: str = eqx.field(static=True, default="paper")

    def __check_init__(self):
        if self.ks.ndim != 1 or self.ks.shape[0] < 2:
            raise ValueError(f"MkTable.ks must be a 1-D array of >= 2 ratios, got shape {self.ks.shape}")
        if self.values.shape != (self.ks.shape[0], len(self.rows)) or len(self.rows) != len(self.cols):
            raise ValueError(
                f"MkTable.values must have shape (K, nnz) = ({self.ks.shape[0]}, {len(self.rows)}), "
                f"got {self.values.shape}"
            )

    @property
    def distances(self) -> Float[Array, " K"]:
        """Tabulated distances d = 1/k in shell radii, descending."""
        return 1.0 / self.ks


def mk_table(
    n: int = 4,
    num: int = 16,
    d_min: float = 0.2,
    d_max: float = 8.0,
    kind: str = "occlusion",
    model: str = "paper",
    dtype=None,
    nodes: int = 64,
    include_shell: bool = True,
) -> MkTable:
    """Tabulate M_k at ``num`` distances d ∈ [d_min, d_max] (shell radii), geometrically spaced.

    With ``include_shell`` (default) d = 1 is a node, so receivers on the sampling shell get M = I
    exactly (the interpolation error of M_k peaks next to the shell: 0.045 per entry at d ≈ 0.98
    without this node); the spacing is then geometric on each side of it.

    Geometric spacing ``d_t = d_min (d_max/d_min)^{t/(num−1)}`` matches how visibility changes
    with distance (the silhouette's angular size goes as 1/d); 16 radial samples follow Zhou et
    al. 2005. Built in float64 numpy, then cast to ``dtype`` (default: JAX's default float).
    Call it outside hot loops (it is a few ms per distance); the result is a pytree to pass around.
    """
    _check(n, kind, model)
    if int(num) != num or num < 2:
        raise ValueError(f"num (number of tabulated distances) must be an integer >= 2, got {num}")
    if not (0.0 < d_min < d_max and np.isfinite(d_max)):
        raise ValueError(f"need 0 < d_min < d_max < inf (shell radii), got d_min={d_min}, d_max={d_max}")
    d = np.geomspace(d_max, d_min, int(num))  # descending d -> ascending k
    d[0], d[-1] = d_max, d_min
    if include_shell and d_min < 1.0 < d_max and num >= 3:
        # the shell itself (k = 1, M = I) is where interpolation error would be largest: make it a
        # node, spacing each side geometrically with the intervals shared in proportion to log range
        n_hi = int(np.clip(round((num - 1) * np.log(d_max) / np.log(d_max / d_min)), 1, num - 2))
        d = np.concatenate([np.geomspace(d_max, 1.0, n_hi + 1), np.geomspace(1.0, d_min, num - n_hi)[1:]])
        d[0], d[n_hi], d[-1] = d_max, 1.0, d_min
    ks = 1.0 / d
    rows, cols = mk_pattern(n, kind)
    vals = np.stack([mk_matrix(k, n, kind, model, nodes)[rows, cols] for k in ks])
    dtype = jnp.result_type(float) if dtype is None else dtype
    return MkTable(
        ks=jnp.asarray(ks, dtype),
        values=jnp.asarray(vals, dtype),
        rows=rows,
        cols=cols,
        n=n,
        kind=kind,
        model=model,
    )


def _interp_values(table: MkTable, k: Array, dtype) -> Array:
    """Entries (..., nnz) of M_k, linear in k between table points, clamped to [k_min, k_max].

    The interpolation weights are hat functions of k over the K table points, so the entries are
    one (..., K) @ (K, nnz) product; on XLA:CPU this was 2–4× faster than gathering two table rows
    per receiver (benchmarks/results/scaling.md).
    """
    ks = table.ks.astype(dtype)
    vals = table.values.astype(dtype)
    n_k = ks.shape[0]
    first = np.arange(n_k) == 0
    last = np.arange(n_k) == n_k - 1
    left = jnp.concatenate([ks[:1], ks[:-1]])  # k_{t−1} (k_0 for t = 0)
    right = jnp.concatenate([ks[1:], ks[-1:]])  # k_{t+1} (k_{K−1} for t = K−1)
    den_l = jnp.where(first, 1.0, ks - left)  # double where: no 0/0 at the ends, even in gradients
    den_r = jnp.where(last, 1.0, right - ks)
    kc = jnp.clip(k, ks[0], ks[-1])[..., None]
    rise = jnp.where(first, 1.0, (kc - left) / den_l)
    fall = jnp.where(last, 1.0, (right - kc) / den_r)
    w = jnp.clip(jnp.where(kc <= ks, rise, fall), 0.0, 1.0)  # (..., K) hat weights, summing to 1
    return jnp.matmul(w, vals, precision=jax.lax.Precision.HIGHEST)


def _float_dtype(*xs):
    dt = jnp.result_type(*[x.dtype for x in xs if jnp.issubdtype(x.dtype, jnp.floating)] or [float])
    return dt


def mk_interpolate(table: MkTable, k: Float[ArrayLike, "..."]) -> Float[Array, "... n2 n2"]:
    """Dense M_k (..., n², n²) at ratios k (...), linear in k, clamped to the table's range.

    Differentiable in k inside the range (zero gradient outside it). Forms the dense matrix per k:
    use :func:`mk_apply` to apply it to coefficients.
    """
    k = jnp.asarray(k)
    dtype = _float_dtype(k, table.values)
    k = k.astype(dtype)
    v = _interp_values(table, k, dtype)
    n2 = table.n * table.n
    out = jnp.zeros((*k.shape, n2, n2), dtype)
    return out.at[..., jnp.asarray(table.rows), jnp.asarray(table.cols)].set(v)


def mk_apply(
    table: MkTable, k: Float[ArrayLike, "..."], coeffs: Float[ArrayLike, "... n2"]
) -> Float[Array, "... n2"]:
    """``M_k @ coeffs`` for batches of ratios k (...) and coefficients (..., n'²), n' <= table.n.

    Never forms the dense matrix: interpolates the table's non-zero entries at k and accumulates
    one product per entry (41 multiply-adds for n = 4), which XLA fuses into a single elementwise
    pass (about 8× faster than the dense form for 1e5 receivers on CPU). k and coeffs broadcast
    over leading axes; computed in coeffs' dtype (the table is cast).
    Coefficient vectors with fewer bands than the table use its leading n'² × n'² block (the same
    integrals). Differentiable in k (inside the table's range) and in coeffs.
    """
    coeffs = jnp.asarray(coeffs)
    if not jnp.issubdtype(coeffs.dtype, jnp.floating):
        raise ValueError(f"coeffs must be a floating-point array, got dtype {coeffs.dtype}")
    nb = sh_bands_of(coeffs.shape[-1])
    if nb > table.n:
        raise ValueError(f"coeffs have {nb} SH bands but the M_k table only {table.n}; build a larger table")
    dtype = coeffs.dtype
    k = jnp.asarray(k).astype(dtype)
    batch = jnp.broadcast_shapes(k.shape, coeffs.shape[:-1])
    v = _interp_values(table, jnp.broadcast_to(k, batch), dtype)
    c = jnp.broadcast_to(coeffs, (*batch, nb * nb))
    acc: list = [None] * (nb * nb)
    for e, (i, j) in enumerate(zip(table.rows, table.cols)):
        if i >= nb * nb or j >= nb * nb:
            continue
        term = v[..., e] * c[..., j]
        acc[i] = term if acc[i] is None else acc[i] + term
    return jnp.stack(acc, axis=-1)


def mk_in_range(table: MkTable, k: Float[ArrayLike, "..."]) -> Bool[Array, "..."]:
    """True where the receiver is not farther than the largest tabulated distance (k >= k_min).

    Where it is False the caller treats the entity as absent (visibility 1); for k above the
    table's largest ratio the interpolation clamps, and this is still True.
    """
    k = jnp.asarray(k)
    dtype = _float_dtype(k, table.ks)
    k_min = table.ks[0].astype(dtype)
    return k.astype(dtype) >= k_min * (1.0 - eps(dtype))
