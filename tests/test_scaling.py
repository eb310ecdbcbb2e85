"""Tests of jshadow.scaling: f_k, the SRF Jacobian, M_k matrices and tables.

Independent checks: the paper's atan form of f_k, finite differences, a brute-force 2-D sphere
quadrature of M_k, and direct projection of rescaled test functions (caps, a smooth lobe, a
box-shaped binary region) by a quadrature split at their discontinuities.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import BATCH_SHAPES
from scipy.special import lpmv

from jshadow._numerics import eps
from jshadow.scaling import (
    MkTable,
    f_k,
    f_k_inverse,
    mk_apply,
    mk_apply_table,
    mk_apply_zonal,
    mk_bracket,
    mk_in_range,
    mk_interpolate,
    mk_matrix,
    mk_pattern,
    mk_table,
    mk_zonal_table,
    srf_jacobian,
)
from jshadow.sh import sh_basis_spherical, sh_lm

MODELS = ["paper", "sphere"]
KS = [0.1, 0.5, 1.0, 2.0, 7.0]


# ---- f_k -----------------------------------------------------------------------------------------


@pytest.mark.usefixtures("x64")
def test_f_k_is_the_papers_atan_form():
    theta = np.linspace(0.01, math.pi - 0.01, 301)
    theta = theta[np.abs(theta - math.pi / 2) > 1e-3]
    for k in [0.125, 0.5, 0.9, 1.5, 5.0]:
        t = np.tan(theta)
        den = 1.0 + t - k * t
        ok = np.abs(den) > 1e-3
        ref = np.arctan(k * t / den)
        ref = np.where(ref < 0, ref + math.pi, ref)
        got = np.asarray(f_k(jnp.asarray(theta), k))
        np.testing.assert_allclose(got[ok], ref[ok], atol=1e-12)
        assert np.all(np.diff(got) > 0), "f_k must be increasing on [0, π]"


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("model", MODELS)
def test_f_k_inverse_is_the_inverse(model):
    theta = jnp.linspace(0.0, math.pi, 181)
    for k in KS:
        back = f_k(f_k_inverse(theta, k, model), k, model)
        np.testing.assert_allclose(back, theta, atol=1e-10)
        np.testing.assert_allclose(f_k(theta, k, model)[jnp.array([0, -1])], [0.0, math.pi], atol=1e-12)
    np.testing.assert_allclose(f_k(theta, 1.0, model), theta, atol=1e-12)


@pytest.mark.usefixtures("x64")
def test_silhouette_direction_of_a_unit_sphere():
    # A unit sphere (= its bounding sphere, r = 1): on the shell its silhouette is at 90°. From d = 2
    # (k = 1/2) the warp V_d(θ) = V_r(f_{1/k}(θ)) puts it at the θ with f_2(θ) = 90°, i.e. 45°.
    k = 0.5
    assert float(f_k_inverse(math.pi / 4, k)) == pytest.approx(math.pi / 2, abs=1e-12)
    assert float(f_k(math.pi / 2, k)) == pytest.approx(math.pi / 4, abs=1e-12)
    # the paper's Sec. 4.1 form V_r(f_k(θ)) would put it at f_{1/2}⁻¹(90°) = f_2(90°) > 90°: wrong side
    assert float(f_k(math.pi / 2, 1.0 / k)) > math.pi / 2
    # the true silhouette is at asin(1/2) = 30°; the sphere model gets it exactly
    assert float(f_k(math.pi / 2, k, "sphere")) == pytest.approx(math.pi / 6, abs=1e-12)


@pytest.mark.usefixtures("x64")
def test_sphere_model_is_exact_for_concentric_spheres():
    r = 1.0
    for rho in [0.2, 0.6, 0.95]:
        for d in [rho * 1.05, 0.7, 1.0, 1.8, 6.0]:
            if d <= rho:
                continue
            got = float(f_k(math.asin(rho / r), r / d, "sphere"))
            assert got == pytest.approx(math.asin(rho / d), abs=1e-10)


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("model", MODELS)
def test_srf_jacobian_is_fprime_sin_f_over_sin(model):
    theta = jnp.linspace(0.05, math.pi - 0.05, 37)
    for k in [0.2, 0.8, 1.0, 1.7, 4.0]:
        fp = jax.vmap(jax.grad(lambda t, k=k: f_k(t, k, model)))(theta)
        ref = fp * jnp.sin(f_k(theta, k, model)) / jnp.sin(theta)
        got = srf_jacobian(theta, k, model)
        # exclude the sphere model's kink (one-sided derivatives differ there)
        if model == "sphere":
            ta = math.pi / 2 if k <= 1 else math.asin(1 / k)
            keep = jnp.abs(theta - ta) > 0.03
            ref, got = ref[keep], got[keep]
        np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-12)
    # closed-form limits of the paper's model: k² at both poles
    np.testing.assert_allclose(srf_jacobian(jnp.array([0.0, math.pi]), 0.3), [0.09, 0.09], rtol=1e-12)


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("model", MODELS)
def test_jacobian_preserves_solid_angle(model):
    # ∫_0^π J(θ) sin θ dθ = ∫_0^π sin u du = 2 for the map θ ↦ f_k(θ)
    x, w = np.polynomial.legendre.leggauss(400)
    for k in [0.3, 2.5]:
        kink = math.pi / 2 if k <= 1 else math.asin(1 / k)  # sphere model: 1/sqrt singularity for k > 1
        u = jnp.linspace(0, math.pi, 33)
        breaks = np.unique([0.0, kink, math.pi, *np.asarray(f_k_inverse(u, k, model))])
        total = 0.0
        for a, b in zip(breaks[:-1], breaks[1:]):
            if b == kink:  # θ = b − (b − a)·s² removes the 1/sqrt(b − θ) singularity
                sg, wg = 0.5 * (x + 1), 0.5 * w
                th, wt = b - (b - a) * sg**2, wg * 2 * (b - a) * sg
            else:
                th, wt = 0.5 * (b - a) * x + 0.5 * (a + b), 0.5 * (b - a) * w
            total += np.sum(wt * np.asarray(srf_jacobian(jnp.asarray(th), k, model)) * np.sin(th))
        assert total == pytest.approx(2.0, abs=1e-9)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("model", MODELS)
def test_no_nan_in_value_or_gradient_at_singular_points(dtype, model):
    with jax.enable_x64(dtype == jnp.float64):
        thetas = [0.0, math.pi / 4, math.pi / 2, math.pi]
        ks = [0.0, 1e-7, 0.5, 1.0, 2.0, 1e6]
        th = jnp.asarray([t for t in thetas for _ in ks], dtype)
        kk = jnp.asarray([k for _ in thetas for k in ks], dtype)
        for fn in (f_k, f_k_inverse, srf_jacobian):
            val = fn(th, kk, model)
            assert val.dtype == dtype
            assert bool(jnp.all(jnp.isfinite(val))), fn.__name__
            g_t, g_k = jax.jit(jax.vmap(jax.grad(lambda t, k, fn=fn: fn(t, k, model), argnums=(0, 1))))(
                th, kk
            )
            assert bool(jnp.all(jnp.isfinite(g_t))) and bool(jnp.all(jnp.isfinite(g_k))), fn.__name__
        # range: f_k maps [0, π] onto [0, π] even in float32 (sin(float32(π)) < 0)
        v = f_k(jnp.asarray([0.0, math.pi], dtype), jnp.asarray([0.5, 0.5], dtype), model)
        np.testing.assert_allclose(v, [0.0, math.pi], atol=eps(dtype, 10))
        # paper model: f_k'(0) = f_k'(π) = k
        if model == "paper":
            g = jax.vmap(jax.grad(f_k))(jnp.asarray([0.0, math.pi], dtype), jnp.asarray([0.5, 0.5], dtype))
            np.testing.assert_allclose(g, [0.5, 0.5], rtol=eps(dtype, 100))


@pytest.mark.usefixtures("x64")
def test_f_k_gradients_three_ways():
    th = jnp.asarray([0.3, 1.2, 2.5])
    k = jnp.asarray([0.4, 1.0, 3.0])

    @jax.jit
    def fn(p):
        return f_k(p[:3], p[3:]) + srf_jacobian(p[:3], p[3:])

    p = jnp.concatenate([th, k])
    jf, jr = jax.jacfwd(fn)(p), jax.jacrev(fn)(p)
    h = 1e-6
    fd = np.stack([(fn(p.at[i].add(h)) - fn(p.at[i].add(-h))) / (2 * h) for i in range(6)], axis=1)
    np.testing.assert_allclose(jf, jr, atol=1e-12)
    np.testing.assert_allclose(jf, fd, atol=1e-7)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_f_k_batch_shapes(shape, rng):
    th = jnp.asarray(rng.uniform(0, math.pi, shape), jnp.float32)
    assert f_k(th, 0.5).shape == shape
    assert srf_jacobian(th, jnp.full(shape, 2.0, jnp.float32), "sphere").shape == shape
    with pytest.raises(ValueError, match="model"):
        f_k(th, 0.5, "cube")


# ---- M_k -----------------------------------------------------------------------------------------


def _gl(a, b, num):
    x, w = np.polynomial.legendre.leggauss(num)
    return 0.5 * (b - a) * x + 0.5 * (a + b), 0.5 * (b - a) * w


def _pieces(breaks, num):
    breaks = np.unique(np.clip(np.asarray(breaks, float), breaks[0], breaks[-1]))
    ts, ws = zip(*[_gl(a, b, num) for a, b in zip(breaks[:-1], breaks[1:])])
    return np.concatenate(ts), np.concatenate(ws)


_f_k = jax.jit(f_k, static_argnums=2)
_f_k_inverse = jax.jit(f_k_inverse, static_argnums=2)


def _basis(theta, phi, n):
    """Real SH (..., n²) in numpy from scipy's associated Legendre functions (an independent route)."""
    x = np.cos(theta)
    out = np.zeros((*np.shape(theta), n * n))
    for l in range(n):
        for m in range(l + 1):
            k = math.sqrt((2 * l + 1) / (4 * math.pi) * math.factorial(l - m) / math.factorial(l + m))
            p = (-1) ** m * lpmv(m, l, x)  # scipy includes the Condon–Shortley phase; remove it
            if m == 0:
                out[..., l * l + l] = k * p
            else:
                out[..., l * l + l + m] = math.sqrt(2) * k * p * np.cos(m * phi)
                out[..., l * l + l - m] = math.sqrt(2) * k * p * np.sin(m * phi)
    return out


def test_independent_basis_agrees_with_jshadow(rng):
    th, ph = rng.uniform(0, math.pi, 50), rng.uniform(-math.pi, math.pi, 50)
    with jax.enable_x64(True):
        np.testing.assert_allclose(
            _basis(th, ph, 5), sh_basis_spherical(jnp.asarray(th), jnp.asarray(ph), 5), atol=1e-12
        )


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("model", MODELS)
def test_mk_matches_brute_force_sphere_quadrature(model):
    n = 4
    for k in [0.35, 2.2]:
        for kind in ["occlusion", "radiance_jacobian"]:
            th_breaks = [0.0, *np.asarray(_f_k(jnp.linspace(0, math.pi, 17), k, model))[1:-1], math.pi]
            if model == "sphere":
                kink = math.pi / 2 if 1 / k <= 1 else math.asin(k)
                # J has a 1/sqrt singularity left of the kink when 1/k > 1: refine geometrically
                th_breaks += [kink, *(kink * (1 - 2.0 ** -np.arange(1, 41)))]
            th, wt = _pieces(sorted(th_breaks), 60)
            phi = (np.arange(16) + 0.5) * (2 * math.pi / 16)
            T, P = np.meshgrid(th, phi, indexing="ij")
            W = (wt * np.sin(th))[:, None] * (2 * math.pi / 16)
            warped = np.asarray(_f_k_inverse(jnp.asarray(T), k, model))
            if kind == "radiance_jacobian":
                W = W * np.asarray(srf_jacobian(jnp.asarray(T), 1 / k, model))
            y_i, y_j = _basis(T, P, n), _basis(warped, P, n)
            brute = np.einsum("tpi,tpj,tp->ij", y_i, y_j, W)
            tol = 1e-9 if (model == "paper" or kind == "occlusion") else 5e-4  # 1/sqrt singularity
            np.testing.assert_allclose(mk_matrix(k, n, kind, model), brute, atol=tol)


@pytest.mark.parametrize("model", MODELS)
def test_m1_is_identity(model):
    for kind in ["occlusion", "radiance", "radiance_jacobian"]:
        np.testing.assert_allclose(mk_matrix(1.0, 5, kind, model), np.eye(25), atol=1e-13)


def test_sparsity_pattern_counts_and_independence_of_k():
    for n in range(1, 8):
        rows, cols = mk_pattern(n)
        q = n - 1
        assert (
            len(rows)
            == sum((n - abs(m)) ** 2 for m in range(-q, n))
            == (q + 1) * (2 * q * q + 4 * q + 3) // 3
        )
        assert all(sh_lm(i)[1] == sh_lm(j)[1] for i, j in zip(rows, cols))
    assert len(mk_pattern(4)[0]) == 44
    for kind in ["occlusion", "radiance", "radiance_jacobian"]:
        rows, cols = mk_pattern(4, kind)
        assert len(rows) == 41
        mask = np.zeros((16, 16), bool)
        mask[rows, cols] = True
        for model in MODELS:
            for k in [0.13, 0.6, 1.7, 4.2]:
                m = mk_matrix(k, 4, kind, model)
                assert np.all(m[~mask] == 0.0)
                assert np.all(np.abs(m[mask]) > 1e-6), (kind, model, k, np.abs(m[mask]).min())


def test_constants_and_integrals():
    rng = np.random.default_rng(0)
    c = rng.normal(size=16)
    e0 = np.eye(16)[0]
    for model in MODELS:
        for k in [0.1, 0.45, 3.0]:
            m_occ = mk_matrix(k, 4, "occlusion", model)
            m_jac = mk_matrix(k, 4, "radiance_jacobian", model)
            np.testing.assert_allclose(m_occ @ e0, e0, atol=1e-14)  # V ≡ 1 stays 1
            np.testing.assert_array_equal(mk_matrix(k, 4, "radiance", model), m_occ)
            # the Jacobian variant keeps ∫ f dω = sqrt(4π)·c0 for every f; the plain warp does not
            assert (m_jac @ c)[0] == pytest.approx(c[0], abs=1e-13)
            assert abs((m_occ @ c)[0] - c[0]) > 1e-3
            assert np.linalg.norm(m_jac @ e0 - e0) > 1e-2  # ... and a constant does not stay constant


def _test_function(name):
    """(f(θ, φ) -> values, θ breakpoints, φ breakpoints) of a test function in the local frame.

    The binary ones are visibilities, 1 − indicator of an occluded region around the local +z.
    """
    if name == "cap":
        a = math.radians(60)
        return (lambda t, p: (t > a).astype(float)), [a], []
    if name == "box":
        a, b = math.radians(70), math.radians(50)
        return (lambda t, p: 1.0 - ((t <= a) & (np.abs(np.angle(np.exp(1j * p))) <= b))), [a], [-b, b]
    return (lambda t, p: np.exp(3 * (np.cos(t) - 1)) * (1 + 0.4 * np.sin(t) * np.cos(p))), [], []


def _project(fn, th_breaks, ph_breaks, n, k=None, model="paper"):
    """SH (n²) of fn, or of fn∘(θ ↦ f_{1/k}(θ)) when k is given, by split GL × GL quadrature."""
    if k is not None:
        th_breaks = list(np.asarray(_f_k(jnp.asarray(th_breaks, float), k, model))) + list(
            np.asarray(_f_k(jnp.linspace(0, math.pi, 9), k, model))
        )
    th, wt = _pieces([0.0, *th_breaks, math.pi], 40)
    ph, wp = _pieces([-math.pi, *ph_breaks, math.pi], 24)
    T, P = np.meshgrid(th, ph, indexing="ij")
    src = T if k is None else np.asarray(_f_k_inverse(jnp.asarray(T), k, model))
    W = (wt * np.sin(th))[:, None] * wp[None, :]
    return np.einsum("tp,tpi->i", fn(src, P) * W, _basis(T, P, n))


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("name", ["cap", "box", "lobe"])
def test_mk_equals_direct_projection_up_to_truncation(name):
    # M_k applied to the N-band projection of f vs the direct projection of the rescaled f, compared
    # on the first 16 coefficients: the difference is the truncation of f before the warp.
    fn, tb, pb = _test_function(name)
    s16 = _project(fn, tb, pb, 16)
    errors = {}
    for k in [0.4, 1.6]:
        direct = _project(fn, tb, pb, 4, k)
        for n_proj in [4, 8, 16]:
            got = (mk_matrix(k, n_proj) @ s16[: n_proj * n_proj])[:16]
            errors[k, n_proj] = float(np.linalg.norm(got - direct) / np.linalg.norm(direct))
    print(f"\n{name}: relative L2 error of the first 16 coefficients, by projection bands:", errors)
    for k in [0.4, 1.6]:
        assert errors[k, 16] < errors[k, 8] < errors[k, 4], errors  # a truncation error: shrinks with bands
        bound = {"cap": 0.25, "box": 0.15, "lobe": 0.25}[name]
        assert errors[k, 4] < bound, errors


# ---- tables ----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def table64():
    with jax.enable_x64(True):
        return mk_table(n=4, num=16, d_min=0.2, d_max=8.0, dtype=jnp.float64)


@pytest.mark.usefixtures("x64")
def test_table_nodes_and_interpolation_error(table64):
    t = table64
    assert isinstance(t, MkTable) and t.values.shape == (16, 41)
    d = np.asarray(t.distances)
    np.testing.assert_allclose(d[[0, -1]], [8.0, 0.2], rtol=1e-14)
    assert 1.0 in d  # the shell itself is a node (M = I there)
    i = int(np.flatnonzero(d == 1.0)[0])  # geometric on each side of the shell
    for part in (d[: i + 1], d[i:]):
        np.testing.assert_allclose(part[:-1] / part[1:], part[0] / part[1], rtol=1e-12)
    np.testing.assert_allclose(mk_interpolate(t, jnp.asarray(1.0)), np.eye(16), atol=1e-14)
    ks = np.asarray(t.ks)
    np.testing.assert_allclose(mk_interpolate(t, jnp.asarray(ks[5])), mk_matrix(ks[5]), atol=1e-14)
    mids = 0.5 * (ks[:-1] + ks[1:])
    errs = np.array(
        [np.abs(np.asarray(mk_interpolate(t, jnp.asarray(k))) - mk_matrix(k)).max() for k in mids]
    )
    print("\nmax |M_interp − M_k| at midpoints (d = 1/k):", dict(zip(np.round(1 / mids, 3), errs.round(4))))
    assert errs.max() < 0.06
    assert errs[1 / mids > 1.0].max() < 0.05  # outside the shell (largest just beyond it)


@pytest.mark.usefixtures("x64")
def test_in_range_and_clamping(table64):
    k = jnp.asarray([1 / 9.0, 1 / 8.0, 1.0, 5.0, 50.0])
    np.testing.assert_array_equal(mk_in_range(table64, k), [False, True, True, True, True])
    np.testing.assert_allclose(mk_interpolate(table64, 50.0), mk_interpolate(table64, 5.0), atol=0)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_apply_equals_dense_and_batches(shape, table64, rng):
    with jax.enable_x64(True):
        k = jnp.asarray(rng.uniform(0.1, 6.0, shape))
        c = jnp.asarray(rng.normal(size=(*shape, 16)))
        got = mk_apply(table64, k, c)
        assert got.shape == (*shape, 16)
        ref = jnp.einsum("...ij,...j->...i", mk_interpolate(table64, k), c)
        np.testing.assert_allclose(got, ref, atol=1e-13)
        # broadcasting: one k for many coefficient vectors, and fewer bands than the table
        got3 = mk_apply(table64, 0.7, c[..., :9])
        np.testing.assert_allclose(
            got3, jnp.einsum("ij,...j->...i", mk_interpolate(table64, 0.7)[:9, :9], c[..., :9])
        )
    # float32 tables and coefficients
    t32 = MkTable(
        ks=table64.ks.astype(jnp.float32),
        values=table64.values.astype(jnp.float32),
        rows=table64.rows,
        cols=table64.cols,
        n=4,
    )
    out = mk_apply(t32, jnp.asarray(np.asarray(k), jnp.float32), jnp.asarray(np.asarray(c), jnp.float32))
    assert out.dtype == jnp.float32
    np.testing.assert_allclose(out, np.asarray(ref), rtol=1e-4, atol=1e-4)


@pytest.mark.usefixtures("x64")
def test_apply_gradients(table64, rng):
    c = jnp.asarray(rng.normal(size=16))

    @jax.jit
    def fn(p):
        return mk_apply(table64, p[0], p[1:])

    p = jnp.concatenate([jnp.asarray([0.61]), c])
    jf, jr = jax.jacfwd(fn)(p), jax.jacrev(fn)(p)
    h = 1e-6
    fd = np.stack([(fn(p.at[i].add(h)) - fn(p.at[i].add(-h))) / (2 * h) for i in range(17)], axis=1)
    np.testing.assert_allclose(jf, jr, atol=1e-12)
    np.testing.assert_allclose(jf, fd, atol=1e-7)
    assert np.linalg.norm(jf[:, 0]) > 1e-3  # M_k does depend on k


def test_validation():
    with pytest.raises(ValueError, match="kind"):
        mk_table(kind="light")
    with pytest.raises(ValueError, match="model"):
        mk_matrix(0.5, model="cube")
    with pytest.raises(ValueError, match="d_min"):
        mk_table(d_min=2.0, d_max=1.0)
    with pytest.raises(ValueError, match="positive"):
        mk_matrix(-1.0)
    t = mk_table(n=2, num=2)
    with pytest.raises(ValueError, match="bands"):
        mk_apply(t, 0.5, jnp.zeros(9, jnp.float32))
    with pytest.raises(ValueError, match="square"):
        mk_apply(t, 0.5, jnp.zeros(3, jnp.float32))


def test_apply_gradient_finite_at_nodes_and_outside_range(table64):
    with jax.enable_x64(True):
        ks = np.asarray(table64.ks)
        k = jnp.asarray([ks[0], ks[5], ks[-1], ks[0] / 2, ks[-1] * 2])
        c = jnp.ones((5, 16))

        @jax.jit  # the table is a pytree argument
        def fn(table, k, c):
            return jnp.sum(mk_apply(table, k, c) * jnp.arange(16.0))

        g_k, g_c = jax.grad(fn, argnums=(1, 2))(table64, k, c)
        assert bool(jnp.all(jnp.isfinite(g_k))) and bool(jnp.all(jnp.isfinite(g_c)))
        np.testing.assert_array_equal(g_k[3:], [0.0, 0.0])  # clamped outside the table
        assert float(jnp.abs(g_k[1])) > 0


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_apply_table_and_bracket_equal_apply(shape, table64, rng):
    # applying every tabulated M_{k_t} once and interpolating the results is mk_apply, exactly
    with jax.enable_x64(True):
        ks = np.asarray(table64.ks)
        k = jnp.asarray(rng.uniform(0.05, 8.0, shape))  # inside and on both sides of the range
        c = jnp.asarray(rng.normal(size=(*shape, 16)))
        t, w = mk_bracket(table64, k)
        assert t.shape == w.shape == shape and t.dtype == jnp.int32
        assert bool(jnp.all((t >= 0) & (t <= len(ks) - 2) & (w >= 0) & (w <= 1)))
        np.testing.assert_allclose((1 - w) * ks[t] + w * ks[t + 1], np.clip(np.asarray(k), ks[0], ks[-1]))
        # one coefficient set for every receiver (the field's case) ...
        c0 = c.reshape(-1, 16)[0]
        ext = mk_apply_table(table64, c0)  # (K, 16)
        assert ext.shape == (len(ks), 16)
        got = (1 - w)[..., None] * ext[t] + w[..., None] * ext[t + 1]
        np.testing.assert_allclose(got, mk_apply(table64, k, c0), atol=1e-13)
        # ... and a batch of sets, truncated to fewer output bands (rows are independent)
        ext_b = mk_apply_table(table64, c, out_bands=3)
        assert ext_b.shape == (len(ks), *shape, 9)
        np.testing.assert_allclose(ext_b[5], mk_apply(table64, ks[5], c)[..., :9], atol=1e-13)
    with pytest.raises(ValueError, match="out_bands"):
        mk_apply_table(table64, c0, out_bands=5)


@pytest.mark.usefixtures("x64")
def test_bracket_at_nodes_and_its_gradient(table64):
    ks = np.asarray(table64.ks)
    t, w = mk_bracket(table64, jnp.asarray(ks))
    np.testing.assert_allclose((1 - w) * ks[t] + w * ks[t + 1], ks, rtol=1e-14)
    g = jax.grad(lambda k: mk_bracket(table64, k)[1])
    assert float(g(ks[3] * 1.01)) == pytest.approx(1 / (ks[4] - ks[3]), rel=1e-12)
    assert float(g(ks[-1] * 2)) == 0.0 and float(g(ks[0] / 2)) == 0.0  # clamped


# ---- zonal tables ----------------------------------------------------------------------------------


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("kind", ["radiance", "radiance_jacobian"])
@pytest.mark.parametrize("model", MODELS)
def test_zonal_table_is_the_m0_block_of_mk(kind, model):
    n = 6
    t = mk_zonal_table(n, num=5, d_min=0.3, d_max=9.0, kind=kind, model=model, dtype=jnp.float64)
    assert t.zonal and t.n == n
    zon = np.asarray([l * l + l for l in range(n)])
    blocks = np.asarray(mk_interpolate(t, t.ks))  # at the table's own ratios: no interpolation
    assert blocks.shape == (5, n, n)
    for k, block in zip(np.asarray(t.ks), blocks, strict=True):
        np.testing.assert_allclose(block, mk_matrix(k, n, kind, model)[np.ix_(zon, zon)], atol=1e-12)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_apply_zonal_equals_the_dense_block_and_batches(shape, rng):
    t = mk_zonal_table(8, num=6, d_min=0.5, d_max=6.0)
    k = jnp.asarray(rng.uniform(0.2, 1.8, shape), jnp.float32)
    z = jnp.asarray(rng.normal(size=(*shape, 8)), jnp.float32)
    got = mk_apply_zonal(t, k, z, 3)
    assert got.shape == (*shape, 3)
    want = np.einsum("...ij,...j->...i", np.asarray(mk_interpolate(t, k)), np.asarray(z))[..., :3]
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)
    # fewer input bands use the leading columns of the block
    np.testing.assert_allclose(
        mk_apply_zonal(t, k, z[..., :5]),
        np.einsum("...ij,...j->...i", np.asarray(mk_interpolate(t, k))[..., :5, :5], np.asarray(z[..., :5])),
        rtol=1e-5,
        atol=1e-5,
    )


@pytest.mark.usefixtures("x64")
def test_apply_zonal_gradient_against_differences(rng):
    t = mk_zonal_table(10, num=8, d_min=0.5, d_max=6.0, dtype=jnp.float64)
    z = jnp.asarray(rng.normal(size=10))
    w = jnp.asarray(rng.normal(size=4))

    def f(k, z):
        return jnp.sum(w * mk_apply_zonal(t, k, z, 4))

    k0 = float(0.5 * (t.ks[3] + t.ks[4]))  # inside one table interval: f is linear there in k
    gk, gz = jax.grad(f, argnums=(0, 1))(jnp.asarray(k0), z)
    h = 1e-6
    assert float(gk) == pytest.approx((float(f(k0 + h, z)) - float(f(k0 - h, z))) / (2 * h), rel=1e-6)
    fd = [(float(f(k0, z.at[i].add(h))) - float(f(k0, z.at[i].add(-h)))) / (2 * h) for i in range(10)]
    np.testing.assert_allclose(gz, fd, rtol=1e-6, atol=1e-9)


def test_zonal_table_validation():
    z = mk_zonal_table(4, num=3)
    full = mk_table(n=2, num=2)
    with pytest.raises(ValueError, match="mk_apply_zonal"):
        mk_apply(z, 0.5, jnp.zeros(16, jnp.float32))
    with pytest.raises(ValueError, match="mk_apply_zonal"):
        mk_apply_table(z, jnp.zeros(16, jnp.float32))
    with pytest.raises(ValueError, match="zonal table"):
        mk_apply_zonal(full, 0.5, jnp.zeros(2, jnp.float32))
    with pytest.raises(ValueError, match="bands"):
        mk_apply_zonal(z, 0.5, jnp.zeros(5, jnp.float32))
    with pytest.raises(ValueError, match="bands"):
        mk_apply_zonal(z, 0.5, jnp.zeros(4, jnp.float32), out_bands=5)
    with pytest.raises(ValueError, match="1..48"):
        mk_zonal_table(49)
    with pytest.raises(ValueError, match="floating"):
        mk_apply_zonal(z, 0.5, jnp.zeros(4, jnp.int32))
