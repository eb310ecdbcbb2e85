"""Zonal harmonics: cap and clamped-cosine closed forms vs exact quadrature, rotation, gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import BATCH_SHAPES, random_dirs
from scipy.special import eval_legendre

from jshadow._numerics import eps
from jshadow.sh import (
    cap,
    clamped_cosine,
    hemisphere_grid,
    rotate,
    sh_basis,
    zonal_cap,
    zonal_cap_versine,
    zonal_clamped_cosine,
    zonal_dot,
    zonal_rotate,
)

AXES = [[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0], [0, 0, 1.0], [0, 0, -1.0]]


def _frame(axis):
    """Rotation (float64 numpy) whose third column is the unit vector ``axis``."""
    a = np.asarray(axis, dtype=np.float64)
    helper = np.array([1.0, 0, 0]) if abs(a[0]) < 0.9 else np.array([0, 1.0, 0])
    u = np.cross(helper, a)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(a, u), a], axis=1)


def _cap_grid(t, n_theta=12, n_phi=24):
    """Exact rule on the cap z >= t: Gauss–Legendre on [t, 1] × uniform φ (numpy float64)."""
    x, w = np.polynomial.legendre.leggauss(n_theta)
    z, wz = t + (1 - t) * (x + 1) / 2, w * (1 - t) / 2
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    s = np.sqrt(1 - z * z)
    d = np.stack([np.outer(s, np.cos(phi)), np.outer(s, np.sin(phi)), np.outer(z, np.ones(n_phi))], -1)
    return d.reshape(-1, 3), np.outer(wz, np.full(n_phi, 2 * np.pi / n_phi)).reshape(-1)


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("t", [-1.0, -0.6, 0.0, 0.3, 0.95, 1.0])
def test_cap_equals_quadrature(t, rng):
    n = 6
    d, w = _cap_grid(t)
    want_z = w @ np.asarray(sh_basis(jnp.asarray(d), n))  # ∫_cap Y_i
    zc = zonal_cap(jnp.asarray(t), n)
    np.testing.assert_allclose(zc, want_z[[l * l + l for l in range(n)]], atol=1e-13)
    # arbitrary axis: integrate over the same cap carried to the axis by a frame
    axis = random_dirs(rng, ())
    F = _frame(axis)
    want = w @ np.asarray(sh_basis(jnp.asarray(d @ F.T), n))
    np.testing.assert_allclose(cap(jnp.asarray(axis), jnp.asarray(t), n), want, atol=1e-13)


@pytest.mark.usefixtures("x64")
def test_cap_limits():
    whole = cap(jnp.asarray([0.0, 1.0, 0.0]), jnp.asarray(-1.0), 4)
    np.testing.assert_allclose(whole, np.eye(16)[0] * np.sqrt(4 * np.pi), atol=1e-15)
    np.testing.assert_allclose(cap(jnp.asarray([0.0, 1.0, 0.0]), jnp.asarray(1.0), 4), 0.0, atol=1e-15)


@pytest.mark.usefixtures("x64")
def test_clamped_cosine_equals_quadrature(rng):
    n = 7
    zc = zonal_clamped_cosine(n)
    np.testing.assert_allclose(
        zc[:3], [np.sqrt(np.pi) / 2, np.sqrt(np.pi / 3), np.sqrt(5 * np.pi) / 8], rtol=1e-15
    )
    np.testing.assert_allclose(zc[jnp.asarray([3, 5])], 0.0, atol=1e-15)
    d, w = hemisphere_grid(8, 16)  # exact for the degree-7 integrand z · Y_i on z >= 0
    for normal in [random_dirs(rng, ()), np.array([0, 0, -1.0]), np.array([0, 1.0, 0])]:
        dw = np.asarray(d) @ _frame(normal).T
        want = (w * (dw @ normal)) @ np.asarray(sh_basis(jnp.asarray(dw), n))
        np.testing.assert_allclose(clamped_cosine(jnp.asarray(normal), n), want, atol=1e-13)


@pytest.mark.usefixtures("x64")
def test_zonal_rotate_consistent_with_rotation(rng):
    # the zonal function about ẑ rotated by R equals the same profile about R ẑ
    z = jnp.asarray(rng.normal(size=5))
    axis = random_dirs(rng, ())
    F = _frame(axis)
    about_z = zonal_rotate(z, jnp.asarray([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(about_z[jnp.asarray([l * l + l for l in range(5)])], z, atol=1e-15)
    np.testing.assert_allclose(
        rotate(about_z, jnp.asarray(F)), zonal_rotate(z, jnp.asarray(axis)), atol=1e-13
    )


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("t", [-1.0, 1.0])
def test_cap_gradient_finite_at_endpoints(t):
    g = jax.jacrev(lambda c: zonal_cap(c, 5))(jnp.asarray(t))
    assert np.all(np.isfinite(g))
    # one-sided derivative d z_l / dt = -2π K_l0 P_l(t) = -sqrt(π(2l+1)) P_l(t), P_l(±1) = (±1)^l
    l = np.arange(5)
    np.testing.assert_allclose(g, -np.sqrt(np.pi * (2 * l + 1)) * t**l, atol=1e-13)


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("axis", AXES)
def test_gradients_finite_along_axes(axis):
    a = jnp.asarray(axis)
    for f in (
        lambda v: cap(v, jnp.asarray(0.4), 5),
        lambda v: clamped_cosine(v, 5),
        lambda v: zonal_rotate(jnp.ones(5), v),
    ):
        assert np.all(np.isfinite(jax.jacrev(f)(a)))
        assert np.all(np.isfinite(jax.jacfwd(f)(a)))


@pytest.mark.usefixtures("x64")
def test_gradient_three_ways(rng):
    axis = jnp.asarray(random_dirs(rng, ()))

    def f(t, v):
        return cap(v, t, 4)

    t0 = jnp.asarray(0.3)
    jf = jax.jacfwd(f, argnums=(0, 1))(t0, axis)
    jr = jax.jacrev(f, argnums=(0, 1))(t0, axis)
    h = 1e-6
    fd_t = (f(t0 + h, axis) - f(t0 - h, axis)) / (2 * h)
    fd_v = jnp.stack([(f(t0, axis + h * e) - f(t0, axis - h * e)) / (2 * h) for e in jnp.eye(3)], -1)
    for a, b in zip(jf, jr):
        np.testing.assert_allclose(a, b, atol=1e-12)
    np.testing.assert_allclose(jf[0], fd_t, atol=1e-8)
    np.testing.assert_allclose(jf[1], fd_v, atol=1e-8)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_batch_shapes(rng, shape):
    axis = jnp.asarray(random_dirs(rng, shape, np.float32))
    t = jnp.asarray(rng.uniform(-1, 1, size=shape).astype(np.float32))
    assert zonal_cap(t, 4).shape == (*shape, 4)
    np.testing.assert_allclose(zonal_cap_versine(1 - t, 4), zonal_cap(t, 4), atol=eps(jnp.float32, 10))
    c = cap(axis, t, 4)
    assert c.shape == (*shape, 16) and c.dtype == jnp.float32
    cc = clamped_cosine(axis, 4)
    assert cc.shape == (*shape, 16) and cc.dtype == jnp.float32
    # each batch element equals the unbatched call
    flat_axis, flat_t = axis.reshape(-1, 3), t.reshape(-1)
    tol = eps(jnp.float32, 10)
    for i in range(flat_t.shape[0]):
        np.testing.assert_allclose(c.reshape(-1, 16)[i], cap(flat_axis[i], flat_t[i], 4), rtol=tol, atol=tol)
    # a single cap angle broadcasts over a batch of axes
    assert cap(axis, jnp.asarray(0.5, jnp.float32), 4).shape == (*shape, 16)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_zonal_dot_is_the_inner_product_with_the_rotated_coefficients(x64, rng, shape):
    # the fused form against zonal_rotate's coefficients, values and gradients, batched; w shared
    # by the whole batch (one row) and per element
    axis = jnp.asarray(random_dirs(rng, shape, np.float64))
    z = jnp.asarray(rng.normal(size=(*shape, 4)))
    for w in (jnp.asarray(rng.normal(size=16)), jnp.asarray(rng.normal(size=(*shape, 16)))):
        got = zonal_dot(z, axis, w)
        want = jnp.sum(zonal_rotate(z, axis) * w, -1)
        assert got.shape == shape
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)
    args = (0, 1, 2)  # one compiled call for each side (op by op, the three took ~5 s)
    g_got = jax.jit(jax.grad(lambda *a: zonal_dot(*a).sum(), argnums=args))(z, axis, w)
    g_want = jax.jit(jax.grad(lambda z, a, w: jnp.sum(zonal_rotate(z, a) * w), argnums=args))(z, axis, w)
    for got, want in zip(g_got, g_want, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_zonal_dot_bad_shapes():
    with pytest.raises(ValueError, match="n² = 16"):
        zonal_dot(jnp.ones(4), jnp.asarray([0.0, 0.0, 1.0]), jnp.ones(9))
    with pytest.raises(ValueError, match="axis"):
        zonal_dot(jnp.ones(4), jnp.ones(2), jnp.ones(16))


def test_bad_input():
    with pytest.raises(ValueError, match="positive integer"):
        zonal_cap(jnp.asarray(0.5), 0)
    with pytest.raises(ValueError, match="floating"):
        zonal_cap(jnp.asarray(0), 3)
    with pytest.raises(ValueError, match="trailing axis"):
        zonal_rotate(jnp.ones(3), jnp.ones(2))
    with pytest.raises(ValueError, match="scalar"):
        zonal_rotate(jnp.ones(()), jnp.ones(3))


@pytest.mark.usefixtures("x64")
def test_python_number_takes_axis_dtype():
    # with x64 on, a Python float must not promote float32 axes to float64 (strict promotion)
    axis = jnp.asarray([0.0, 0.0, 1.0], jnp.float32)
    c = cap(axis, 0.5, 3)
    assert c.dtype == jnp.float32
    np.testing.assert_allclose(c[0], np.sqrt(np.pi) * 0.5, rtol=eps(jnp.float32))


def _cap_reference(t):
    """float64 z_l, l < 6, from scipy's Legendre polynomials at the given t."""
    t = np.float64(t)
    rest = [
        np.sqrt(np.pi / (2 * l + 1)) * (eval_legendre(l - 1, t) - eval_legendre(l + 1, t))
        for l in range(1, 6)
    ]
    return np.array([np.sqrt(np.pi) * (1 - t), *rest])


@pytest.mark.parametrize("alpha", [1.0, 0.1, 0.01, 0.003])
def test_small_caps_accurate_in_float32(alpha):
    # same float32 input, exact arithmetic as reference: no cancellation for small caps
    t32 = np.float32(np.cos(alpha))
    got = np.asarray(zonal_cap(jnp.asarray(t32), 6))
    np.testing.assert_allclose(got, _cap_reference(t32), rtol=eps(jnp.float32))
    u32 = np.float32(2 * np.sin(alpha / 2) ** 2)
    got_v = np.asarray(zonal_cap_versine(jnp.asarray(u32), 6))
    np.testing.assert_allclose(got_v, _cap_reference(1 - np.float64(u32)), rtol=eps(jnp.float32))


@pytest.mark.usefixtures("x64")
def test_branches_agree_at_the_switch():
    # the u-series (t >= 0.9) and the recurrence are the same polynomial: check both sides
    for t in [0.9 - 1e-12, 0.9, 0.95, 0.3, -0.7]:
        np.testing.assert_allclose(zonal_cap(jnp.asarray(t), 8)[:6], _cap_reference(t), atol=1e-13)
        np.testing.assert_allclose(
            zonal_cap_versine(jnp.asarray(1 - t), 8), zonal_cap(jnp.asarray(t), 8), atol=1e-13
        )
