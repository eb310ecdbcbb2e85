"""The key sorts of ``jshadow._sorting``: NumPy's on the CPU, XLA's elsewhere, the same results."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jshadow._sorting import PAD, _np_argsort, argsort_keys, sort_keys


def _keys(shape, seed=0, pad=0.3, span=50):
    """uint32 keys with many ties (values below ``span``), a fraction of them PAD and a few large."""
    rng = np.random.default_rng(seed)
    k = rng.integers(0, span, shape).astype(np.uint32)
    k[rng.random(shape) < 0.05] = np.uint32(PAD - 1)
    k[rng.random(shape) < pad] = np.uint32(PAD)
    return k


@pytest.mark.parametrize("shape", [(97,), (1, 97), (3, 1, 40)])
def test_argsort_is_numpys_stable_argsort(shape):
    k = _keys(shape)
    expected = np.argsort(k, axis=-1, kind="stable")
    got = np.asarray(jax.jit(argsort_keys)(jnp.asarray(k)))
    assert got.dtype == np.int32
    np.testing.assert_array_equal(got, expected)
    # the other platforms' branch (XLA's sort) gives the same permutation
    other = np.asarray(jnp.argsort(jnp.asarray(k), axis=-1, stable=True))
    np.testing.assert_array_equal(other, expected)


@pytest.mark.parametrize("shape", [(97,), (1, 97), (3, 1, 40)])
def test_sort_matches_numpy_for_both_dtypes(shape):
    k = _keys(shape, seed=1)
    for dtype in (np.uint32, np.int32):
        a = (k >> 1).astype(dtype) if dtype == np.int32 else k  # int32: non-negative and max values
        got = np.asarray(jax.jit(sort_keys)(jnp.asarray(a)))
        assert got.dtype == dtype
        np.testing.assert_array_equal(got, np.sort(a, axis=-1))


def test_under_vmap_each_row_alone():
    k = _keys((4, 33), seed=2)
    got = np.asarray(jax.jit(jax.vmap(argsort_keys))(jnp.asarray(k)))
    np.testing.assert_array_equal(got, np.argsort(k, axis=-1, kind="stable"))
    got = np.asarray(jax.vmap(sort_keys)(jnp.asarray(k)))
    np.testing.assert_array_equal(got, np.sort(k, axis=-1))


def test_edge_cases_of_the_host_sort():
    # all padding, no padding, one element, empty batch rows
    for k in (np.full(5, PAD, np.uint32), np.arange(5, 0, -1, dtype=np.uint32), np.zeros(1, np.uint32)):
        np.testing.assert_array_equal(_np_argsort(k), np.argsort(k, kind="stable"))
    assert _np_argsort(np.zeros((0, 4), np.uint32)).shape == (0, 4)
    # the largest non-padding key and index order of ties survive the 64-bit packing
    k = np.array([PAD - 1, 0, PAD - 1, PAD, 0], np.uint32)
    np.testing.assert_array_equal(_np_argsort(k), [1, 4, 0, 2, 3])


def test_inside_a_gradient_and_bad_input():
    # integer outputs: a loss that orders values by a key still has its ordinary derivative
    x = jnp.linspace(0.0, 1.0, 7)

    def loss(x):
        order = argsort_keys((jnp.arange(7, dtype=jnp.uint32) * 5) % 7)
        return jnp.sum(x[order] * jnp.arange(7.0))

    g = jax.grad(jax.jit(loss))(x)
    expected = np.zeros(7)
    expected[np.argsort((np.arange(7) * 5) % 7, kind="stable")] = np.arange(7.0)
    np.testing.assert_allclose(np.asarray(g), expected)
    with pytest.raises(TypeError, match="uint32"):
        argsort_keys(jnp.zeros(3, jnp.int32))
    with pytest.raises(TypeError, match="int32 or uint32"):
        sort_keys(jnp.zeros(3, jnp.float32))
    with pytest.raises(ValueError, match="one axis"):
        argsort_keys(jnp.uint32(3))
