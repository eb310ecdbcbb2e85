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

A function that is zonal about the scaling axis stays zonal (M_k keeps m), and only the m = 0 block
acts on it: :func:`mk_zonal_table` tabulates that block alone, up to :data:`ZONAL_BANDS_MAX` bands
(a sphere light's radiance field, sampled with many more bands than the lighting keeps, so that the
warp acts on an almost untruncated cap: :func:`jshadow.lights.sphere_light_srf`).
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
    "mk_apply_table",
    "mk_bracket",
    "mk_in_range",
    "mk_zonal_table",
    "mk_apply_zonal",
    "ZONAL_BANDS_MAX",
]

KINDS = ("occlusion", "radiance", "radiance_jacobian")
ZONAL_BANDS_MAX = 48
"""Most bands of :func:`mk_zonal_table`. At 64 bands its quadrature (64 Gauss–Legendre nodes per
piece) made a sphere light's 4-band coefficients worse, not better (at 10 light radii 0.41 % against
0.04 % at 48, a throwaway comparison); at 48 the light is within 1 % of its closed form from 1.2 to
24 light radii (tests/test_lights.py)."""


def _check(n: int, kind: str, model: str, most: int = 16) -> None:
    if int(n) != n or not 1 <= n <= most:
        raise ValueError(f"n (number of SH bands) must be an integer in 1..{most}, got {n}")
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


def _legendre_theta(x: np.ndarray, n: int, orders: int | None = None) -> np.ndarray:
    """θ-parts y_lm (n, n, ...) with ∫_0^π y_lm y_l'm sin θ dθ = δ_ll' (index [m, l]); x = cos θ.
    Only the first ``orders`` m (default all n) are computed, the rest stay 0."""
    out = np.zeros((n, n, *x.shape))
    s = np.sqrt(np.clip(1.0 - x * x, 0.0, None))
    for m in range(n if orders is None else orders):
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
def _blocks(
    k: float, n: int, kind: str, model: str, nodes: int, orders: int | None = None
) -> tuple[np.ndarray, ...]:
    """Per-m θ-blocks B_m[l, l'] (l, l' = m..n−1) of M_k in float64 (the first ``orders`` m; default all).

    J = 1: ``∫ y_l(θ) y_l'(w(θ)) sin θ dθ`` with w = f_{1/k}. Jacobian kind: substituting u = w(θ)
    (J sin θ dθ = sin u du) gives ``∫ y_l(f_k(u)) y_l'(u) sin u du``, which has no singular factor.
    """
    if kind == "radiance_jacobian":
        u, wt = _nodes(1.0 / k, model, nodes)
        y_i = _legendre_theta(np.cos(_np_map(u, k, model)), n, orders)
        y_j = _legendre_theta(np.cos(u), n, orders)
        weight = wt * np.sin(u)
    else:
        theta, wt = _nodes(k, model, nodes)
        y_i = _legendre_theta(np.cos(theta), n, orders)
        y_j = _legendre_theta(np.cos(_np_map(theta, 1.0 / k, model)), n, orders)
        weight = wt * np.sin(theta)
    ms = range(n if orders is None else orders)
    return tuple(np.einsum("aq,bq,q->ab", y_i[m, m:], y_j[m, m:], weight) for m in ms)


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
    return _exact_structure(out, kind)


def _exact_structure(a: np.ndarray, kind: str) -> np.ndarray:
    """``a`` (M_k or its m = 0 block; index 0 is Y_00 in both) with its exact structure set in place:
    column 0 is e0 for the J = 1 kinds, row 0 is e0ᵀ for the Jacobian kind."""
    if kind in ("occlusion", "radiance"):
        a[:, 0] = 0.0
    else:
        a[0, :] = 0.0
    a[0, 0] = 1.0
    return a


class MkTable(eqx.Module):
    """M_k tabulated at ratios ``ks`` (ascending), non-zero entries only.

    ``values[t, e]`` is ``M_{ks[t]}[rows[e], cols[e]]`` (pattern from :func:`mk_pattern` with the
    table's kind). Distances are in units of the sampling-shell radius: k = 1/d. A ``zonal`` table
    (:func:`mk_zonal_table`) holds the m = 0 block only, indexed by band (``rows``, ``cols`` are l, l').
    """

    ks: Float[Array, " K"]  # k_t = r/d_t, ascending (d descending)
    values: Float[Array, "K nnz"]  # M_{k_t}[rows[e], cols[e]]
    rows: tuple[int, ...] = eqx.field(static=True)
    cols: tuple[int, ...] = eqx.field(static=True)
    n: int = eqx.field(static=True)  # SH bands
    kind: str = eqx.field(static=True, default="occlusion")
    model: str = eqx.field(static=True, default="paper")
    zonal: bool = eqx.field(static=True, default=False)  # m = 0 block only; rows, cols are bands l

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
    d = _distances(num, d_min, d_max, include_shell)
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


def _distances(num, d_min, d_max, include_shell) -> np.ndarray:
    """The tabulated distances, descending (:func:`mk_table`)."""
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
    return d


def mk_zonal_table(
    n: int = 48,
    num: int = 64,
    d_min: float = 0.2,
    d_max: float = 32.0,
    kind: str = "radiance",
    model: str = "sphere",
    dtype=None,
    nodes: int = 64,
    include_shell: bool = True,
) -> MkTable:
    """Tabulate the m = 0 block of M_k (bands l, l' < n) at ``num`` distances (as :func:`mk_table`).

    For functions that are zonal about the scaling axis, such as the radiance a sphere light sends
    to a point (a cap about the direction to its centre): M_k maps them to zonal functions with this
    block alone, so they can be carried in up to :data:`ZONAL_BANDS_MAX` bands (at 48 bands the full
    matrix has 2304² positions; this block 48²). Apply it with :func:`mk_apply_zonal`. The defaults are
    the sphere-light setting of :func:`jshadow.lights.sphere_light_srf`: the concentric-sphere model
    (exact for a sphere's cap), no Jacobian, 64 distances up to 32 shell radii.
    """
    _check(n, kind, model, most=ZONAL_BANDS_MAX)
    ks = 1.0 / _distances(num, d_min, d_max, include_shell)
    if kind in ("occlusion", "radiance"):  # column 0 is e0
        pairs = [(i, j) for i in range(n) for j in range(n) if j > 0 or i == 0]
    else:  # row 0 is e0ᵀ
        pairs = [(i, j) for i in range(n) for j in range(n) if i > 0 or j == 0]
    rows, cols = (tuple(p[a] for p in pairs) for a in (0, 1))
    vals = [
        _exact_structure(_blocks(float(k), n, kind, model, int(nodes), 1)[0].copy(), kind)[rows, cols]
        for k in ks
    ]
    dtype = jnp.result_type(float) if dtype is None else dtype
    return MkTable(
        ks=jnp.asarray(ks, dtype),
        values=jnp.asarray(np.stack(vals), dtype),
        rows=rows,
        cols=cols,
        n=int(n),
        kind=kind,
        model=model,
        zonal=True,
    )


def mk_apply_zonal(
    table: MkTable,
    k: Float[ArrayLike, "..."],
    zonal: Float[ArrayLike, "... nb"],
    out_bands: int | None = None,
) -> Float[Array, "... m"]:
    """The m = 0 block of M_k applied to zonal coefficients (..., nb), nb <= table.n: zonal
    coefficients (..., out_bands) (default nb) at ratios k (...), linear in k between table points
    and clamped to its range, as :func:`mk_apply`. Needs a table of :func:`mk_zonal_table`.
    Differentiable in k (inside the range) and in the coefficients."""
    if not table.zonal:
        raise ValueError("mk_apply_zonal needs a zonal table (mk_zonal_table); use mk_apply for this one")
    z = jnp.asarray(zonal)
    if not jnp.issubdtype(z.dtype, jnp.floating) or z.ndim == 0:
        raise ValueError(
            f"zonal coefficients must be a floating-point array (..., nb), got {z.dtype} {z.shape}"
        )
    nb = z.shape[-1]
    m = nb if out_bands is None else int(out_bands)
    if not (1 <= nb <= table.n and 1 <= m <= table.n):
        raise ValueError(f"need 1 <= bands <= {table.n} (the table's), got {nb} in and {m} out")
    sel, scatter = _entries_cached(table.rows, table.cols, m, nb)  # rows, cols are bands here
    dtype = z.dtype
    k = jnp.asarray(k).astype(dtype)
    batch = jnp.broadcast_shapes(k.shape, z.shape[:-1])
    v = _interp_values(table, jnp.broadcast_to(k, batch), dtype, sel)  # (..., E)
    cols = np.asarray([table.cols[e] for e in sel], np.int32)
    zb = jnp.broadcast_to(z, (*batch, nb))
    return jnp.matmul(v * zb[..., cols], jnp.asarray(scatter, dtype), precision=jax.lax.Precision.HIGHEST)


def _interp_values(table: MkTable, k: Array, dtype, sel: tuple[int, ...] | None = None) -> Array:
    """Entries (..., nnz) of M_k, linear in k between table points, clamped to [k_min, k_max].

    The interpolation weights are hat functions of k over the K table points, so the entries are
    one (..., K) @ (K, nnz) product; on XLA:CPU this was 2–4× faster than gathering two table rows
    per receiver (benchmarks/results/scaling.md).
    """
    ks = table.ks.astype(dtype)
    vals = table.values.astype(dtype)
    if sel is not None:  # only these entries (..., len(sel))
        vals = vals[:, np.asarray(sel, np.int32)]
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
    """Dense M_k (..., n², n²) at ratios k (...), linear in k, clamped to the table's range (of a
    zonal table: its m = 0 block (..., n, n)).

    Differentiable in k inside the range (zero gradient outside it). Forms the dense matrix per k:
    use :func:`mk_apply` to apply it to coefficients.
    """
    k = jnp.asarray(k)
    dtype = _float_dtype(k, table.values)
    k = k.astype(dtype)
    v = _interp_values(table, k, dtype)
    n2 = table.n if table.zonal else table.n * table.n  # a zonal table's m = 0 block (..., n, n)
    out = jnp.zeros((*k.shape, n2, n2), dtype)
    return out.at[..., jnp.asarray(table.rows), jnp.asarray(table.cols)].set(v)


def mk_apply(
    table: MkTable, k: Float[ArrayLike, "..."], coeffs: Float[ArrayLike, "... n2"]
) -> Float[Array, "... n2"]:
    """``M_k @ coeffs`` for batches of ratios k (...) and coefficients (..., n'²), n' <= table.n.

    Never forms the dense matrix: interpolates the table's non-zero entries at k, multiplies each by
    its input coefficient (41 products for n = 4) and sums them into rows with a constant 0/1
    matrix (one pass over the entries; the per-output stacked sums it replaced measured 1.5× slower
    for 1e5 receivers, ``benchmarks/bench_sh.py``). When one coefficient set serves many ratios,
    :func:`mk_apply_table` is cheaper still. k and coeffs broadcast
    over leading axes; computed in coeffs' dtype (the table is cast).
    Coefficient vectors with fewer bands than the table use its leading n'² × n'² block (the same
    integrals). Differentiable in k (inside the table's range) and in coeffs.
    """
    coeffs, nb = _check_coeffs(table, coeffs)
    dtype = coeffs.dtype
    k = jnp.asarray(k).astype(dtype)
    batch = jnp.broadcast_shapes(k.shape, coeffs.shape[:-1])
    sel, scatter = _entries(table, nb, nb)
    v = _interp_values(table, jnp.broadcast_to(k, batch), dtype, sel)
    c = jnp.broadcast_to(coeffs, (*batch, nb * nb))
    cols = np.asarray([table.cols[e] for e in sel], np.int32)
    # (entries · gathered inputs) @ 0/1 row-scatter matrix: one pass over (..., nnz) instead of one
    # strided pass per output coefficient (XLA:CPU fused each stacked output separately)
    return jnp.matmul(v * c[..., cols], jnp.asarray(scatter, dtype), precision=jax.lax.Precision.HIGHEST)


def _check_coeffs(table: MkTable, coeffs) -> tuple[Array, int]:
    """coeffs as a floating array and its SH band count, which the table must cover."""
    if table.zonal:
        raise ValueError("this M_k table is zonal (mk_zonal_table): apply it with mk_apply_zonal")
    coeffs = jnp.asarray(coeffs)
    if not jnp.issubdtype(coeffs.dtype, jnp.floating):
        raise ValueError(f"coeffs must be a floating-point array, got dtype {coeffs.dtype}")
    nb = sh_bands_of(coeffs.shape[-1])
    if nb > table.n:
        raise ValueError(f"coeffs have {nb} SH bands but the M_k table only {table.n}; build a larger table")
    return coeffs, nb


@lru_cache(maxsize=64)
def _entries_cached(rows: tuple, cols: tuple, out_n2: int, in_n2: int) -> tuple[tuple[int, ...], np.ndarray]:
    """Entries with row < out_n2 and column < in_n2, and their (len, out_n2) 0/1 row-scatter matrix
    (rows and columns are coefficient indices; in a zonal table, bands)."""
    sel = tuple(e for e, (i, j) in enumerate(zip(rows, cols)) if i < out_n2 and j < in_n2)
    scatter = np.zeros((len(sel), out_n2))
    scatter[np.arange(len(sel)), [rows[e] for e in sel]] = 1.0
    scatter.setflags(write=False)
    return sel, scatter


def _entries(table: MkTable, out_bands: int, in_bands: int) -> tuple[tuple[int, ...], np.ndarray]:
    """Indices of the table entries mapping the first in_bands² inputs to the first out_bands²
    outputs, and the (len, out_bands²) 0/1 matrix summing the entries' products into rows."""
    return _entries_cached(table.rows, table.cols, out_bands * out_bands, in_bands * in_bands)


def mk_apply_table(
    table: MkTable, coeffs: Float[ArrayLike, "... n2"], out_bands: int | None = None
) -> Float[Array, "K ... m2"]:
    """``M_{k_t} @ coeffs`` at every tabulated ratio k_t (leading axis K), truncated to out_bands².

    M_k is linear in k between table points (:func:`mk_apply`), so for any k in the table's range
    ``M_k @ c = (1 − w) · (M_{k_t} @ c) + w · (M_{k_t+1} @ c)`` with ``(t, w) = mk_bracket(table, k)``.
    When one coefficient set serves many receivers (the BSV samples of an occluder), applying
    every tabulated matrix once and interpolating the results per receiver is exact and skips the
    per-receiver matrix interpolation and product. ``out_bands`` (default: the input's) keeps only
    the first out_bands² output rows (rows are independent, so this equals truncating afterwards).
    """
    coeffs, nb = _check_coeffs(table, coeffs)
    m = nb if out_bands is None else int(out_bands)
    if not 1 <= m <= table.n:
        raise ValueError(f"out_bands must be in 1..{table.n}, got {out_bands}")
    sel, scatter = _entries(table, m, nb)
    dtype = coeffs.dtype
    vals = table.values.astype(dtype)[:, np.asarray(sel, np.int32)]  # (K, E)
    cs = coeffs[..., np.asarray([table.cols[e] for e in sel], np.int32)]  # (..., E)
    prod = vals.reshape(vals.shape[0], *([1] * (coeffs.ndim - 1)), -1) * cs[None]
    return jnp.matmul(prod, jnp.asarray(scatter, dtype), precision=jax.lax.Precision.HIGHEST)


def mk_bracket(table: MkTable, k: Float[ArrayLike, "..."]) -> tuple[Array, Float[Array, "..."]]:
    """Table interval and weight of ratios k: ``(t, w)`` with ``k = (1 − w) k_t + w k_{t+1}``.

    k is clamped to [k_0, k_{K−1}] first (so ``w`` has zero derivative outside the range, as in
    :func:`mk_apply`); ``t`` is an int32 index in [0, K − 2] found by K comparisons (no search).
    Differentiable in k through ``w``.
    """
    k = jnp.asarray(k)
    dtype = _float_dtype(k, table.ks)
    ks = table.ks.astype(dtype)
    n_k = ks.shape[0]
    kc = jnp.clip(k.astype(dtype), ks[0], ks[-1])
    t = jnp.clip(jnp.sum(kc[..., None] >= ks, axis=-1, dtype=jnp.int32) - 1, 0, n_k - 2)
    lo, hi = ks[t], ks[t + 1]
    return t, (kc - lo) / (hi - lo)  # table ratios are strictly ascending: no 0/0


def mk_in_range(table: MkTable, k: Float[ArrayLike, "..."]) -> Bool[Array, "..."]:
    """True where the receiver is not farther than the largest tabulated distance (k >= k_min).

    Where it is False the caller treats the entity as absent (visibility 1); for k above the
    table's largest ratio the interpolation clamps, and this is still True.
    """
    k = jnp.asarray(k)
    dtype = _float_dtype(k, table.ks)
    k_min = table.ks[0].astype(dtype)
    return k.astype(dtype) >= k_min * (1.0 - eps(dtype))
