"""Tests of jshadow.optim: the loss, the Laplacian penalty, multi-light rendering, a tiny fit."""

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from conftest import BATCH_SHAPES

from jshadow._numerics import eps
from jshadow.config import plane_receivers
from jshadow.entities import Environment, Method, Scene, SphereLight, SphereOccluder
from jshadow.geometry import icosphere
from jshadow.optim import (
    fit,
    fit_params,
    laplacian_penalty,
    plane_radiance,
    plane_radiances,
    relative_mse,
    uniform_laplacian,
)
from jshadow.scene import render

# ---------------------------------------------------------------- relative_mse


def test_relative_mse_properties(rng):
    t = jnp.asarray(rng.uniform(0.1, 1.0, size=(20, 3)), jnp.float32)
    p = jnp.asarray(rng.uniform(0.1, 1.0, size=(20, 3)), jnp.float32)
    tol = 10 * eps(jnp.float32)
    assert float(relative_mse(t, t)) == 0.0
    assert float(relative_mse(jnp.zeros_like(t), t)) == pytest.approx(1.0, abs=tol)
    a = float(relative_mse(p, t))
    assert a > 0.0
    assert float(relative_mse(3.0 * p, 3.0 * t)) == pytest.approx(a, rel=tol)
    # closed form
    ref = np.mean((np.asarray(p) - np.asarray(t)) ** 2) / np.mean(np.asarray(t) ** 2)
    assert a == pytest.approx(ref, rel=tol)


def test_relative_mse_zero_target_is_finite():
    z = jnp.zeros((4, 3), jnp.float32)
    assert float(relative_mse(z, z)) == 0.0
    g = jax.grad(lambda p: relative_mse(p, z))(jnp.ones((4, 3), jnp.float32))
    assert np.all(np.isfinite(np.asarray(g)))


def test_relative_mse_shape_mismatch():
    with pytest.raises(ValueError, match="equal shapes"):
        relative_mse(jnp.zeros((4, 3)), jnp.zeros((5, 3)))


# ---------------------------------------------------------------- Laplacian penalty


@pytest.fixture(scope="module")
def ico():
    m = icosphere(1)  # 42 vertices, degrees 5 and 6
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces)


def _neighbours(faces, v):
    nb = [set() for _ in range(v)]
    for a, b, c in faces:
        nb[a] |= {b, c}
        nb[b] |= {a, c}
        nb[c] |= {a, b}
    return nb


@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_laplacian_zero_for_constant_field(ico, batch, rng):
    verts, faces = ico
    const = rng.normal(size=(*batch, 1, 3))
    field = jnp.asarray(np.broadcast_to(const, (*batch, verts.shape[0], 3)), jnp.float32)
    pen = laplacian_penalty(field, faces)
    assert pen.shape == batch
    assert np.all(np.abs(np.asarray(pen)) <= 10 * eps(jnp.float32))
    assert uniform_laplacian(field, faces).shape == field.shape


def test_laplacian_spike_closed_form(ico, x64):
    verts, faces = ico
    v = verts.shape[0]
    nb = _neighbours(faces, v)
    k, s = 7, np.array([0.3, -0.2, 0.5])
    field = np.zeros((v, 3))
    field[k] = s
    # (L o)_k = s; (L o)_j = −s/deg_j for the neighbours j of k; 0 elsewhere
    expected = (s @ s) * (1.0 + sum(1.0 / len(nb[j]) ** 2 for j in nb[k])) / v
    pen = float(laplacian_penalty(jnp.asarray(field), faces))
    assert pen > 0.0
    assert pen == pytest.approx(expected, rel=100 * eps(jnp.float64))
    lap = np.asarray(uniform_laplacian(jnp.asarray(field), faces))
    np.testing.assert_allclose(lap[k], s, rtol=1e-12)
    for j in nb[k]:
        np.testing.assert_allclose(lap[j], -s / len(nb[j]), rtol=1e-12)


def test_laplacian_gradient(ico, x64, rng):
    verts, faces = ico
    o = jnp.asarray(rng.normal(size=verts.shape) * 0.1)
    f = lambda x: laplacian_penalty(x, faces)  # noqa: E731
    g_rev = np.asarray(jax.grad(f)(o))
    g_fwd = np.asarray(jax.jacfwd(f)(o))
    np.testing.assert_allclose(g_rev, g_fwd, rtol=1e-10, atol=1e-14)
    # central finite differences on a few coordinates (the penalty is quadratic: exact up to rounding)
    h = 1e-5
    for idx in [(0, 0), (5, 1), (17, 2), (41, 0)]:
        e = np.zeros(verts.shape)
        e[idx] = h
        fd = (float(f(o + e)) - float(f(o - e))) / (2 * h)
        assert g_rev[idx] == pytest.approx(fd, rel=1e-6, abs=1e-10)


def test_laplacian_bad_faces(ico):
    verts, faces = ico
    with pytest.raises(ValueError, match="faces"):
        laplacian_penalty(jnp.zeros((verts.shape[0], 3)), faces.astype(np.float32))
    with pytest.raises(ValueError, match="index vertices"):
        laplacian_penalty(jnp.zeros((10, 3)), faces)


# ---------------------------------------------------------------- rendering and fitting


def _scene(light_center, n=3, res=(8, 8)):
    f32 = jnp.float32
    return Scene(
        method=Method(sh_bands=n),
        receivers=plane_receivers(
            jnp.zeros(3, f32), jnp.asarray([4.0, 4.0], f32), res, jnp.full(3, 0.8, f32)
        ),
        occluders=(SphereOccluder(center=jnp.asarray([0.0, 1.0, 0.0], f32), radius=jnp.asarray(0.5, f32)),),
        lights=(_light(light_center),),
        environment=Environment(radiance=jnp.full(3, 0.2, f32)),
    )


def _light(c):
    f32 = jnp.float32
    return SphereLight(
        center=jnp.asarray(c, f32), radius=jnp.asarray(0.3, f32), radiance=jnp.full(3, 30.0, f32)
    )


def test_plane_radiances_matches_render():
    sc = _scene([0.5, 3.0, 0.3])
    sets = [(_light([0.5, 3.0, 0.3]),), (_light([-1.0, 2.5, 0.0]), _light([0.0, 3.0, 1.0])), ()]
    out = plane_radiances(sc, sets)
    assert out.shape == (3, 64, 3)
    for k, lights in enumerate(sets):
        ref = render(Scene(sc.method, sc.receivers, sc.occluders, tuple(lights), sc.environment)).radiance
        np.testing.assert_allclose(np.asarray(out[k]), np.asarray(ref), rtol=1e-6, atol=1e-7)
    with pytest.raises(ValueError, match="at least one light set"):
        plane_radiances(sc, [])


def test_tiny_light_fit_converges():
    truth = jnp.asarray([-0.6, 3.0, 0.4], jnp.float32)
    start = jnp.asarray([0.6, 3.0, -0.2], jnp.float32)
    target = plane_radiance(_scene(truth))

    def make_scene(p):
        return _scene(p[0])

    res = fit_params(make_scene, [start], target, steps=40, optimizer=optax.adam(0.08))
    d0 = float(jnp.linalg.norm(start - truth))
    d1 = float(jnp.linalg.norm(res.params[0] - truth))
    assert d1 < 0.15 * d0, (d0, d1, np.asarray(res.params[0]))
    assert res.loss[-1] < 0.05 * res.loss[0]
    assert len(res.loss) == len(res.history) == 40
    assert len(res.step_s) == 39 and res.ms_per_step > 0.0


def test_fit_minimises_a_quadratic_and_validates():
    res = fit(lambda p: jnp.sum((p[0] - 2.0) ** 2), [jnp.zeros(3)], steps=200, learning_rate=0.1)
    np.testing.assert_allclose(np.asarray(res.params[0]), 2.0, atol=0.05)
    with pytest.raises(ValueError, match="steps"):
        fit(lambda p: jnp.sum(p[0] ** 2), [jnp.zeros(3)], steps=0)
    with pytest.raises(ValueError, match="light sets"):
        fit_params(lambda p: _scene(p[0]), [jnp.zeros(3)], jnp.zeros((64, 3)), light_sets=[()])


def test_fit_retraces_after_an_overflow_the_callback_grows():
    # A loss whose static size (read when the step is traced) is too small for a parameter beyond
    # it raises an equinox overflow at run time; the callback grows the size and the step is
    # traced again. Without a callback, or when it reports no growth, the error propagates.
    import equinox as eqx

    size = {"limit": 1.0}
    calls = []

    def loss_fn(p):
        limit = size["limit"]  # static: read at trace time
        x = eqx.error_if(p[0], jnp.abs(p[0]) > limit, "slots overflowed (test)")
        return jnp.sum((x - 3.0) ** 2)

    def grow(params):
        calls.append(float(np.asarray(params[0])))
        size["limit"] = abs(calls[-1]) + 0.5
        return True

    res = fit(loss_fn, [jnp.zeros(())], steps=120, learning_rate=0.1, on_overflow=grow)
    np.testing.assert_allclose(float(res.params[0]), 3.0, atol=0.05)
    # the limit grows by about 0.5 per overflow on the way to 3: four growths, each at a parameter
    # past the limit then in force, each at its own step
    assert len(calls) == len(res.retraced) == 4 and calls[0] > 1.0 and np.all(np.diff(calls) > 0.4)
    assert res.retraced == sorted(set(res.retraced))
    size["limit"] = 1.0
    with pytest.raises(eqx.EquinoxRuntimeError, match="overflowed"):
        fit(loss_fn, [jnp.zeros(())], steps=60, learning_rate=0.1)
    size["limit"] = 1.0
    with pytest.raises(eqx.EquinoxRuntimeError, match="overflowed"):
        fit(loss_fn, [jnp.zeros(())], steps=60, learning_rate=0.1, on_overflow=lambda p: False)


def test_mesh_fit_grows_sizes_a_traced_pose_overflows(monkeypatch):
    # The image derivative's static sizes are measured on concrete poses; a fitted deformation
    # amount is traced, and a pose beyond those measured overflows them. fit_params then measures
    # the scene again at the current parameters (grow_slots) and retraces the step. Here the
    # measured sizes are replaced by ones far too small, so the first step must overflow.
    import trimesh

    from jshadow import optim
    from jshadow import scene as scene_module
    from jshadow.entities import MeshOccluder
    from jshadow.geometry import Bend, normalize_to_unit_sphere
    from jshadow.scene import _image_grad_slots

    ico = trimesh.creation.icosphere(subdivisions=1)
    unit = normalize_to_unit_sphere(jnp.asarray(ico.vertices, jnp.float32))
    faces = jnp.asarray(ico.faces, jnp.int32)
    method = Method(bsv_grid=(6, 10), directions=(12, 12))  # shell 1.5: the image derivative

    def make_scene(p):
        occ = MeshOccluder(unit, faces, jnp.asarray([0.0, 1.0, 0.0]), jnp.float32(0.6), Bend(p[0]))
        base = _scene([0.5, 3.0, 0.3])
        return Scene(method, base.receivers, (occ,), base.lights, base.environment)

    target = plane_radiance(make_scene([jnp.float32(0.9)]))
    occ = make_scene([jnp.float32(0.3)]).occluders[0]
    good = _image_grad_slots(occ, np.asarray(faces), method)
    keys = [k for k in scene_module._SLOTS if k[0] == "image" and k[2] == hash(np.asarray(faces).tobytes())]
    assert keys
    for k in keys:
        scene_module._SLOTS[k] = tuple(1 for _ in good)
    grew = []

    def counting(scene):
        grew.append(scene_module.grow_slots(scene))
        return grew[-1]

    monkeypatch.setattr(optim, "grow_slots", counting)
    res = fit_params(make_scene, [jnp.float32(0.3)], target, steps=3, optimizer=optax.adam(0.05))
    assert len(res.loss) == 3 and np.isfinite(res.loss).all()
    assert grew[:1] == [True] and res.retraced[:1] == [0]  # the first step overflowed, sizes grew
    grown = _image_grad_slots(occ, np.asarray(faces), method)
    assert all(g >= 2 for g in grown) and grown != tuple(1 for _ in good)
