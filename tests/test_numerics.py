"""NaN-safety of the safe_* helpers: values and jax.grad at each singular point."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jshadow._numerics import (
    eps,
    fast_acos,
    fast_atan2,
    fast_sin,
    safe_acos,
    safe_atan2,
    safe_div,
    safe_norm,
    safe_normalize,
    safe_sqrt,
    select_max,
    select_min,
    small_sum,
)


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


@pytest.mark.parametrize("shape", [(), (1,), (3, 1, 2)])
def test_fast_atan2_matches_arctan2_in_float32(shape):
    # every octant, both axes, signed zeros and the origin; then random points
    ang = np.linspace(-np.pi, np.pi, 20001)
    y = np.concatenate([np.sin(ang), [0.0, -0.0, 1.0, -1.0, 0.0, 0.0, 1e-30, 3.0]])
    x = np.concatenate([np.cos(ang), [1.0, 1.0, 0.0, 0.0, -1.0, 0.0, -1.0, 3.0]])
    y32, x32 = jnp.asarray(y, jnp.float32), jnp.asarray(x, jnp.float32)
    got = fast_atan2(y32, x32)
    assert got.dtype == jnp.float32
    want = np.arctan2(np.asarray(y32, np.float64), np.asarray(x32, np.float64))
    want[(y == 0) & (x == 0)] = 0.0
    err = np.abs(np.asarray(got, np.float64) - want)
    err = np.minimum(err, 2 * np.pi - err)  # ±π is one angle
    assert err.max() < 4e-7, err.max()  # measured 3.1e-7: about one float32 ulp (2.4e-7) at ±π
    rng = np.random.default_rng(0)
    yr, xr = (jnp.asarray(rng.normal(size=shape), jnp.float32) for _ in range(2))
    out = fast_atan2(yr, xr)
    assert out.shape == shape
    np.testing.assert_allclose(out, np.arctan2(np.asarray(yr), np.asarray(xr)), atol=4e-7)


@pytest.mark.parametrize("shape", [(), (1,), (3, 1, 2)])
def test_fast_sin_matches_sin_on_its_range(shape):
    # float32 over [−π, π] (the folds at ±π/2 and the ends included) and its derivative, cos x, from
    # the same polynomial; float64 is jnp.sin itself
    x = jnp.asarray(
        np.concatenate([np.linspace(-np.pi, np.pi, 200001), [0.5 * np.pi, -0.5 * np.pi]]), jnp.float32
    )
    x64 = np.asarray(x, np.float64)
    got = fast_sin(x)
    assert got.dtype == jnp.float32
    assert np.abs(np.asarray(got, np.float64) - np.sin(x64)).max() < 2.4e-7  # measured 1.6e-7
    d = jax.vmap(jax.grad(fast_sin))(x[::50])
    assert np.abs(np.asarray(d, np.float64) - np.cos(x64[::50])).max() < 2.4e-7
    xs = jnp.asarray(np.random.default_rng(1).uniform(-np.pi, np.pi, size=shape), jnp.float32)
    out = fast_sin(xs)
    assert out.shape == shape
    np.testing.assert_allclose(out, np.sin(np.asarray(xs, np.float64)), atol=2.4e-7)
    with jax.enable_x64(True):
        v = jnp.asarray([0.3, 3.0, -2.0])
        np.testing.assert_array_equal(fast_sin(v), jnp.sin(v))
        np.testing.assert_allclose(
            jax.grad(lambda t: fast_sin(t).sum())(v), np.cos([0.3, 3.0, -2.0]), rtol=1e-15
        )


@pytest.mark.usefixtures("x64")
def test_fast_atan2_float64_and_exact_derivative():
    np.testing.assert_allclose(fast_atan2(1.0, -1.0), 3 * np.pi / 4, rtol=1e-15)
    # the derivative is the exact one, not the polynomial's, also in float32
    for dtype, tol in ((jnp.float64, 1e-13), (jnp.float32, 1e-6)):
        y, x = jnp.asarray(0.3, dtype), jnp.asarray(-0.7, dtype)
        gy, gx = jax.grad(fast_atan2, argnums=(0, 1))(y, x)
        r2 = 0.3**2 + 0.7**2
        np.testing.assert_allclose([gy, gx], [-0.7 / r2, -0.3 / r2], rtol=tol)
    g = jax.grad(fast_atan2, argnums=(0, 1))(0.0, 0.0)  # the origin: zero, not NaN
    assert [float(v) for v in g] == [0.0, 0.0]
    g32 = jax.grad(fast_atan2, argnums=(0, 1))(jnp.float32(0.0), jnp.float32(0.0))
    assert [float(v) for v in g32] == [0.0, 0.0]


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_fast_acos_matches_and_is_finite_at_the_ends(dtype):
    with jax.enable_x64(dtype == jnp.float64):
        c = jnp.asarray(np.r_[np.linspace(-1, 1, 4001), [1.0 + 1e-6, -1.0 - 1e-6]], dtype)
        tol = 4e-7 if dtype == jnp.float32 else 1e-14
        np.testing.assert_allclose(fast_acos(c), safe_acos(c), atol=tol)
        for end in (1.0, -1.0):
            g = jax.grad(fast_acos)(jnp.asarray(end, dtype))
            assert np.isfinite(g)
        g = jax.grad(fast_acos)(jnp.asarray(0.3, dtype))
        np.testing.assert_allclose(g, -1 / np.sqrt(1 - 0.09), rtol=1e-6)


@pytest.mark.parametrize("shape, axis", [((5, 3), -1), ((3,), 0), ((2, 4, 3), 1), ((2, 6), -1), ((1, 1), 0)])
@pytest.mark.parametrize("keepdims", [False, True])
def test_small_sum_is_jnp_sum(shape, axis, keepdims):
    # unrolled for axes of length <= 4 (6 takes jnp.sum), the same numbers and shapes
    x = jnp.asarray(np.random.default_rng(0).normal(size=shape), jnp.float32)
    got, want = small_sum(x, axis, keepdims), jnp.sum(x, axis=axis, keepdims=keepdims)
    assert got.shape == want.shape
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)
    g = jax.grad(lambda x: (small_sum(x, axis, keepdims) ** 2).sum())(x)
    np.testing.assert_allclose(
        g, 2 * jnp.broadcast_to(jnp.sum(x, axis=axis, keepdims=True), shape), rtol=1e-6
    )


@pytest.mark.parametrize("shape, axis", [((5,), 0), ((1, 4), -1), ((3, 1, 2, 6), -1), ((3, 7, 2), 1)])
@pytest.mark.parametrize("kind", ["max", "min"])
def test_select_max_and_min_are_the_reductions_with_one_hot_gradients(shape, axis, kind):
    select, ref, arg = {
        "max": (select_max, jnp.max, jnp.argmax),
        "min": (select_min, jnp.min, jnp.argmin),
    }[kind]
    x = jnp.asarray(np.random.default_rng(1).normal(size=shape), jnp.float32)
    want = ref(x, axis=axis)
    np.testing.assert_array_equal(select(x, axis), want)
    weights = jnp.arange(1.0, 1.0 + want.size).reshape(want.shape)
    g = jax.grad(lambda x: jnp.sum(select(x, axis) * weights))(x)
    # every slice along ``axis`` sends its whole cotangent to its extreme element
    hot = jax.nn.one_hot(arg(x, axis=axis), x.shape[axis], axis=axis)
    np.testing.assert_array_equal(g, hot * jnp.expand_dims(weights, axis))


def test_select_max_splits_ties_equally_and_stays_finite_for_any_rounding():
    x = jnp.asarray([2.0, -1.0, 2.0, 2.0])
    third = 1.0 / 3.0
    np.testing.assert_allclose(jax.grad(select_max)(x), [third, 0.0, third, third], rtol=1e-6)
    np.testing.assert_allclose(jax.grad(select_min)(-x), [third, 0.0, third, third], rtol=1e-6)
    np.testing.assert_allclose(jax.grad(select_max)(jnp.zeros(3)), [third] * 3, rtol=1e-6)
    # central differences of a tied maximum measure the average of the tied derivatives
    a = jnp.asarray([1.0, 1.0], jnp.float64 if jax.config.jax_enable_x64 else jnp.float32)
    slope = jnp.asarray([1.0, 3.0], a.dtype)

    def f(t):
        return select_max(a + t * slope)

    h = 1e-2
    fd = (float(f(h)) - float(f(-h))) / (2 * h)
    np.testing.assert_allclose(float(jax.grad(f)(0.0)), fd, rtol=1e-5)  # both 2, not 1 or 3


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_select_max_counts_values_within_rounding_of_the_maximum_as_ties(dtype):
    # mirror-image vertices of a symmetric mesh end up one rounding unit apart: that is a tie
    with jax.enable_x64(dtype == jnp.float64):
        top = np.asarray(0.75, dtype)
        below = np.nextafter(top, np.asarray(0.0, dtype))
        x = jnp.asarray([below, 0.5, top], dtype)
        np.testing.assert_allclose(jax.grad(select_max)(x), [0.5, 0.0, 0.5], rtol=1e-6)
        # ... but not a difference of ten rounding units (the widening of with_center_anchors)
        far = np.asarray(top - eps(dtype) * top, dtype)
        y = jnp.asarray([far, 0.5, top], dtype)
        np.testing.assert_array_equal(jax.grad(select_max)(y), [0.0, 0.0, 1.0])
        np.testing.assert_array_equal(jax.grad(select_min)(-y), [0.0, 0.0, 1.0])
