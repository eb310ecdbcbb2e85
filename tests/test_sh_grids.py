"""Quadrature grids and SH projection: weights, exactness limits, orthonormality, batch shapes."""

import jax.numpy as jnp
import numpy as np
import pytest
from conftest import BATCH_SHAPES, random_dirs

from jshadow._numerics import eps
from jshadow.sh import hemisphere_grid, num_coeffs, project, project_fn, sh_basis, sphere_grid
from jshadow.sh._grids import _np_sh_basis


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_sphere_grid_weights_and_dirs(dtype, x64):
    d, w = sphere_grid(5, 7, dtype)
    assert d.shape == (35, 3) and w.shape == (35,)
    assert d.dtype == dtype and w.dtype == dtype
    np.testing.assert_allclose(float(jnp.sum(w)), 4 * np.pi, rtol=eps(dtype))
    np.testing.assert_allclose(jnp.linalg.norm(d, axis=-1), 1.0, rtol=eps(dtype))
    assert np.all(np.diff(np.asarray(d[::7, 2])) < 0)  # θ-major, θ increasing
    dh, wh = hemisphere_grid(5, 7, dtype)
    np.testing.assert_allclose(float(jnp.sum(wh)), 2 * np.pi, rtol=eps(dtype))
    assert np.all(np.asarray(dh[:, 2]) > 0)


def test_default_dtype_is_float32():
    d, w = sphere_grid(3, 4)
    assert d.dtype == jnp.float32 and w.dtype == jnp.float32


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("n", [1, 4, 8])
def test_orthonormal_on_minimal_exact_grid(n):
    # Y_i Y_j has degree 2(n-1) in z and |m| <= 2(n-1): n_theta = n, n_phi = 2n - 1 is exact.
    d, w = sphere_grid(n, 2 * n - 1)
    gram = project(sh_basis(d, n).T, d, w, n)
    np.testing.assert_allclose(gram, np.eye(num_coeffs(n)), atol=eps(jnp.float64, 10))


@pytest.mark.usefixtures("x64")
def test_exactness_limit_is_sharp():
    # one node fewer in θ or φ than the rule needs: the Gram matrix is visibly wrong
    n = 4
    for nt, nphi in [(n - 1, 2 * n - 1), (n, 2 * n - 2)]:
        d, w = sphere_grid(nt, nphi)
        gram = project(sh_basis(d, n).T, d, w, n)
        assert np.abs(gram - np.eye(16)).max() > 1e-3


@pytest.mark.usefixtures("x64")
def test_hemisphere_integrates_polynomials_exactly():
    d, w = hemisphere_grid(4, 9)
    for k in range(8):  # ∫_{z>=0} z^k dω = 2π / (k + 1)
        np.testing.assert_allclose(float(jnp.sum(w * d[:, 2] ** k)), 2 * np.pi / (k + 1), rtol=1e-13)
    # ∫_{z>=0} x² y² dω = 2π/15 (half of the full-sphere 4π/15); needs |m| <= 4 < n_phi
    np.testing.assert_allclose(float(jnp.sum(w * d[:, 0] ** 2 * d[:, 1] ** 2)), 2 * np.pi / 15, rtol=1e-13)


@pytest.mark.usefixtures("x64")
def test_numpy_basis_matches_jax_basis(rng):
    d = random_dirs(rng, (40,))
    d[0] = [0, 0, 1.0]
    d[1] = [0, 0, -1.0]
    np.testing.assert_allclose(_np_sh_basis(d, 8), sh_basis(jnp.asarray(d), 8), atol=1e-13)


@pytest.mark.usefixtures("x64")
def test_project_recovers_band_limited_function(rng):
    c = rng.normal(size=(2, 25))
    d, w = sphere_grid(6, 11)
    got = project(c @ np.asarray(sh_basis(d, 5)).T, d, w, 5)
    np.testing.assert_allclose(got, c, atol=1e-13)
    # projecting onto fewer bands truncates
    np.testing.assert_allclose(project(c @ np.asarray(sh_basis(d, 5)).T, d, w, 3), c[:, :9], atol=1e-13)


@pytest.mark.usefixtures("x64")
def test_project_fn_high_accuracy_grid():
    # f = 1 + 2 z + x y z² (degree 4) is captured exactly; the coefficients are checked against
    # closed forms: c_00 = sqrt(4π) + ∫ x y z² Y_00 = sqrt(4π), c_10 = 2 sqrt(4π/3).
    def f(d):
        return jnp.stack([1 + 2 * d[:, 2] + d[:, 0] * d[:, 1] * d[:, 2] ** 2, d[:, 2] ** 2], -1)

    c = project_fn(f, 5)
    assert c.shape == (2, 25)
    np.testing.assert_allclose(c[0, 0], np.sqrt(4 * np.pi), rtol=1e-13)
    np.testing.assert_allclose(c[0, 2], 2 * np.sqrt(4 * np.pi / 3), rtol=1e-13)
    # z² = 1/3 + (2/3) P_2(z): c_00 = sqrt(4π)/3, c_20 = (2/3) sqrt(4π/5)
    want = [np.sqrt(4 * np.pi) / 3, 2 / 3 * np.sqrt(4 * np.pi / 5)]
    np.testing.assert_allclose(c[1, [0, 6]], want, rtol=1e-13)
    np.testing.assert_allclose(np.delete(c[1], [0, 6]), 0.0, atol=1e-13)
    # an indicator converges at first order: half-sphere z >= 0 has c_00 = sqrt(π)
    c_half = project_fn(lambda d: (d[:, 2] >= 0).astype(d.dtype), 2)
    np.testing.assert_allclose(c_half[0], np.sqrt(np.pi), rtol=1e-2)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_project_batch_shapes(rng, shape):
    d, w = sphere_grid(4, 7)
    v = jnp.asarray(rng.normal(size=(*shape, d.shape[0])).astype(np.float32))
    out = project(v, d, w, 4)
    assert out.shape == (*shape, 16)
    flat = project(v.reshape(-1, d.shape[0]), d, w, 4)
    tol = eps(jnp.float32, 10)
    np.testing.assert_allclose(out.reshape(-1, 16), flat, rtol=tol, atol=tol)


def test_bad_input():
    d, w = sphere_grid(3, 5)
    with pytest.raises(ValueError, match="positive integers"):
        sphere_grid(0, 5)
    with pytest.raises(ValueError, match=r"dirs must have shape \(N, 3\)"):
        project(jnp.ones(15), d[:, :2], w, 2)
    with pytest.raises(ValueError, match="weights"):
        project(jnp.ones(15), d, w[:-1], 2)
    with pytest.raises(ValueError, match=r"values must have shape \(..., 15\)"):
        project(jnp.ones(14), d, w, 2)
    with pytest.raises(ValueError, match="bands"):
        project(jnp.ones(15), d, w, 0)
    with pytest.raises(ValueError, match="f must return"):
        project_fn(lambda d: jnp.ones(3), 2, 4, 4)
