"""NaN-safe elementary functions and the one dtype-aware tolerance helper.

Every singular point (sqrt at 0, division by 0, atan2 at the origin, acos at ±1, normalising a
zero vector) is handled with the *double-where* pattern: the unsafe input is replaced by a harmless
value before the singular function sees it, and the result is selected afterwards. A single
``where`` is not enough: reverse mode would still multiply a zero cotangent by an infinite partial
derivative and produce NaN. Each helper has a ``jax.grad`` regression test at its singular point
(``tests/test_numerics.py``).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

__all__ = [
    "eps",
    "safe_sqrt",
    "safe_div",
    "safe_atan2",
    "fast_atan2",
    "fast_acos",
    "fast_sin",
    "safe_acos",
    "small_sum",
    "safe_norm",
    "safe_normalize",
    "select_max",
    "select_min",
]


def eps(dtype=None, scale: float = 1.0) -> float:
    """Tolerance for ``dtype``: ``scale`` times a fixed multiple of machine epsilon.

    float32 -> about 1.2e-6 · scale, float64 -> about 2.2e-15 · scale. Use this instead of bare
    literals such as ``1e-6`` so that float64 tests are held to float64 accuracy.
    """
    dtype = jnp.result_type(float) if dtype is None else dtype
    return float(10.0 * np.finfo(np.dtype(dtype)).eps * scale)


def safe_sqrt(x: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
    """sqrt(max(x, 0)) whose gradient at x <= 0 is 0 instead of inf/NaN."""
    x = jnp.asarray(x)
    pos = x > 0
    x_safe = jnp.where(pos, x, 1.0)  # double where: sqrt never sees 0 or a negative number
    return jnp.where(pos, jnp.sqrt(x_safe), 0.0)


def safe_div(num: Float[ArrayLike, "..."], den: Float[ArrayLike, "..."], fill: float = 0.0):
    """num / den, or ``fill`` where |den| is below eps; finite gradient everywhere."""
    num, den = jnp.asarray(num), jnp.asarray(den)
    ok = jnp.abs(den) > eps(jnp.result_type(num, den)) ** 2
    den_safe = jnp.where(ok, den, 1.0)
    return jnp.where(ok, num / den_safe, fill)


def safe_atan2(y: Float[ArrayLike, "..."], x: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
    """atan2(y, x) with value 0 and zero gradient at the origin (x = y = 0)."""
    y, x = jnp.asarray(y), jnp.asarray(x)
    zero = (x == 0) & (y == 0)
    x_safe = jnp.where(zero, 1.0, x)
    return jnp.where(zero, 0.0, jnp.arctan2(y, x_safe))


# atan(t) ≈ t · Σ_i c_i t^(2i) on [0, 1]: odd polynomial of degree 15 fitted by iteratively reweighted
# least squares (minimax-like) on 20001 points; max |error| 3.7e-8 rad in exact arithmetic; after the
# octant reduction in float32, 3.1e-7 rad over all angles (one float32 ulp at ±π; tests/test_numerics.py).
_ATAN_POLY = (
    0.99999934,
    -0.33329861,
    0.19946564,
    -0.1390862,
    0.09642172,
    -0.05591196,
    0.02186269,
    -0.00405449,
)


def _atan2_poly(y: Array, x: Array) -> Array:
    ax, ay = jnp.abs(x), jnp.abs(y)
    hi, lo = jnp.maximum(ax, ay), jnp.minimum(ax, ay)
    t = lo / jnp.where(hi > 0, hi, 1.0)  # in [0, 1]; 0 at the origin
    s = t * t
    p = jnp.asarray(_ATAN_POLY[-1], t.dtype)
    for c in _ATAN_POLY[-2::-1]:
        p = p * s + c
    r = p * t
    r = jnp.where(ay > ax, 0.5 * np.pi - r, r)
    r = jnp.where(x < 0, np.pi - r, r)
    return jnp.where(y < 0, -r, r)


@jax.custom_jvp
def fast_atan2(y: Float[ArrayLike, "..."], x: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
    """atan2(y, x) in (−π, π], 0 at the origin, with the exact derivative and zero gradient there.

    float32 (and narrower) inputs use an odd polynomial after octant reduction (max error 3.1e-7
    rad, about one float32 ulp at ±π; XLA:CPU's ``atan2`` measured 7–16× slower, benchmarks/bench_sh.py);
    float64 inputs use ``jnp.arctan2``. The derivative is the exact ``(x dy − y dx)/(x² + y²)``
    (not the polynomial's), with a double ``where`` at the origin.
    """
    y, x = jnp.asarray(y), jnp.asarray(x)
    y, x = jnp.broadcast_arrays(*(a.astype(jnp.result_type(y, x, float)) for a in (y, x)))
    if jnp.finfo(y.dtype).bits > 32:
        return safe_atan2(y, x)
    return _atan2_poly(y, x)


@fast_atan2.defjvp
def _fast_atan2_jvp(primals, tangents):
    y, x = (jnp.asarray(a) for a in primals)
    dy, dx = (jnp.asarray(a) for a in tangents)
    out = fast_atan2(y, x)
    r2 = x * x + y * y
    ok = r2 > 0
    inv = jnp.where(ok, 1.0 / jnp.where(ok, r2, 1.0), 0.0)
    return out, ((x * dy - y * dx) * inv).astype(out.dtype)


def fast_acos(c: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
    """:func:`safe_acos` through :func:`fast_atan2`: the polynomial in float32, exact in float64.

    Same clipping and the same finite (one-sided) gradient at ±1; max error 3.1e-7 rad in float32.
    """
    c = jnp.clip(jnp.asarray(c), -1.0, 1.0)
    return fast_atan2(safe_sqrt(1.0 - c * c), c)


# sin(x) on [−π/2, π/2] as x · Σ_i (−1)^i x^(2i)/(2i+1)!, i ≤ 6 (Taylor to x¹³: truncation below
# 7e-10 at ±π/2, far under float32 rounding)
_SIN_POLY = tuple((-1.0) ** i / float(np.prod(np.arange(1, 2 * i + 2))) for i in range(7))


def _sin_poly(x: Array) -> Array:
    r = jnp.where(x > 0.5 * np.pi, np.pi - x, jnp.where(x < -0.5 * np.pi, -np.pi - x, x))
    s = r * r
    p = jnp.asarray(_SIN_POLY[-1], r.dtype)
    for c in _SIN_POLY[-2::-1]:
        p = p * s + c
    return p * r


@jax.custom_jvp
def fast_sin(x: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
    """sin(x) for x in [−π, π] (outside that range the result is wrong: reduce first).

    float32 (and narrower) inputs use a polynomial after folding to [−π/2, π/2] (within 2.4e-7 of
    float64 ``sin``, tests/test_numerics.py). XLA:CPU's ``jnp.sin`` is several times slower:
    ``benchmarks/bench_sh.py``'s rows for 1e5 values measured 0.43–0.46 ms against 0.07–0.20 ms
    (BENCHMARKS.md). float64 inputs use ``jnp.sin``. The derivative is cos x, from the same
    polynomial at π/2 − |x|.
    """
    x = jnp.asarray(x)
    x = x.astype(jnp.result_type(x, float))
    if jnp.finfo(x.dtype).bits > 32:
        return jnp.sin(x)
    return _sin_poly(x)


@fast_sin.defjvp
def _fast_sin_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    x = jnp.asarray(x)
    x = x.astype(jnp.result_type(x, float))
    return fast_sin(x), fast_sin(0.5 * np.pi - jnp.abs(x)) * jnp.asarray(dx, x.dtype)


def safe_acos(c: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
    """acos(clip(c, -1, 1)) with a finite (one-sided) gradient at ±1.

    Computed as atan2(sqrt(1 - c²), c), which is well conditioned near ±1; the sqrt is safe.
    """
    c = jnp.clip(jnp.asarray(c), -1.0, 1.0)
    return jnp.arctan2(safe_sqrt(1.0 - c * c), c)


def small_sum(x: Float[ArrayLike, "... d"], axis: int = -1, keepdims: bool = False) -> Float[Array, "..."]:
    """``jnp.sum(x, axis)``; over a short axis (d <= 4) as unrolled adds.

    XLA:CPU (jax 0.10) hands a reduction over a trailing axis of length 3 to a library kernel that
    neither fuses with its operands nor with its users: the norm of 1e5 offsets took 0.93 ms that
    way and 0.27 ms unrolled (``benchmarks/bench_sh.py``; BENCHMARKS.md, "Spherical harmonics").
    Unrolled, it fuses into the surrounding elementwise work.
    """
    x = jnp.asarray(x)
    ax = axis % x.ndim
    if x.shape[ax] > 4:
        return jnp.sum(x, axis=ax, keepdims=keepdims)
    parts = [jax.lax.index_in_dim(x, i, ax, keepdims=keepdims) for i in range(x.shape[ax])]
    acc = parts[0]
    for p in parts[1:]:
        acc = acc + p
    return acc


def safe_norm(v: Float[ArrayLike, "... d"], axis: int = -1, keepdims: bool = False):
    """Euclidean norm with zero gradient at v = 0 (instead of NaN)."""
    v = jnp.asarray(v)
    return safe_sqrt(small_sum(v * v, axis=axis, keepdims=keepdims))


def safe_normalize(v: Float[ArrayLike, "... d"], axis: int = -1) -> Float[Array, "... d"]:
    """v / |v|; a zero vector maps to zero with a zero gradient."""
    v = jnp.asarray(v)
    n2 = small_sum(v * v, axis=axis, keepdims=True)
    ok = n2 > 0
    inv = jnp.where(ok, 1.0 / jnp.sqrt(jnp.where(ok, n2, 1.0)), 0.0)
    return v * inv


def select_max(x: Float[ArrayLike, "..."], axis: int = -1) -> Float[Array, "..."]:
    """``jnp.max(x, axis)`` whose derivative is finite for any rounding and splits ties equally.

    ``jnp.max``'s derivative is ``g · [x = max] / Σ [x = max]``: it compares ``x`` with the maximum
    and divides by the number of ties. XLA may compute ``x`` in the two fused kernels with
    different rounding (for example one of them contracted into a fused multiply–add), and then
    no element equals the maximum: ``1/0``. Measured: the bounding sphere of ``c + 0.6 · u`` for
    random 42-point sets, at ``--xla_backend_optimization_level=0`` on CPU, had an infinite or NaN
    gradient for 18 of 20 sets (``tests/test_geometry.py``). Here the value is ``jnp.max``'s and the
    derivative averages the tangent over the elements equal to the maximum *and* the one ``argmax``
    picks (the first), so the count is at least one whatever the rounding.

    At a tie the maximum is not differentiable; its one-sided derivative in a direction is the
    largest of the tied elements' derivatives, and the average is the one that central differences
    measure and the only choice that does not depend on the order of the elements. A symmetric mesh
    has such ties at rest, and rounding leaves them a unit or two apart, so elements within
    ``eps(dtype, 0.25)`` (2.5 rounding units) of the maximum, relative to it, count as tied. The two
    ends of the breathing egg are its bounding radius, one float32 unit apart: with the whole
    derivative on the larger (the former rule, first of exact ties) the radius's derivative along a
    smooth motion was 4.4 % from central differences and the whole frame's 1.0 % (from the slope of a
    cubic through seventeen differenced values); with the average 0.1 % and 0.4 % (BENCHMARKS.md,
    "Near-ties split equally"). A forward pass costs what ``jnp.max`` costs.
    """
    return _select_max(jnp.asarray(x), axis)


def select_min(x: Float[ArrayLike, "..."], axis: int = -1) -> Float[Array, "..."]:
    """``jnp.min(x, axis)`` with the derivative of :func:`select_max` (ties at the minimum averaged)."""
    return -_select_max(-jnp.asarray(x), axis)


@partial(jax.custom_jvp, nondiff_argnums=(1,))
def _select_max(x: Array, axis: int) -> Array:
    return jnp.max(x, axis=axis)


@_select_max.defjvp
def _select_max_jvp(axis, primals, tangents):
    (x,), (dx,) = primals, tangents
    m = jnp.max(x, axis=axis, keepdims=True)
    first = jnp.argmax(x, axis=axis, keepdims=True)
    # within 2.5 rounding units of the maximum; below the widening of with_center_anchors (eps(dtype))
    near = x >= m - eps(x.dtype, 0.25) * jnp.abs(m)
    ties = near | (jax.lax.broadcasted_iota(first.dtype, x.shape, axis % x.ndim) == first)
    count = jnp.sum(ties, axis=axis, dtype=x.dtype)  # >= 1: the argmax is always counted
    return jnp.squeeze(m, axis), jnp.sum(jnp.where(ties, dx, 0.0), axis=axis) / count
