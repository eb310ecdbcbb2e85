"""Deformations: identity at 0, closed forms, axes, derivatives (jvp vs finite differences), batching."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import BATCH_SHAPES

from jshadow._numerics import eps
from jshadow.entities import MeshOccluder
from jshadow.geometry import (
    Bend,
    Breathe,
    Compose,
    Offsets,
    SquashStretch,
    Taper,
    Twist,
    egg,
    icosphere,
    make_deformation,
    normalize_to_unit_sphere,
    signed_volume,
)

SCALAR_KINDS = {
    "bend": Bend,
    "twist": Twist,
    "taper": Taper,
    "squash_stretch": SquashStretch,
    "breathe": Breathe,
}


def _points(rng, n=7, dtype=np.float64):
    p = rng.uniform(-1.0, 1.0, size=(n, 3))
    p[0] = 0.0  # the origin: h = 0 (a bend's 0/0)
    p[1] = [0.3, 0.0, -0.2]  # on the fixed plane h = 0
    return jnp.asarray(p, dtype)


def _make(kind, a0, a1=None, **kw):
    if kind == "offsets":
        return Offsets(a0, a1)
    return SCALAR_KINDS[kind](a0, a1, **kw)


# ---------------------------------------------------------------- identity at amount 0


@pytest.mark.parametrize("kind", [*SCALAR_KINDS, "offsets"])
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_amount_zero_is_exactly_the_identity(rng, kind, dtype, x64):
    x = _points(rng, dtype=dtype)
    zero = jnp.zeros((7, 3), dtype) if kind == "offsets" else 0.0
    kw = {"origin": -0.4} if kind != "offsets" else {}
    d = _make(kind, zero, **kw)
    for t in (0.0, 0.37, 1.0):
        y = d(x, t)
        assert y.dtype == dtype
        np.testing.assert_array_equal(y, x)


@pytest.mark.parametrize("kind", [*SCALAR_KINDS, "offsets"])
def test_no_nan_in_value_or_gradient_at_amount_zero(rng, kind, x64):
    x = _points(rng)
    w = jnp.asarray(rng.normal(size=(7, 3)))
    a0 = jnp.zeros((7, 3)) if kind == "offsets" else jnp.asarray(0.0)

    def loss(a, x):
        return jnp.sum(_make(kind, a)(x, 0.5) * w)

    ga, gx = jax.grad(loss, argnums=(0, 1))(a0, x)
    assert bool(jnp.all(jnp.isfinite(ga)))
    np.testing.assert_array_equal(gx, w)  # the identity's Jacobian, exactly
    # float32 too (the default dtype)
    g32 = jax.grad(lambda a: jnp.sum(_make(kind, a)(x.astype(jnp.float32), 0.5)))(a0.astype(jnp.float32))
    assert bool(jnp.all(jnp.isfinite(g32)))


# ---------------------------------------------------------------- closed forms


@pytest.mark.usefixtures("x64")
def test_twist_closed_form():
    a, h = 0.8, 0.6
    x = jnp.array([[1.0, h, 0.0], [0.0, h, 2.0], [0.0, 0.5, 0.0]])
    y = Twist(a)(x)
    ang = a * h  # right-handed about +y: +x goes toward −z
    np.testing.assert_allclose(y[0], [math.cos(ang), h, -math.sin(ang)], atol=eps(jnp.float64))
    np.testing.assert_allclose(y[1], [2 * math.sin(ang), h, 2 * math.cos(ang)], atol=eps(jnp.float64))
    np.testing.assert_allclose(y[2], x[2], atol=eps(jnp.float64))  # on the axis: fixed
    # distances to the axis and heights are preserved
    rng = np.random.default_rng(0)
    p = jnp.asarray(rng.normal(size=(20, 3)))
    q = Twist(1.7, origin=0.3)(p)
    np.testing.assert_allclose(q[:, 1], p[:, 1], atol=eps(jnp.float64))
    np.testing.assert_allclose(
        jnp.hypot(q[:, 0], q[:, 2]), jnp.hypot(p[:, 0], p[:, 2]), rtol=eps(jnp.float64)
    )


@pytest.mark.usefixtures("x64")
def test_taper_closed_form():
    x = jnp.array([[1.0, 0.5, 2.0], [-1.0, -0.5, 0.5]])
    y = Taper(0.4, origin=0.0)(x)
    np.testing.assert_allclose(y[0], [1.2, 0.5, 2.4], rtol=eps(jnp.float64))
    np.testing.assert_allclose(y[1], [-0.8, -0.5, 0.4], rtol=eps(jnp.float64))
    y = Taper(0.4, origin=-1.0)(x)  # the bottom plane y = -1 keeps its width
    np.testing.assert_allclose(y[0], [1.6, 0.5, 3.2], rtol=eps(jnp.float64))


@pytest.mark.usefixtures("x64")
def test_squash_stretch_closed_form():
    x = jnp.array([[1.0, 0.5, -2.0]])
    s = 1.0 + 0.44  # amount 0.44
    y = SquashStretch(0.44)(x)
    np.testing.assert_allclose(y[0], [1 / math.sqrt(s), 0.5 * s, -2 / math.sqrt(s)], rtol=eps(jnp.float64))
    y = SquashStretch(-0.5, axis="z", origin=1.0)(x)  # squash along z toward the plane z = 1
    np.testing.assert_allclose(y[0], [math.sqrt(2), 0.5 * math.sqrt(2), 1 - 3 * 0.5], rtol=eps(jnp.float64))


@pytest.mark.usefixtures("x64")
def test_bend_closed_form():
    k = 0.9
    R = 1 / k
    h = jnp.linspace(-1.0, 1.0, 9)
    spine = jnp.stack([jnp.zeros_like(h), h, jnp.zeros_like(h)], -1)
    y = Bend(k)(spine)
    # the spine becomes an arc of the circle of radius 1/κ centred at (1/κ, 0, 0), keeping its length
    np.testing.assert_allclose(jnp.hypot(y[:, 0] - R, y[:, 1]), R, rtol=eps(jnp.float64))
    arc = R * jnp.arctan2(y[:, 1], R - y[:, 0])
    np.testing.assert_allclose(arc, h, atol=eps(jnp.float64))
    np.testing.assert_array_equal(y[:, 2], 0.0)
    # off the spine: distance from the bend centre is R - u, the third coordinate is unchanged
    p = jnp.array([[0.3, 0.7, -0.4], [-0.2, -0.5, 0.9]])
    q = Bend(k)(p)
    np.testing.assert_allclose(jnp.hypot(q[:, 0] - R, q[:, 1]), R - p[:, 0], rtol=eps(jnp.float64))
    np.testing.assert_allclose(jnp.arctan2(q[:, 1], R - q[:, 0]), k * p[:, 1], rtol=eps(jnp.float64))
    np.testing.assert_array_equal(q[:, 2], p[:, 2])
    # negative amount bends toward -x
    assert float(Bend(-k)(jnp.array([[0.0, 1.0, 0.0]]))[0, 0]) < 0


@pytest.mark.usefixtures("x64")
def test_bend_derivative_at_zero_closed_form():
    # d/dκ at κ = 0: u' gains h²/2, h' loses u·h (from the Taylor branch)
    p = jnp.array([[0.3, 0.7, -0.4], [0.0, 0.0, 0.5], [-0.6, -0.9, 0.1]])
    _, tangent = jax.jvp(lambda k: Bend(k)(p), (jnp.asarray(0.0),), (jnp.asarray(1.0),))
    u, h = p[:, 0], p[:, 1]
    np.testing.assert_allclose(tangent[:, 0], h * h / 2, atol=eps(jnp.float64))
    np.testing.assert_allclose(tangent[:, 1], -u * h, atol=eps(jnp.float64))
    np.testing.assert_array_equal(tangent[:, 2], 0.0)


@pytest.mark.usefixtures("x64")
def test_bend_taylor_branch_is_continuous():
    # near the branch switch the series and the direct formula agree to float64 precision
    h = jnp.asarray(np.geomspace(1e-4, 2.0, 400))
    p = jnp.stack([0.4 * jnp.ones_like(h), h, jnp.zeros_like(h)], -1)
    y = Bend(1.0)(p)
    th = np.asarray(h)
    R = 1.0
    ref_u = R - (R - 0.4) * np.cos(th)  # the geometric form
    ref_h = (R - 0.4) * np.sin(th)
    np.testing.assert_allclose(y[:, 0], ref_u, atol=eps(jnp.float64))
    np.testing.assert_allclose(y[:, 1], ref_h, atol=eps(jnp.float64))


@pytest.mark.usefixtures("x64")
def test_breathe_and_offsets_closed_forms():
    x = jnp.array([[1.0, 0.5, -2.0]])
    b = Breathe(0.2, 0.6, period=0.5)
    # t = 1/8: amplitude 0.25, phase sin(2π/4) = 1 -> squash-stretch amount 0.25
    np.testing.assert_allclose(b(x, 0.125), SquashStretch(0.25)(x), rtol=eps(jnp.float64))
    np.testing.assert_allclose(b(x, 0.5), x, atol=eps(jnp.float64))  # a whole period: back at rest
    assert b.periodic
    a0 = jnp.asarray(np.arange(3.0).reshape(1, 3))
    o = Offsets(a0, -a0)
    np.testing.assert_allclose(o(x, 0.25), x + 0.5 * a0, rtol=eps(jnp.float64))


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("kind", ["bend", "twist", "taper", "squash_stretch"])
def test_axis_option_is_a_relabelling_of_coordinates(rng, kind):
    # axis "x" with toward "z" is axis "y" with toward "x" after the cyclic relabelling y->x, z->y, x->z
    p = jnp.asarray(rng.normal(size=(6, 3)))
    extra = {"toward": "z"} if kind == "bend" else {}
    extra_y = {"toward": "x"} if kind == "bend" else {}
    on_x = SCALAR_KINDS[kind](0.7, axis="x", origin=0.2, **extra)(p)
    q = jnp.roll(p, 1, axis=-1)  # q_y = p_x, q_z = p_y, q_x = p_z
    on_y = jnp.roll(SCALAR_KINDS[kind](0.7, axis="y", origin=0.2, **extra_y)(q), -1, axis=-1)
    np.testing.assert_allclose(on_x, on_y, rtol=eps(jnp.float64), atol=eps(jnp.float64))
    assert not np.allclose(on_x, p)


# ---------------------------------------------------------------- derivatives vs finite differences


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("kind", [*SCALAR_KINDS, "offsets"])
@pytest.mark.parametrize("at_zero", [True, False])
def test_jvp_wrt_amounts_matches_central_differences(rng, kind, at_zero):
    x = _points(rng)
    if kind == "offsets":
        a0 = jnp.zeros((7, 3)) if at_zero else jnp.asarray(rng.normal(size=(7, 3)) * 0.1)
        a1 = a0 + 0.2
        da0, da1 = jnp.asarray(rng.normal(size=(7, 3))), jnp.asarray(rng.normal(size=(7, 3)))
    else:
        a0 = jnp.asarray(0.0 if at_zero else 0.45)
        a1 = jnp.asarray(0.0 if at_zero else -0.3)
        da0, da1 = jnp.asarray(1.0), jnp.asarray(-0.7)
    kw = {"origin": -0.25} if kind != "offsets" else {}
    t = 0.3

    def f(a0, a1):
        return _make(kind, a0, a1, **kw)(x, t)

    _, tangent = jax.jvp(f, (a0, a1), (da0, da1))
    h = 1e-5
    fd = (f(a0 + h * da0, a1 + h * da1) - f(a0 - h * da0, a1 - h * da1)) / (2 * h)
    assert bool(jnp.all(jnp.isfinite(tangent)))
    np.testing.assert_allclose(tangent, fd, rtol=1e-7, atol=1e-9)
    # reverse mode agrees with forward mode
    w = jnp.asarray(rng.normal(size=(7, 3)))
    g0, g1 = jax.grad(lambda a0, a1: jnp.sum(f(a0, a1) * w), argnums=(0, 1))(a0, a1)
    np.testing.assert_allclose(jnp.sum(g0 * da0) + jnp.sum(g1 * da1), jnp.sum(tangent * w), rtol=1e-10)


@pytest.mark.usefixtures("x64")
def test_breathe_period_is_differentiable(rng):
    x = _points(rng)

    def f(p):
        return Breathe(0.3, period=p)(x, 0.4)

    p0 = jnp.asarray(0.7)
    _, tangent = jax.jvp(f, (p0,), (jnp.asarray(1.0),))
    h = 1e-6
    np.testing.assert_allclose(tangent, (f(p0 + h) - f(p0 - h)) / (2 * h), rtol=1e-6, atol=1e-9)


# ---------------------------------------------------------------- batching, jit, volume


@pytest.mark.parametrize("kind", [*SCALAR_KINDS, "offsets"])
@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_batch_over_time(rng, kind, batch):
    x = _points(rng, dtype=np.float32)
    a = jnp.asarray(rng.normal(size=(7, 3)), jnp.float32) if kind == "offsets" else 0.4
    d = _make(kind, a * 0.5, a) if kind == "offsets" else _make(kind, 0.1, a)
    t = jnp.asarray(rng.uniform(size=batch), jnp.float32)
    y = d(x, t)
    assert y.shape == (*batch, 7, 3)
    for idx in np.ndindex(*batch):
        np.testing.assert_allclose(y[idx], d(x, t[idx]), rtol=eps(jnp.float32), atol=eps(jnp.float32))
    # leading axes of the points broadcast against t's shape
    xb = jnp.broadcast_to(x, (*batch, 7, 3))
    np.testing.assert_allclose(d(xb, t), y, rtol=eps(jnp.float32), atol=eps(jnp.float32))
    jitted = eqx.filter_jit(lambda d, x, t: d(x, t))
    np.testing.assert_allclose(jitted(d, x, t), y, rtol=eps(jnp.float32), atol=eps(jnp.float32))


@pytest.mark.usefixtures("x64")
def test_squash_stretch_preserves_the_volume_of_the_egg():
    e = egg(2, dtype=jnp.float64)
    unit = normalize_to_unit_sphere(e.vertices)
    v0 = signed_volume(unit, e.faces)

    def vol(a):
        return signed_volume(SquashStretch(a)(unit), e.faces)

    # to first order (derivative 0 at rest) and, the map being linear with determinant 1, exactly
    _, dv = jax.jvp(vol, (jnp.asarray(0.0),), (jnp.asarray(1.0),))
    assert abs(float(dv)) < eps(jnp.float64, 10) * float(v0)
    for a in (-0.5, 0.3, 1.5):
        np.testing.assert_allclose(vol(a), v0, rtol=eps(jnp.float64))
    breathing = Breathe(0.4, period=0.5)
    for t in (0.1, 0.3, 0.9):
        np.testing.assert_allclose(signed_volume(breathing(unit, t), e.faces), v0, rtol=eps(jnp.float64))
    # a taper is not volume preserving: its first-order change is non-zero
    _, dv_taper = jax.jvp(
        lambda a: signed_volume(Taper(a, origin=-1.0)(unit), e.faces),
        (jnp.asarray(0.0),),
        (jnp.asarray(1.0),),
    )
    assert float(dv_taper) > 0.1 * float(v0)


def test_squash_stretch_clamps_instead_of_nan():
    x = jnp.ones((2, 3))
    y = SquashStretch(-1.5)(x)
    assert bool(jnp.all(jnp.isfinite(y)))
    g = jax.grad(lambda a: SquashStretch(a)(x).sum())(jnp.asarray(-1.5))
    assert bool(jnp.isfinite(g))


def test_compose_applies_in_order():
    x = icosphere(0).vertices
    c = Compose(Twist(0.5), Bend(0.3))
    np.testing.assert_allclose(c(x, 0.5), Bend(0.3)(Twist(0.5)(x, 0.5), 0.5), rtol=eps(jnp.float32))


def test_deformation_in_a_mesh_occluder():
    s = icosphere(1)
    occ = MeshOccluder(s.vertices, s.faces, jnp.array([0.0, 1.0, 0.0]), jnp.asarray(0.5), Twist(0.0, 1.0))
    v0 = occ.vertices(0.0)
    np.testing.assert_allclose(v0, jnp.array([0.0, 1.0, 0.0]) + 0.5 * s.vertices, rtol=eps(jnp.float32))
    v1 = occ.vertices(1.0)
    np.testing.assert_allclose(
        v1, jnp.array([0.0, 1.0, 0.0]) + 0.5 * Twist(1.0)(s.vertices), rtol=eps(jnp.float32)
    )


# ---------------------------------------------------------------- the factory


@pytest.mark.parametrize("kind", list(SCALAR_KINDS))
def test_make_deformation_builds_each_type(kind):
    d = make_deformation(kind, 0.3)
    assert isinstance(d, SCALAR_KINDS[kind])
    np.testing.assert_array_equal(d.amount_start, d.amount_end)
    d = make_deformation(kind, (0.1, 0.5), axis="z", origin=-1.0)
    assert float(d.amount_start) == pytest.approx(0.1) and float(d.amount_end) == pytest.approx(0.5)
    assert d.axis == 2 and d.origin == -1.0
    d = make_deformation(kind, [0.1, 0.5])
    assert float(d.amount_end) == pytest.approx(0.5)


def test_make_deformation_offsets_and_aliases():
    a = np.zeros((5, 3))
    d = make_deformation("offsets", a)
    assert isinstance(d, Offsets) and d.amount_start.shape == (5, 3)
    d = make_deformation("offsets", (a, a + 1.0))
    np.testing.assert_array_equal(d.amount_end, 1.0)
    d = make_deformation("offsets", np.stack([a, a + 2.0]))
    np.testing.assert_array_equal(d.amount_end, 2.0)
    assert isinstance(make_deformation("Squash-Stretch", 0.2), SquashStretch)
    assert isinstance(make_deformation("bend", 0.2, toward="z"), Bend)


@pytest.mark.parametrize(
    ("args", "kwargs", "match"),
    [
        (("wobble", 0.3), {}, r"unknown deformation type 'wobble'.*bend"),
        (("bend", 0.3), {"angle": 1.0}, r"unknown parameter 'angle' for deformation 'bend'"),
        (("twist", 0.3), {"toward": "x"}, r"unknown parameter 'toward' for deformation 'twist'"),
        (("offsets", np.zeros((4, 3))), {"axis": "y"}, r"unknown parameter 'axis'"),
        (("bend", (0.1, 0.2, 0.3)), {}, r"'bend'.*pair \[start, end\]"),
        (("bend", np.zeros((2, 2))), {}, r"'bend'.*pair \[start, end\]"),
        (("taper", float("nan")), {}, r"'taper'.*finite"),
        (("taper", "big"), {}, r"'taper'.*number"),
        (("squash_stretch", (0.0, -1.0)), {}, r"'squash_stretch'.*> -1"),
        (("breathe", 0.2), {"period": 0.0}, r"'breathe'.*period must be > 0"),
        (("bend", 0.2), {"axis": "w"}, r"axis must be 'x', 'y' or 'z'"),
        (("bend", 0.2), {"toward": "y"}, r"'toward' must differ"),
        (("offsets", np.zeros(3)), {}, r"'offsets'.*\(V, 3\)"),
    ],
)
def test_make_deformation_errors(args, kwargs, match):
    with pytest.raises(ValueError, match=match):
        make_deformation(*args, **kwargs)


@pytest.mark.usefixtures("x64")
def test_make_deformation_is_differentiable_with_traced_amounts(rng):
    x = _points(rng)

    def f(a):
        return make_deformation("bend", (a, 2.0 * a), origin=-1.0)(x, 0.5)

    a0 = jnp.asarray(0.4)
    _, tangent = jax.jvp(f, (a0,), (jnp.asarray(1.0),))
    h = 1e-6
    np.testing.assert_allclose(tangent, (f(a0 + h) - f(a0 - h)) / (2 * h), rtol=1e-6, atol=1e-9)
    g = jax.grad(lambda a: f(a).sum())(jnp.asarray(0.0))
    assert bool(jnp.isfinite(g))
    # and through the equinox tree (what a fit does)
    d = make_deformation("twist", 0.2)
    g_tree = jax.grad(lambda d: d(x, 0.0).sum())(d)
    assert bool(jnp.isfinite(g_tree.amount_start)) and float(g_tree.amount_end) == 0.0


@pytest.mark.usefixtures("x64")
def test_jacobian_determinants_closed_form(rng):
    # local volume change det(∂x'/∂x): bend 1 − κu, twist 1, taper (1 + a h)², squash-stretch 1
    p = jnp.asarray(rng.uniform(-0.8, 0.8, size=(5, 3)))
    a, o = 0.6, -0.3
    h, u = p[:, 1] - o, p[:, 0]
    cases = [
        (Bend(a, origin=o), 1.0 - a * u),
        (Twist(a, origin=o), jnp.ones(5)),
        (Taper(a, origin=o), (1.0 + a * h) ** 2),
        (SquashStretch(a, origin=o), jnp.ones(5)),
    ]
    for d, expected in cases:
        jac = jax.vmap(jax.jacfwd(lambda q, d=d: d(q[None], 0.0)[0]))(p)
        np.testing.assert_allclose(jnp.linalg.det(jac), expected, rtol=eps(jnp.float64, 10))


@pytest.mark.usefixtures("x64")
def test_inverse_amounts_undo_twist_and_squash(rng):
    p = jnp.asarray(rng.normal(size=(6, 3)))
    np.testing.assert_allclose(Twist(-0.9)(Twist(0.9)(p)), p, atol=eps(jnp.float64))
    a = 0.6
    back = SquashStretch(1.0 / (1.0 + a) - 1.0)(SquashStretch(a)(p))
    np.testing.assert_allclose(back, p, atol=eps(jnp.float64))
