"""Sorting integer keys: NumPy's sorts on the CPU, XLA's elsewhere.

XLA:CPU sorts with a generic comparator, element by element. Measured on the 2-core CPU
(``python benchmarks/bench_sort.py``, 201k uint32 keys, 43 % of them padding): XLA's sort takes
about 13 ms there and its stable argsort (a sort with an index payload) about 70 ms, where NumPy's
vectorised sort takes 2 ms and this module's argsort (one sort of 64-bit words, key above index,
padding left out) about 6 ms. The
silhouette derivatives of the BSV sort that many keys per call, so on the CPU they sort through a
host callback (:func:`jax.pure_callback`). :func:`jax.lax.platform_dependent` picks the branch when
the computation is lowered: on any other platform (a GPU) the same functions run XLA's sort, which
is fast there, and no data leaves the device.

Both functions work on the last axis, batch over the leading ones and under :func:`jax.vmap`, and
have no derivative (their outputs are integers).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Int, Shaped

__all__ = ["PAD", "argsort_keys", "sort_keys"]

PAD = 0xFFFFFFFF
"""The uint32 key that marks padding for :func:`argsort_keys`: it sorts last, and the CPU branch
leaves those entries out of the sort."""


def _np_argsort_row(k: np.ndarray) -> np.ndarray:
    live = np.flatnonzero(k != PAD)
    # key in the high word, index in the low word: one sort of distinct words, stable for the keys
    packed = (k[live].astype(np.uint64) << np.uint64(32)) | live.astype(np.uint64)
    packed.sort()
    out = np.empty(k.shape[0], np.int32)
    out[: live.size] = packed & np.uint64(0xFFFFFFFF)
    out[live.size :] = np.flatnonzero(k == PAD)
    return out


def _np_argsort(keys: np.ndarray) -> np.ndarray:
    k = np.asarray(keys, np.uint32)
    n = k.shape[-1]
    rows = k.reshape(-1, n)
    if rows.shape[0] == 0:
        return np.zeros(k.shape, np.int32)
    return np.stack([_np_argsort_row(r) for r in rows]).reshape(k.shape)


def _np_sort(keys: np.ndarray) -> np.ndarray:
    return np.sort(np.asarray(keys), axis=-1)


def _dispatch(name, keys, dtypes, host, out_dtype, xla):
    """Validate ``keys`` for ``name``, then ``host`` through a callback on the CPU, ``xla`` elsewhere."""
    keys = jnp.asarray(keys)
    if keys.dtype not in dtypes:
        allowed = " or ".join(str(jnp.dtype(d)) for d in dtypes)
        raise TypeError(f"{name} sorts {allowed} keys, got {keys.dtype}")
    if keys.ndim == 0:
        raise ValueError(f"{name} needs at least one axis")

    def cpu(k):
        out = jax.ShapeDtypeStruct(k.shape, out_dtype or k.dtype)
        return jax.pure_callback(host, out, k, vmap_method="expand_dims")

    return jax.lax.platform_dependent(keys, cpu=cpu, default=xla)


def argsort_keys(keys: Shaped[Array, "*batch n"]) -> Int[Array, "*batch n"]:
    """Stable argsort of uint32 keys along the last axis: indices (int32) that put ``keys`` in
    ascending order, equal keys in index order.

    Keys equal to :data:`PAD` sort last (as their value says); the CPU branch does not sort them,
    so padding costs nothing there. ``n`` must be below 2³¹.
    """

    def xla(k):
        return jnp.argsort(k, axis=-1, stable=True).astype(jnp.int32)

    return _dispatch("argsort_keys", keys, (jnp.uint32,), _np_argsort, jnp.int32, xla)


def sort_keys(keys: Int[Array, "*batch n"]) -> Int[Array, "*batch n"]:
    """Integer keys (int32 or uint32) sorted ascending along the last axis."""
    return _dispatch(
        "sort_keys", keys, (jnp.int32, jnp.uint32), _np_sort, None, lambda k: jnp.sort(k, axis=-1)
    )
