"""Evaluating a row-wise function on the rows that need it only (static shapes, under ``jit``).

A frame's receivers are many and a per-receiver computation is often trivial for most of them (a
light whose cone misses every occluder: its visible fraction is 1). :func:`over_active` moves the
rows that need the computation to the front (a stable compaction), splits the rows into a fixed
number of equal chunks and maps over the chunks with ``lax.map``, running ``fn`` on a chunk only if
it holds an active row (``lax.cond``); the other rows get ``fill``. Shapes stay static, so it works
under ``jax.jit``. Its derivative (``jax.jvp``, ``jax.grad``) is that of ``where(active, fn(rows),
fill)`` evaluated on all rows: differentiating the chunked map instead (a reverse pass through
``lax.map`` and ``lax.cond``) was slower than the full evaluation's, 1.15–1.3× on a sphere light's
visible fractions with 40–50 % of the receivers active, so only a forward pass skips work. Under
``jax.vmap`` the condition becomes a select and every chunk runs.

Nothing here imports the rest of jshadow.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import jax
import jax.numpy as jnp
from jax import lax
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Array, Bool, Shaped

__all__ = ["over_active", "chunk_count"]

# rows; a floor for small receiver sets, not measured (on 16384 receivers, 16 chunks of 1024 were
# as fast as 32 or 64 smaller ones and faster than 8: BENCHMARKS.md, "Skipping the receivers...")
_MIN_CHUNK = 512


def chunk_count(n: int, chunks: int = 16, min_chunk: int = _MIN_CHUNK) -> int:
    """The number of chunks :func:`over_active` splits ``n`` rows into: at most ``chunks``, each of
    at least ``min_chunk`` rows (one chunk for ``n <= 2 * min_chunk``)."""
    if n < 0 or chunks < 1 or min_chunk < 1:
        raise ValueError(
            f"chunk_count: need n >= 0, chunks >= 1, min_chunk >= 1 (got {n}, {chunks}, {min_chunk})"
        )
    return max(1, min(chunks, n // min_chunk))


def over_active(
    fn: Callable[..., Array],
    active: Bool[Array, " N"],
    rows: tuple[Shaped[Array, "N ..."], ...],
    fill: float,
    chunks: int | None = None,
) -> Shaped[Array, " N *rest"]:
    """``where(active, fn(*rows), fill)`` row by row, with ``fn`` run only on chunks of rows that
    hold an active one (in a forward pass; derivatives evaluate every row, module docstring).

    Args:
        fn: maps arrays of M rows (the leading axis of each of ``rows``) to one array of M rows; it
            must treat rows independently (it sees chunks of rows in another order) and may close
            over other arrays (their derivatives are kept: :func:`jax.closure_convert`).
        active: (N,) the rows whose value is needed; every other row gets ``fill``.
        rows: arrays with the same leading size N.
        fill: the value of inactive rows.
        chunks: how many chunks to split the N rows into (default :func:`chunk_count` of N). With
            A active rows, ``ceil(A / ceil(N / chunks))`` chunks run.

    Returns:
        (N, ...) the result, of ``fn``'s output dtype and trailing shape.
    """
    rows = tuple(jnp.asarray(r) for r in rows)
    n = active.shape[0]
    if any(r.shape[0] != n for r in rows):
        raise ValueError(f"over_active: rows must share the leading size {n}, got {[r.shape for r in rows]}")
    chunks = chunk_count(n) if chunks is None else chunks
    size = -(-n // chunks)
    # fn as a function of its rows and the arrays it closes over, traced once for all N rows (the
    # derivative's evaluation) and once for one chunk (the forward's map)
    on_all, consts = jax.closure_convert(lambda *xs: fn(*xs), *rows)
    chunk = tuple(jax.ShapeDtypeStruct((size,) + r.shape[1:], r.dtype) for r in rows)
    on_chunk, chunk_consts = jax.closure_convert(lambda *xs: fn(*xs), *chunk)
    if len(consts) != len(chunk_consts) or any(
        a is not b for a, b in zip(consts, chunk_consts, strict=False)
    ):
        return _full(on_all, fill, active, rows, tuple(consts))  # not seen: fn's closure depends on N
    return _over_active((on_all, on_chunk), chunks, fill, active, rows, tuple(consts))


def _full(fn, fill, active, rows, consts):
    return _masked(fn(*rows, *consts), active, fill)


def _masked(out, active, fill):
    """``out`` (N, ...) with ``fill`` on the inactive rows."""
    return jnp.where(active.reshape((-1,) + (1,) * (out.ndim - 1)), out, jnp.asarray(fill, out.dtype))


@partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2))
def _over_active(fns, chunks: int, fill: float, active, rows, consts):
    fn = fns[1]
    n = active.shape[0]
    size = -(-n // chunks)
    pad = size * chunks - n
    a = active.astype(jnp.int32)
    before = jnp.cumsum(a, dtype=jnp.int32) - a  # active rows before each row
    count = jnp.sum(a, dtype=jnp.int32)
    # compacted position of each row: active rows first, both groups in their original order
    pos = jnp.where(active, before, count + jnp.arange(n, dtype=jnp.int32) - before)
    order = jnp.zeros(n + pad, jnp.int32).at[pos].set(jnp.arange(n, dtype=jnp.int32))
    # padding rows (positions n .. n + pad − 1) read row 0; their results are never gathered back
    blocks = tuple(r[order].reshape((chunks, size) + r.shape[1:]) for r in rows)
    out_shape = jax.eval_shape(fn, *(b[0] for b in blocks), *consts)

    def step(args):
        i, xs = args
        return lax.cond(
            i * size < count,
            lambda xs: fn(*xs, *consts),
            lambda xs: jnp.full(out_shape.shape, fill, out_shape.dtype),
            xs,
        )

    out = lax.map(step, (jnp.arange(chunks, dtype=jnp.int32), blocks))
    return _masked(out.reshape((chunks * size,) + out.shape[2:])[pos], active, fill)


def _over_active_jvp(fns, chunks, fill, primals, tangents):
    fn = fns[0]
    active, rows, consts = primals
    _, d_rows, d_consts = tangents
    leaves, tree = jax.tree_util.tree_flatten((rows, consts))
    d_leaves = jax.tree_util.tree_leaves((d_rows, d_consts), is_leaf=lambda x: isinstance(x, SymbolicZero))
    live = [i for i, d in enumerate(d_leaves) if not isinstance(d, SymbolicZero)]

    def full(*xs):  # of the leaves with a tangent; the others are constants
        args = list(leaves)
        for i, x in zip(live, xs, strict=True):
            args[i] = x
        return _full(fn, fill, active, *jax.tree_util.tree_unflatten(tree, args))

    if not live:
        out = _full(fn, fill, active, rows, consts)
        return out, jnp.zeros_like(out)
    return jax.jvp(full, [leaves[i] for i in live], [d_leaves[i] for i in live])


_over_active.defjvp(_over_active_jvp, symbolic_zeros=True)
