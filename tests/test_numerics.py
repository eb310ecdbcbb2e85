"""NaN-safety of the safe_* helpers: values and jax.grad at each singular point."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jshadow._numerics import eps, safe_acos, safe_atan2, safe_div, safe_norm, safe_normalize, safe_sqrt


@pytest.mark.usefixtures("x64")
def test_eps_is_dtype_aware():
    assert eps(jnp.float64) < 1e-13 < 1e-7 < eps(jnp.float32) < 1e-5


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("x", [0.0, -1.0, 1e-300])
def test_safe_sqrt_grad_finite(x):
    g = jax.grad(safe_sqrt)(x)
    assert np.isfinite(g)
    assert float(safe_sqrt(4.0)) == 2.0


@pytest.mark.usefixtures("x64")
def test_safe_div_at_zero():
    assert float(safe_div(1.0, 0.0)) == 0.0
    g = jax.grad(safe_div, argnums=(0, 1))(1.0, 0.0)
    assert all(np.isfinite(gi) for gi in g)
    assert float(safe_div(1.0, 4.0)) == 0.25


@pytest.mark.usefixtures("x64")
def test_safe_atan2_at_origin():
    g = jax.grad(safe_atan2, argnums=(0, 1))(0.0, 0.0)
    assert all(np.isfinite(gi) for gi in g)
    np.testing.assert_allclose(safe_atan2(1.0, -1.0), 3 * np.pi / 4)


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("c", [1.0, -1.0, 1.0 + 1e-12])
def test_safe_acos_at_ends(c):
    assert np.isfinite(jax.grad(safe_acos)(c))
    np.testing.assert_allclose(safe_acos(0.5), np.arccos(0.5), rtol=1e-14)


@pytest.mark.usefixtures("x64")
def test_safe_norm_and_normalize_at_zero():
    z = jnp.zeros(3)
    assert np.all(np.isfinite(jax.grad(safe_norm)(z)))
    assert np.all(np.isfinite(jax.jacfwd(safe_normalize)(z)))
    assert np.all(np.isfinite(jax.jacrev(safe_normalize)(z)))
    np.testing.assert_allclose(safe_normalize(jnp.array([3.0, 0.0, 4.0])), [0.6, 0.0, 0.8])
