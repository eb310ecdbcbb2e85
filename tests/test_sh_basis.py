"""SH basis: agreement with scipy, orthonormality by quadrature, batch shapes, NaN-free gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import BATCH_SHAPES, random_dirs
from scipy.special import sph_harm_y

from jshadow.sh import num_coeffs, sh_basis, sh_basis_spherical, sh_eval, sh_index, sh_lm


def test_index_roundtrip():
    for i in range(64):
        assert sh_index(*sh_lm(i)) == i
    with pytest.raises(ValueError):
        sh_index(2, 3)


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("n", [1, 4, 8])
def test_matches_scipy(rng, n):
    d = random_dirs(rng, (50,))
    b = np.asarray(sh_basis(jnp.asarray(d), n))
    th, ph = np.arccos(d[:, 2]), np.arctan2(d[:, 1], d[:, 0])
    for l in range(n):
        for m in range(-l, l + 1):
            y = sph_harm_y(l, abs(m), th, ph) * (-1) ** m  # remove Condon–Shortley phase
            ref = y.real if m == 0 else np.sqrt(2) * (y.real if m > 0 else y.imag)
            np.testing.assert_allclose(b[:, sh_index(l, m)], ref, atol=1e-12)


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("n", [1, 3, 4, 8])
def test_orthonormal_by_quadrature(n):
    # Gauss–Legendre in cos θ × uniform φ integrates polynomials of degree < 2·nt exactly
    nt, nphi = 2 * n + 2, 4 * n + 4
    x, w = np.polynomial.legendre.leggauss(nt)
    phi = (np.arange(nphi) + 0.5) * 2 * np.pi / nphi
    th = np.arccos(x)[:, None] * np.ones((1, nphi))
    y = np.asarray(sh_basis_spherical(jnp.asarray(th), jnp.asarray(phi[None, :] * np.ones((nt, 1))), n))
    wq = (w[:, None] * np.ones((1, nphi)) * 2 * np.pi / nphi)[..., None]
    gram = np.einsum("tpi,tpj->ij", y * wq, y)
    np.testing.assert_allclose(gram, np.eye(num_coeffs(n)), atol=1e-12)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_batch_shapes(rng, shape):
    d = jnp.asarray(random_dirs(rng, shape, np.float32))
    assert sh_basis(d, 4).shape == (*shape, 16)
    c = jnp.asarray(rng.normal(size=(*shape, 16)).astype(np.float32))
    v = sh_eval(c, d)
    assert v.shape == shape
    np.testing.assert_allclose(v, jnp.sum(c * sh_basis(d, 4), -1), rtol=1e-5, atol=1e-5)


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize(
    "d", [[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0], [0, 1.0, 0], [-1.0, 0, 0], [0, -1.0, 0]]
)
def test_grad_finite_at_poles_and_axes(d):
    d = jnp.asarray(d)
    jac = jax.jacrev(lambda v: sh_basis(v, 6))(d)
    assert np.all(np.isfinite(jac))
    jac = jax.jacrev(lambda t, p: sh_basis_spherical(t, p, 6), argnums=(0, 1))(
        jnp.arccos(d[2]), jnp.arctan2(d[1], d[0])
    )
    assert all(np.all(np.isfinite(j)) for j in jac)


def test_bad_input():
    with pytest.raises(ValueError, match="trailing axis"):
        sh_basis(jnp.ones((4, 2)), 4)
    with pytest.raises(ValueError, match="square"):
        sh_eval(jnp.ones(15), jnp.ones(3))
