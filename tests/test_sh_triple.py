"""SH triple product: Gaunt coefficients vs quadrature, product vs projected pointwise product."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import BATCH_SHAPES

from jshadow._numerics import eps
from jshadow.sh import (
    gaunt_tensor,
    product_matrix,
    project,
    sh_basis,
    sh_lm,
    sh_product,
    sh_product_t,
    sphere_grid,
)
from jshadow.sh._triple import _sh_product_dense


def _dense(n, n_out):
    i, j, k, v = gaunt_tensor(n, n_out)
    g = np.zeros((n_out * n_out, n * n, n * n))
    g[i, j, k] = v
    return g


def test_gaunt_count_and_symmetry():
    i, j, k, v = gaunt_tensor(4)
    assert len(v) == 353  # of 16³ = 4096
    assert i.dtype == np.int32 and v.dtype == np.float64
    g = _dense(4, 4)
    np.testing.assert_allclose(g, g.transpose(0, 2, 1), atol=1e-15)
    np.testing.assert_allclose(g, g.transpose(1, 0, 2), atol=1e-15)
    # G[0, j, k] = δ_jk / sqrt(4π)
    np.testing.assert_allclose(g[0], np.eye(16) / np.sqrt(4 * np.pi), atol=1e-15)
    # selection rules: triangle inequality and even l_i + l_j + l_k
    for a, b, c in zip(i, j, k):
        (li, _), (lj, _), (lk, _) = sh_lm(int(a)), sh_lm(int(b)), sh_lm(int(c))
        assert abs(lj - lk) <= li <= lj + lk and (li + lj + lk) % 2 == 0
    assert gaunt_tensor(4) is gaunt_tensor(4, 4)  # cached


@pytest.mark.usefixtures("x64")
def test_gaunt_matches_independent_quadrature():
    # a different (larger) grid and the JAX basis instead of the numpy one used to build G
    n, n_out = 3, 5
    d, w = sphere_grid(9, 17)
    y = np.asarray(sh_basis(d, 5))
    want = np.einsum("q,qi,qj,qk->ijk", np.asarray(w), y[:, : n_out**2], y[:, : n * n], y[:, : n * n])
    np.testing.assert_allclose(_dense(n, n_out), want, atol=1e-13)


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("n", [2, 4])
def test_product_equals_quadrature_of_product(rng, n):
    a, b = rng.normal(size=(2, n * n))
    d, w = sphere_grid(3 * n, 6 * n)
    y = sh_basis(d, n)
    fg = (y @ a) * (y @ b)
    # n_out = 2n - 1 is exact; n_out = n is the truncation of the same coefficients
    full = project(fg, d, w, 2 * n - 1)
    np.testing.assert_allclose(sh_product(jnp.asarray(a), jnp.asarray(b), 2 * n - 1), full, atol=1e-12)
    np.testing.assert_allclose(sh_product(jnp.asarray(a), jnp.asarray(b)), full[: n * n], atol=1e-12)
    np.testing.assert_allclose(_sh_product_dense(jnp.asarray(a), jnp.asarray(b)), full[: n * n], atol=1e-12)


@pytest.mark.usefixtures("x64")
def test_product_matrix_and_jacobian(rng):
    a, b = (jnp.asarray(x) for x in rng.normal(size=(2, 16)))
    M = product_matrix(a)
    assert M.shape == (16, 16)
    np.testing.assert_allclose(M @ b, sh_product(a, b), atol=1e-14)
    np.testing.assert_allclose(M, M.T, atol=1e-14)  # symmetric when n_out = n
    # sh_product is bilinear: its Jacobian in b is product_matrix(a), by jacfwd and jacrev
    np.testing.assert_allclose(jax.jacfwd(sh_product, argnums=1)(a, b), M, atol=1e-14)
    np.testing.assert_allclose(jax.jacrev(sh_product, argnums=1)(a, b), M, atol=1e-14)
    M7 = product_matrix(a, 7)
    assert M7.shape == (49, 16)
    np.testing.assert_allclose(M7 @ b, sh_product(a, b, 7), atol=1e-14)
    # multiplying by the constant function 1 (c_00 = sqrt(4π)) is the identity
    one = jnp.zeros(16).at[0].set(np.sqrt(4 * np.pi))
    np.testing.assert_allclose(product_matrix(one), np.eye(16), atol=1e-14)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_batch_shapes(rng, shape):
    a = jnp.asarray(rng.normal(size=(*shape, 16)).astype(np.float32))
    b = jnp.asarray(rng.normal(size=(*shape, 16)).astype(np.float32))
    p = sh_product(a, b)
    assert p.shape == (*shape, 16) and p.dtype == jnp.float32
    tol = eps(jnp.float32, 10)
    np.testing.assert_allclose(p, _sh_product_dense(a, b), rtol=tol, atol=tol)
    M = product_matrix(a)
    assert M.shape == (*shape, 16, 16)
    np.testing.assert_allclose(jnp.einsum("...ik,...k->...i", M, b), p, rtol=tol, atol=tol)
    # one light times a batch of visibilities broadcasts
    assert sh_product(a.reshape(-1, 16)[0], b).shape == (*shape, 16)
    # coefficient axis first: the same numbers, also truncated and broadcast
    a_t, b_t = jnp.moveaxis(a, -1, 0), jnp.moveaxis(b, -1, 0)
    np.testing.assert_allclose(jnp.moveaxis(sh_product_t(a_t, b_t), 0, -1), p, rtol=tol, atol=tol)
    p9 = sh_product_t(a_t, a.reshape(-1, 16)[0].reshape(16, *([1] * len(shape))), n_out=3)
    assert p9.shape == (9, *shape)
    np.testing.assert_allclose(
        jnp.moveaxis(p9, 0, -1), sh_product(a, a.reshape(-1, 16)[0], n_out=3), rtol=tol, atol=tol
    )


def test_bad_input():
    with pytest.raises(ValueError, match="same number"):
        sh_product(jnp.ones(9), jnp.ones(16))
    with pytest.raises(ValueError, match="as many"):
        sh_product_t(jnp.ones((9, 2)), jnp.ones((16, 2)))
    with pytest.raises(ValueError, match="square"):
        sh_product(jnp.ones(8), jnp.ones(8))
    with pytest.raises(ValueError, match="positive integers"):
        gaunt_tensor(0)
    with pytest.raises(ValueError, match="scalar"):
        product_matrix(jnp.ones(()))
