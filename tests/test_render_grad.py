"""Gradients of full renders with respect to deformation parameters and light positions."""

import dataclasses
import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from jshadow.entities import Environment, MeshOccluder, Method, Receivers, Scene, SphereLight
from jshadow.geometry import normalize_to_unit_sphere
from jshadow.scene import mesh_bsv, render

METHOD = Method.paper(bsv_grid=(8, 12), directions=(16, 16))


class Scale(eqx.Module):
    """Uniform scaling by (1 + a): the BSV is invariant, only the bounding sphere grows."""

    a: jax.Array

    def __call__(self, x, t):
        return x * (1.0 + self.a)


def plane(n=7, size=3.0):
    xs = np.linspace(-size / 2, size / 2, n, dtype=np.float32)
    x, z = np.meshgrid(xs, xs)
    pts = np.stack([x.ravel(), np.zeros(x.size, np.float32), z.ravel()], -1)
    nrm = np.tile(np.float32([0, 1, 0]), (x.size, 1))
    return Receivers(jnp.asarray(pts), jnp.asarray(nrm), jnp.full(3, 0.8, jnp.float32), (n, n))


_ICO = trimesh.creation.icosphere(subdivisions=1)
UNIT = normalize_to_unit_sphere(jnp.asarray(_ICO.vertices, jnp.float32))
FACES = jnp.asarray(_ICO.faces, jnp.int32)  # built outside any jit: concrete when closed over


def scene_with(deform, faces=FACES):
    occ = MeshOccluder(UNIT, faces, jnp.asarray([0.1, 1.0, 0.0]), jnp.float32(0.5), deform)
    light = SphereLight(jnp.asarray([0.8, 3.0, 0.4]), jnp.float32(0.4), jnp.full(3, 20.0, jnp.float32))
    return Scene(METHOD, plane(), (occ,), (light,), Environment(jnp.full(3, 0.3, jnp.float32)))


def test_uniform_scale_gradient_matches_finite_differences():
    # The BSV of a uniformly scaled mesh is unchanged, so the forward pass is smooth in a and central
    # differences are exact up to rounding; the silhouette term and the motion of the sample points
    # must cancel inside the BSV for the gradient to agree.
    @jax.jit
    def loss(a):
        return jnp.sum(render(scene_with(Scale(a))).radiance)

    a0, h = jnp.float32(0.1), 0.02
    g = float(jax.jit(jax.grad(loss))(a0))
    fd = float((loss(a0 + h) - loss(a0 - h)) / (2 * h))
    assert np.isfinite(g) and abs(fd) > 1e-3
    np.testing.assert_allclose(g, fd, rtol=0.03)


def test_light_position_gradient_matches_finite_differences():
    @jax.jit
    def loss(c):
        s = scene_with(None)
        s = eqx.tree_at(lambda s: s.lights[0].center, s, c)
        return jnp.sum(render(s).radiance)

    c0 = jnp.asarray([0.8, 3.0, 0.4])
    g = np.asarray(jax.jit(jax.grad(loss))(c0))
    for i in range(3):
        e = np.zeros(3, np.float32)
        e[i] = 0.01
        fd = float((loss(c0 + e) - loss(c0 - e)) / 0.02)
        np.testing.assert_allclose(g[i], fd, rtol=0.02, atol=1e-3 * np.abs(g).max())


class StretchY(eqx.Module):
    a: jax.Array

    def __call__(self, x, t):
        return x * jnp.asarray([1.0, 1.0 + self.a, 1.0])


@pytest.mark.parametrize("setting", ["paper", "raycast", "image", "scanline"])
def test_stretch_gradient_comes_from_the_silhouette_and_matches_finite_differences(setting):
    # Stretching changes the BSV itself: without the silhouette term the BSV's derivative would be
    # zero (binary visibility). Finite differences use a finer direction grid. a0 = 0.2, not 0: at
    # a = 0 every icosphere vertex ties for the bounding radius, which has a kink there (measured:
    # one-sided derivatives differ by ~75 %), and central differences would average the two sides.
    # On the default 1.5 r shell the ray-cast silhouette integral needs more directions to converge
    # (16²: 10 % low), so that setting's gradient is taken at 48²; the image-plane one converges
    # sooner (measured 0.4 / 1.2 / 0.6 / 0.7 % from the differences at 16² / 24² / 32² / 48²) and is
    # taken at 16², as is the scanline one (0.9 / 0.4 / 0.8 % at 16² / 24² / 32²). Finite
    # differences are noisy at 48² (binary visibility: ±15 % at h = 0.05), so they use 128² rays
    # (brute force: the derivative is that of the exact integral, whichever quadrature).
    def loss_with(method):
        def loss(a):
            s = scene_with(StretchY(a))
            s = Scene(method, s.receivers, s.occluders, s.lights, s.environment)
            return jnp.sum(render(s).radiance)

        return loss

    if setting == "paper":
        method, fine = METHOD, Method.paper(bsv_grid=(8, 12), directions=(48, 48))
    else:  # the 1.5 r shell: visibility of silhouette nodes by rays, or in the edge-scan's image plane
        gradient, d = {"image": ("image", 16), "scanline": ("scanline", 16)}.get(setting, ("raycast", 48))
        method = Method(bsv_grid=(8, 12), directions=(d, d), bsv_gradient=gradient)
        fine = Method(bsv_grid=(8, 12), directions=(128, 128), bsv_method="brute")
    a0, h = jnp.float32(0.2), 0.05
    g = float(jax.jit(jax.grad(loss_with(method)))(a0))
    loss_fine = jax.jit(loss_with(fine))
    fd = float((loss_fine(a0 + h) - loss_fine(a0 - h)) / (2 * h))
    assert abs(fd) > 1.0
    np.testing.assert_allclose(g, fd, rtol=0.08)


class ShiftY(eqx.Module):
    """Translation by a along y (unit coordinates): the mesh leaves the occluder's placed centre."""

    a: jax.Array

    def __call__(self, x, t):
        return x + jnp.asarray([0.0, 1.0, 0.0]) * self.a


def _loss(deform, method):
    def loss(a):
        s = scene_with(deform(a))
        return jnp.sum(render(Scene(method, s.receivers, s.occluders, s.lights, s.environment)).radiance)

    return loss


def test_placed_centre_gradient_of_a_mesh_leaving_its_centre_matches_finite_differences():
    # bsv_center = "placed" (the default): the BSV's sample points stay about the occluder's centre
    # while the mesh moves up, so the BSV itself changes (a box-centred one would only move): the
    # silhouette term, and the shell's growth with the radius about the centre, which reaches the
    # derivative through the anchors (geometry.with_center_anchors). Finite differences as in the
    # stretch test, at 256² rays and h = 0.03: 2.05 (h = 0.02 / 0.04: 2.13 / 2.00; the slope of a
    # cubic fit of 41 losses over a in [0.14, 0.26]: 2.06); the gradient at 16²: 2.09.
    method = Method(bsv_grid=(8, 12), directions=(16, 16), bsv_gradient="image")
    fine = Method(bsv_grid=(8, 12), directions=(256, 256), bsv_method="brute")
    assert method.bsv_center == fine.bsv_center == "placed"
    a0, h = jnp.float32(0.2), 0.03
    g = float(jax.jit(jax.grad(_loss(ShiftY, method)))(a0))
    loss_fine = jax.jit(_loss(ShiftY, fine))
    fd = float((loss_fine(a0 + h) - loss_fine(a0 - h)) / (2 * h))
    assert abs(fd) > 1.0
    np.testing.assert_allclose(g, fd, rtol=0.08)


class LiftTop(eqx.Module):
    """Lifts the upper half (y > 0, unit coordinates) by a·y: at a = 0 the symmetric icosphere's
    top and bottom vertices tie as the extremes about the centre, and only the top one moves."""

    a: jax.Array

    def __call__(self, x, t):
        return x + jnp.asarray([0.0, 1.0, 0.0]) * self.a * jnp.maximum(x[:, 1:2], 0.0)


def test_placed_centre_has_no_vertex_derivative_where_extremes_tie():
    # The placed centre is the occluder's centre for every pose: its derivative with respect to the
    # vertices is zero. Where a vertex tied with an anchor on each side (a mesh normalised about its
    # centre, at rest) the anchored box's centre used to take half of each extreme vertex's motion
    # (first-of-ties rule), in the BSV's centre and in the sample points of its silhouette
    # derivative (the animated bunny's whole-frame vertex gradient moved by 33 %).
    from jshadow.geometry import bounding_sphere, with_center_anchors

    method = Method(bsv_grid=(8, 12), directions=(16, 16))
    assert method.bsv_center == "placed"

    def center(a):
        s = dataclasses.replace(scene_with(LiftTop(a)), method=method)
        return mesh_bsv(s.occluders[0], 0.0, s).center

    def box_center(a):  # as the samplers and their derivatives see it
        occ = scene_with(LiftTop(a)).occluders[0]
        return bounding_sphere(with_center_anchors(occ.vertices(0.0), occ.center))[0]

    a0 = jnp.float32(0.0)
    occ = scene_with(LiftTop(a0)).occluders[0]
    v = np.asarray(occ.vertices(0.0))
    assert v[:, 1].max() - 1.0 == pytest.approx(1.0 - v[:, 1].min(), abs=1e-6)  # the tie is there
    np.testing.assert_allclose(np.asarray(center(a0)), [0.1, 1.0, 0.0], atol=1e-6)
    np.testing.assert_array_equal(np.asarray(jax.jacrev(center)(a0)), np.zeros(3))
    np.testing.assert_array_equal(np.asarray(jax.jacrev(box_center)(a0)), np.zeros(3))


def _weighted_bsv(a, method=METHOD, faces=FACES):
    """A weighted sum of the stretched occluder's BSV coefficients (a scalar of the stretch a)."""
    s = dataclasses.replace(scene_with(StretchY(a), faces), method=method)
    b = mesh_bsv(s.occluders[0], 0.0, s)
    return jnp.sum(b.coeffs * jnp.arange(b.coeffs.shape[-1], dtype=b.coeffs.dtype))


def test_jit_of_grad_equals_grad_and_traced_faces_raise():
    # A scene built outside jit and closed over keeps its faces concrete: under jit (and under
    # grad of a jitted function) the BSV keeps its silhouette derivative; it equals the eager one.
    loss = _weighted_bsv

    a0 = jnp.float32(0.2)
    want = float(jax.grad(loss)(a0))
    assert abs(want) > 1.0
    np.testing.assert_allclose(float(jax.jit(jax.grad(loss))(a0)), want, rtol=1e-4)
    np.testing.assert_allclose(float(jax.grad(jax.jit(loss))(a0)), want, rtol=1e-4)

    # Faces converted inside the trace are tracers: the forward pass still works, but a derivative
    # would miss the silhouette term (binary visibility), so it raises instead of returning zero.
    def traced(a):
        return loss(a, faces=jnp.asarray(_ICO.faces, jnp.int32))

    np.testing.assert_allclose(float(jax.jit(traced)(a0)), float(loss(a0)), rtol=1e-5)
    with pytest.raises(ValueError, match="mesh faces are traced"):
        jax.jit(jax.grad(traced))(a0)


def test_eager_image_plane_gradient_equals_the_jitted_one():
    # the default gradient (image plane): its static sizes are measured when the derivative is
    # traced, from concrete poses taken beforehand, so the eager trace (whose deformation parameter
    # is a tracer) and jit of grad agree
    def loss(a):
        return _weighted_bsv(a, Method(bsv_grid=(3, 4), directions=(8, 8)))

    a0 = jnp.float32(0.2)
    want = float(jax.grad(loss)(a0))
    assert abs(want) > 0.1
    np.testing.assert_allclose(float(jax.jit(jax.grad(loss))(a0)), want, rtol=1e-4)


def test_jit_of_an_edgescan_render_equals_the_eager_render():
    # Shell 1.5 and a closed mesh: the BSV comes from the edge-scan (eagerly, and in the Renderer).
    # Under jit the differentiable forward (raycast gradient) once fell back to brute-force ray
    # casting, another quadrature of the same integral (0.6 % apart here, and 20x slower for the
    # bunny); it now runs the same edge-scan, with slots measured on concrete poses of the animation.
    from jshadow import scene as scene_module
    from jshadow.scene import _edgescan_slots
    from jshadow.visibility._edgescan import _traced_default_slots

    method = Method(bsv_grid=(8, 12), directions=(16, 16))  # shell 1.5, the image-plane gradient
    s = dataclasses.replace(scene_with(StretchY(jnp.float32(0.2))), method=method)
    eager = np.asarray(render(s).irradiance)
    image_sizes = {k for k in scene_module._SLOTS if k[0] == "image"}
    jitted = np.asarray(jax.jit(lambda: render(s).irradiance)())
    assert np.abs(jitted - eager).max() <= 1e-5 * np.abs(eager).max()
    # a forward pass does not measure the derivative's sizes (only a traced derivative does)
    assert {k for k in scene_module._SLOTS if k[0] == "image"} == image_sizes
    occ, faces = s.occluders[0], np.asarray(FACES)
    measured = _edgescan_slots(occ, faces, method)
    assert measured is not None and measured[0] < _traced_default_slots(faces.shape[0], (8, 12), (16, 16))[0]


def _with_traced_rest_pose(occ, lookup):
    """What ``lookup(o)`` returns, traced once, for ``occ`` with its rest pose a tracer (as under
    ``jax.grad`` with respect to ``unit_vertices``). A new function each call: jax.jit would reuse
    an earlier trace of the same function."""
    seen = []

    @jax.jit
    def probe(u):
        seen.append(lookup(eqx.tree_at(lambda o: o.unit_vertices, occ, u)))
        return u

    probe(occ.unit_vertices + 0.01)
    (out,) = seen
    return out


def test_traced_rest_pose_reuses_the_slot_sizes_measured_on_a_concrete_one():
    # fitting per-vertex offsets traces the rest pose: the silhouette slot sizes measured on the
    # concrete pose of the same topology must be reused (not "every edge", not a guess)
    from jshadow.scene import _image_grad_slots, _slots

    occ = scene_with(StretchY(jnp.float32(0.2))).occluders[0]
    faces = np.asarray(occ.faces)
    image = Method(bsv_grid=(8, 12), directions=(16, 16), bsv_gradient="image")

    def both(o):
        return _slots(o, faces, METHOD), _image_grad_slots(o, faces, image)

    concrete, seen = both(occ), _with_traced_rest_pose(occ, both)
    assert concrete[0] is not None and concrete[1] is not None
    assert seen == concrete

    # the image-plane sizes are measured lazily (only a derivative needs them): a concrete shape
    # seen by a forward pass leaves its measurement pending, and a traced rest pose of the same
    # topology gets it (the sizes of that shape), not generous defaults
    other = Method(bsv_grid=(5, 7), directions=(16, 16), bsv_gradient="image")  # no other test's
    pending = _image_grad_slots(occ, faces, other, lazy=True)
    assert callable(pending)
    assert _with_traced_rest_pose(occ, lambda o: _image_grad_slots(o, faces, other, lazy=True)) == pending
    sizes = pending()
    assert len(sizes) == 6 and sizes == _image_grad_slots(occ, faces, other)


def test_a_traced_rest_pose_measures_its_sizes_on_the_occluder_built_before_the_trace():
    # A user's first jax.grad with respect to unit_vertices, with no render before it: the
    # occluder built concretely (as build_scene builds it) is remembered per topology, and a traced
    # rest pose of that topology is measured on it, not given generous defaults (the airplane's
    # frame gradient: 1.6 s -> 0.16 s,
    # benchmarks/bench_first_grad.py). Faces in another order: a topology no other test has seen.
    from jshadow.scene import _edgescan_slots, _image_grad_slots

    faces = jnp.asarray(np.roll(np.asarray(_ICO.faces), 7, axis=0), jnp.int32)
    occ = scene_with(StretchY(jnp.float32(0.2)), faces=faces).occluders[0]
    method = Method(bsv_grid=(6, 9), directions=(16, 16), bsv_gradient="image")
    f_np = np.asarray(faces)
    forward, pending = _with_traced_rest_pose(
        occ, lambda o: (_edgescan_slots(o, f_np, method), _image_grad_slots(o, f_np, method, lazy=True))
    )
    assert forward is not None and callable(pending)
    # the sizes of the concrete occluder's poses (rest and five of its animation), measured now
    assert forward == _edgescan_slots(occ, np.asarray(faces), method)
    assert pending() == _image_grad_slots(occ, np.asarray(faces), method)

    # an occluder built inside a trace is not remembered (nothing concrete to measure on)
    other = jnp.asarray(np.roll(np.asarray(_ICO.faces), 11, axis=0), jnp.int32)
    jax.jit(lambda u: MeshOccluder(u, other, jnp.zeros(3), jnp.float32(1.0)).unit_vertices)(UNIT)
    from jshadow.entities import remembered_rest_shape

    assert remembered_rest_shape(other) is None and remembered_rest_shape(faces) is occ


def test_sizes_of_a_more_deformed_concrete_pose_are_merged_into_the_traced_ones():
    # What the edge-scan gradient's overflow message tells a render_at user: differentiating at a
    # concrete pose as deformed as the traced ones measures its sizes, and a traced rest pose of
    # the topology then gets the largest of every shape measured (element by element).
    from jshadow.scene import _image_grad_slots

    faces = jnp.asarray(np.roll(np.asarray(_ICO.faces), 13, axis=0), jnp.int32)  # a fresh topology
    f_np = np.asarray(faces)
    method = Method(bsv_grid=(6, 9), directions=(16, 16), bsv_gradient="image")
    a = scene_with(StretchY(jnp.float32(0.1)), faces=faces).occluders[0]
    stretched = UNIT * jnp.asarray([1.0, 2.5, 0.4], jnp.float32)
    b = MeshOccluder(stretched, faces, a.center, a.radius, StretchY(jnp.float32(0.1)))
    sizes_a = _image_grad_slots(a, f_np, method, lazy=True)()  # as a derivative calls it
    sizes_b = _image_grad_slots(b, f_np, method, lazy=True)()
    assert sizes_a != sizes_b  # the two shapes need different sizes
    seen = _with_traced_rest_pose(a, lambda o: _image_grad_slots(o, f_np, method, lazy=True))
    assert seen == tuple(max(x, y) for x, y in zip(sizes_a, sizes_b, strict=True))


def test_plane_and_own_vertices_evaluated_apart_give_the_same_field_and_gradient(monkeypatch):
    # render_at evaluates the field on the plane (constant points, placed centre: no derivative for
    # their cells) and on the occluder's own vertices as two calls; the values and the gradient
    # must be those of one call over all receivers, and the plane's interpolation weights and frame
    # angles must drop out of the backward pass: fewer reductions over the plane's 49 receivers
    # than over the 42 moving vertices, whose cells do carry a derivative
    import jshadow.scene as sc
    from jshadow.visibility import bsv_sphere

    method = Method(bsv_grid=(8, 12), directions=(16, 16))
    base = scene_with(Scale(jnp.float32(0.1)))
    scene = Scene(method, base.receivers, base.occluders, base.lights, base.environment, self_shadow=True)
    occ = scene.occluders[0]
    assert occ.unit_vertices.shape[0] == 42 and scene.receivers.points.shape[0] == 49
    m = scene.method  # any BSV of the right shape will do: the sphere's (no mesh sampling to compile)
    bsv = bsv_sphere(occ.center, occ.radius, n=m.field_bands, grid=m.bsv_grid, shell=m.shell)
    weights = jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, (91, 16)), jnp.float32)

    def loss(a, plane_first):
        # the BSV and the own vertices move with a, the plane does not (nor the placed centre)
        b = eqx.tree_at(
            lambda b: (b.coeffs, b.shell_radius), bsv, (bsv.coeffs * (1 + a), bsv.shell_radius * (1 + a))
        )
        points = jnp.concatenate([scene.receivers.points, occ.vertices(0.0) * (1 + a)])
        (vis,), (dist,) = sc.occluder_visibilities(scene, (b,), points, plane_first=plane_first)
        return jnp.sum(weights * vis) + jnp.sum(dist)

    def reductions(plane_first, size):
        text = str(jax.make_jaxpr(jax.grad(loss), static_argnums=1)(a0, plane_first))
        return len(re.findall(rf"f32\[{size}\] = reduce_sum", text))

    a0 = jnp.float32(0.05)
    split, one = (jax.jit(jax.value_and_grad(loss), static_argnums=1)(a0, p) for p in (True, False))
    np.testing.assert_allclose(float(split[0]), float(one[0]), rtol=1e-6)
    np.testing.assert_allclose(float(split[1]), float(one[1]), rtol=1e-5)
    assert abs(float(one[1])) > 1e-3
    assert reductions(False, 49) == 0  # one call: no plane-sized arrays at all
    assert reductions(True, 49) < reductions(True, 42)  # (none of 42 values without the split)
    with pytest.raises(ValueError, match="plane_first"):  # points that cannot begin with the plane
        sc.occluder_visibilities(scene, (bsv,), scene.receivers.points[:10], plane_first=True)
    # and render_at asks for it
    seen = []
    original = sc.occluder_visibilities
    monkeypatch.setattr(sc, "occluder_visibilities", lambda *a, **k: seen.append(k) or original(*a, **k))
    jax.eval_shape(lambda: sc.render_at(scene, 0.0))
    assert len(seen) == 1 and seen[0]["plane_first"] is True


def test_a_traced_position_still_measures_the_animation_poses():
    # The sizes are measured on the rest pose and five poses of the animation; only a traced
    # deformation parameter limits them to the rest pose. A traced centre or radius (moving the
    # occluder) does not change the sampled images, so its animation is still measured.
    from jshadow.scene import _poses

    occ = scene_with(StretchY(jnp.float32(0.3))).occluders[0]
    unit = np.asarray(occ.unit_vertices)
    method = Method(bsv_grid=(8, 12), directions=(16, 16))
    counts = {}

    @jax.jit
    def traced(center, radius, a):
        counts["placement"] = len(
            _poses(eqx.tree_at(lambda o: (o.center, o.radius), occ, (center, radius)), unit, method)
        )
        counts["deformation"] = len(_poses(eqx.tree_at(lambda o: o.deform.a, occ, a), unit, method))
        return center

    traced(occ.center, occ.radius, occ.deform.a)
    assert counts == {"placement": 6, "deformation": 1}
    stretched = _poses(occ, unit, method)[-1]  # t = 1, the unit frame: y stretched by 1.3
    np.testing.assert_allclose(np.ptp(stretched[: len(unit), 1]), 1.3 * np.ptp(unit[:, 1]), rtol=1e-5)
