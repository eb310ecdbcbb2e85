"""Receivers next to a mesh occluder by exact rays (``[method] contact_visibility = "rays"``;
:func:`jshadow.scene.contact_rows_at_time`).

Claims tested: the receivers marked near are exactly those within the reach of a vertex (a numpy
brute force) or of a face larger than the reach (a cube's exact distance), own vertices never;
their cast visibility SH is the analytic cap of the sphere the icosphere approximates, and the
cube's by a fine grid; cast over the half of the grid above a receiver's plane it equals the whole
turned grid's, and a mesh reaching below the plane gets the whole grid (in a trace too); under a
constant sky their irradiance matches the exact sphere's through the same path (and the closed form
within that path's floor) far better than the field's; their sphere-light and environment-light
fractions match the exact ray–sphere tests that the images' path uses for a sphere occluder; a mesh
far from every receiver gives None (no work, the read-out path kept); the Renderer makes them once
for shapes that do not change and every frame for a deforming mesh, in one call and in pieces, as
``render`` does, which keeps the rows of a scene and time it has seen (not of a traced one);
differentiating them raises in words, ``"field"`` differentiates; config keys are read, checked and
chosen by "auto" (over a deforming mesh by the ray tests a frame would take).
"""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from test_environment_lights import _sun_map
from test_scene import SMALL, f32, icosphere_occluder, plane

from jshadow.config import AUTO_CONTACT_TESTS, ConfigError, build_scene, config_from_dict
from jshadow.entities import Environment, MeshOccluder, Scene, SphereLight, SphereOccluder
from jshadow.field import sphere_visibility_sh
from jshadow.geometry import Twist, normalize_to_unit_sphere
from jshadow.runner import Renderer
from jshadow.scene import (
    CONTACT_GRID,
    CONTACT_GRID_DIM,
    CONTACT_NO_DERIVATIVE,
    CONTACT_REACH,
    CONTACT_SH_SHARE,
    clear_pose_caches,
    contact_grid,
    contact_ray_tests,
    contact_rows_at_time,
    environment_visible_fraction,
    light_visible_fractions,
    render,
    render_at,
    scene_lighting,
)
from jshadow.sh import rotate, sh_basis, sphere_grid
from jshadow.visibility import halfspace_visibility_sh, ray_fan_any_hit
from jshadow.visibility._raycast import _onb

R, C = 0.5, (0.0, 0.55, 0.0)  # a sphere 0.05 above the plane y = 0
RAYS = dataclasses.replace(SMALL, contact_visibility="rays")
SKY = Environment(f32(1.0, 1.0, 1.0))


def _scene(method=RAYS, center=C, **kw):
    occ = icosphere_occluder(center, R, subdiv=3)
    kw.setdefault("environment", SKY)
    return Scene(method=method, receivers=plane(n=9, size=2.0), occluders=(occ,), **kw)


def _sphere_twin(scene):
    """``scene`` with its icosphere replaced by the exact sphere it approximates, on the field's
    path (the images' path tests a sphere occluder by exact ray–sphere hits)."""
    field = dataclasses.replace(scene.method, contact_visibility="field")
    return dataclasses.replace(scene, method=field, occluders=(SphereOccluder(f32(*C), jnp.float32(R)),))


def _within_reach(scene) -> np.ndarray:
    p = np.asarray(scene.receivers.points, np.float64)
    v = np.asarray(scene.occluders[0].vertices(0.0), np.float64)
    return np.sqrt(((p[:, None] - v[None]) ** 2).sum(-1)).min(1) < CONTACT_REACH * R


def test_near_receivers_and_their_visibility_are_the_spheres():
    scene = _scene()
    near, rows, lights, env = contact_rows_at_time(scene, 0.0)
    assert lights is None and env is None  # no sphere light, no environment lights
    want = _within_reach(scene)
    assert 3 <= want.sum() < want.size // 4
    np.testing.assert_array_equal(np.asarray(near[:, 0]), want)
    # the icosphere's vertices lie on the sphere: its cast visibility is the sphere's cap up to the
    # facets and the 24 x 48 grid (measured 0.036 against coefficients up to 2.8)
    cap = np.asarray(sphere_visibility_sh(f32(*C), jnp.float32(R), scene.receivers.points, 4))
    got = np.asarray(rows[:, 0])
    np.testing.assert_allclose(got[want], cap[want], atol=0.06)
    assert np.all(got[~want] == 0.0)


def _cube_scene():
    """A cube of bounding radius R whose bottom face (side 2R/√3, larger than the reach) lies 0.05
    above the plane: the receivers under its middle are far from every vertex."""
    m = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    unit = normalize_to_unit_sphere(jnp.asarray(m.vertices, jnp.float32))
    half = R / math.sqrt(3.0)
    occ = MeshOccluder(unit, jnp.asarray(m.faces, jnp.int32), f32(0.0, 0.05 + half, 0.0), jnp.float32(R))
    return Scene(method=RAYS, receivers=plane(n=9, size=2.0), occluders=(occ,), environment=SKY), half


def test_receivers_under_a_large_face_are_near_and_cast():
    scene, half = _cube_scene()
    near, rows, _, _ = contact_rows_at_time(scene, 0.0)
    near = np.asarray(near[:, 0])
    p = np.asarray(scene.receivers.points, np.float64)
    c = np.asarray(scene.occluders[0].center, np.float64)
    box = np.linalg.norm(np.maximum(np.abs(p - c) - half, 0.0), axis=1)  # exact, outside the box
    np.testing.assert_array_equal(near, box < CONTACT_REACH * R)
    assert near.sum() == 9 and (_within_reach(scene) & near).sum() == 4  # 5 by the faces alone
    # their rows: the visibility SH of the cube (a fine grid's rays as the measure; the rows are cast
    # over the half of the 24 x 48 grid above the plane)
    v, f = scene.occluders[0].vertices(0.0), scene.occluders[0].faces
    d, w = sphere_grid(96, 192)
    fine = (1.0 - ray_fan_any_hit(scene.receivers.points[near], d, v, f).astype(jnp.float32)) @ (
        sh_basis(d, 4) * w[:, None]
    )
    # measured: 0.059 at most (the whole 24 x 48 grid in world axes: 0.042; the cube's edges run
    # along the grid's rings), against coefficients up to 2.7
    np.testing.assert_allclose(np.asarray(rows[near, 0]), np.asarray(fine), atol=0.08)


def test_halfspace_rows_are_the_whole_turned_grid_at_half_the_rays():
    scene = _scene()
    p, q = scene.receivers.points[:20], scene.receivers.normals[:20]
    v, f = scene.occluders[0].vertices(0.0), scene.occluders[0].faces
    got = halfspace_visibility_sh(p, q, v, f, 4, CONTACT_GRID)
    # the whole grid, turned as the function turns it (pole along a tangent, φ = π/2 along n), cast
    # in full: the rays below the plane miss a mesh above it, so the two agree to rounding
    e1, e2 = _onb(q)
    frame = jnp.stack([e2, q, e1], -1)
    d, w = sphere_grid(*CONTACT_GRID)
    vis = 1.0 - ray_fan_any_hit(p, jnp.einsum("mij,kj->mki", frame, d), v, f).astype(jnp.float32)
    want = rotate(vis @ (sh_basis(d, 4) * w[:, None]), frame)
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=2e-5)
    with pytest.raises(ValueError, match="even"):
        halfspace_visibility_sh(p, q, v, f, 4, (24, 47))


def test_a_mesh_below_a_receivers_plane_gets_the_whole_grid():
    """A sphere through the plane: the near receivers' rows are the world grid's whole cast, on the
    host's path and in a trace alike."""
    scene = _scene(center=(0.0, 0.3, 0.0))
    near, rows, _, _ = contact_rows_at_time(scene, 0.0)
    m = np.asarray(near[:, 0])
    assert m.sum() >= 3
    v, f = scene.occluders[0].vertices(0.0), scene.occluders[0].faces
    d, w = sphere_grid(*CONTACT_GRID)
    p = scene.receivers.points[m]
    want = (1.0 - ray_fan_any_hit(p, d, v, f).astype(jnp.float32)) @ (sh_basis(d, 4) * w[:, None])
    np.testing.assert_allclose(np.asarray(rows[m, 0]), np.asarray(want), atol=2e-5)
    traced = jax.jit(lambda t: contact_rows_at_time(scene, t)[1])(jnp.float32(0.0))
    np.testing.assert_allclose(np.asarray(traced), np.asarray(rows), atol=2e-5)


def test_own_vertices_are_never_near():
    scene = _scene(self_shadow=True)
    near = np.asarray(contact_rows_at_time(scene, 0.0)[0][:, 0])
    n_plane = scene.receivers.points.shape[0]
    assert near[:n_plane].sum() >= 3 and not near[n_plane:].any()


def test_contact_irradiance_matches_the_closed_form_where_the_field_does_not():
    """Under a unit constant sky a sphere whose cap stays above the horizon leaves
    E = π (1 − sin²α cos β) (α its angular radius, β its centre's angle from the normal)."""
    out = {}
    for mode in ("rays", "field"):
        out[mode] = np.asarray(render(_scene(dataclasses.replace(RAYS, contact_visibility=mode))).irradiance)
    scene = _scene()
    p = np.asarray(scene.receivers.points, np.float64)
    rel = p - np.asarray(C)
    dist = np.linalg.norm(rel, axis=1)
    sin_a = R / dist
    beta = np.arccos(np.clip(-rel[:, 1] / dist, -1.0, 1.0))
    ok = _within_reach(scene) & (np.arcsin(sin_a) + beta < np.pi / 2)
    assert ok.sum() >= 3
    exact = np.pi * (1.0 - sin_a**2 * np.cos(beta))
    # the exact sphere's n-band visibility through the same path: the floor of any cast visibility
    floor = np.asarray(render(_sphere_twin(scene)).irradiance)[:, 0]
    err = {k: np.abs(v[:, 0] - floor)[ok].max() / np.pi for k, v in out.items()}
    # measured: 0.25 % by the rays, 3.1 % by the field (extrapolated inward from 1.5 radii); against
    # the closed form the floor is 1.39 % (the 4-band truncation, at the receiver right under it) and
    # the rays 1.14 %
    assert err["rays"] < 0.005 and err["field"] > 5 * err["rays"]
    assert np.abs(out["rays"][:, 0] - exact)[ok].max() / np.pi < 0.015
    far = ~_within_reach(scene)
    np.testing.assert_allclose(out["rays"][far], out["field"][far], rtol=1e-6)


def test_sphere_light_fraction_matches_the_exact_sphere_test():
    light = (SphereLight(f32(2.0, 1.2, 1.0), jnp.float32(0.8), f32(5.0, 5.0, 5.0)),)
    images = dataclasses.replace(RAYS, light_visibility="images")
    scene = _scene(images, environment=None, lights=light)
    near, _, lights, env = contact_rows_at_time(scene, 0.0)
    assert env is None and lights.shape == (81, 1)
    # the images' path tests a sphere occluder by exact ray-sphere hits along the same cap directions
    ball = _sphere_twin(scene)
    exact = np.asarray(
        light_visible_fractions(ball, (None,), ball.receivers.points, ball.receivers.normals)[0]
    )
    m = np.asarray(near[:, 0])
    assert 0.2 < exact[m].mean() < 0.8  # partly shadowed there
    # measured: equal at every near receiver (a facet could pass a grazing ray the sphere stops)
    np.testing.assert_allclose(np.asarray(lights[m, 0]), exact[m], atol=0.03)
    # and the rendered fraction is the contact one there
    assert np.all(np.asarray(lights[~m, 0]) == 1.0)


def test_environment_light_fraction_matches_the_exact_sphere_test():
    sun = Environment(f32(1.0, 1.0, 1.0), jnp.asarray(_sun_map()), "hdr")
    split = dataclasses.replace(RAYS, light_visibility="images", environment_lights=8)
    scene = _scene(split, environment=sun)
    lighting = scene_lighting(scene)
    near, _, lights, env = contact_rows_at_time(scene, 0.0, lighting)
    assert lights is None and env.shape == (81, 3)
    ball = _sphere_twin(scene)
    pts, nrm = ball.receivers.points, ball.receivers.normals
    exact, _ = environment_visible_fraction(ball, (None,), lighting.env_lights, pts, nrm)
    m = np.asarray(near[:, 0])
    np.testing.assert_allclose(np.asarray(env)[m], np.asarray(exact)[m], atol=0.03)


def test_grid_is_coarser_where_the_n_band_path_carries_little_light(monkeypatch):
    """A sun map split into lamps leaves its dim sky on the n-band path: the rows are cast on the
    coarser grid there, close to the whole grid's, and on the whole grid where the sky is bright."""
    import jshadow.scene as scene_mod

    split = dataclasses.replace(RAYS, light_visibility="images", environment_lights=8)
    assert contact_grid(_scene()) == tuple(CONTACT_GRID)  # a constant sky: no lamps
    for sky, sun, dim in ((0.1, 400.0, True), (0.3, 40.0, False)):
        scene = _scene(
            split, environment=Environment(f32(1.0, 1.0, 1.0), jnp.asarray(_sun_map(sky=sky, sun=sun)), "hdr")
        )
        lighting = scene_lighting(scene)
        rest, bright = float(np.mean(lighting.env_sh[0])), float(np.mean(lighting.env_bright_sh[0]))
        assert (rest / (rest + bright) <= CONTACT_SH_SHARE) == dim  # measured 0.177 and 0.867
        assert contact_grid(scene, lighting) == tuple(CONTACT_GRID_DIM if dim else CONTACT_GRID)
        clear_pose_caches()
        near, rows, _, _ = contact_rows_at_time(scene, 0.0, lighting)
        got = np.asarray(render(scene, 0.0).irradiance)
        monkeypatch.setattr(scene_mod, "CONTACT_GRID_DIM", CONTACT_GRID)  # the whole grid everywhere
        clear_pose_caches()
        _, whole, _, _ = contact_rows_at_time(scene, 0.0, lighting)
        want = np.asarray(render(scene, 0.0).irradiance)
        monkeypatch.undo()
        m = np.asarray(near[:, 0])
        assert m.sum() >= 3
        diff = np.abs(np.asarray(rows) - np.asarray(whole))[m]
        if dim:  # another grid (coefficients up to about 2.8; measured 0.080 at most), a small change
            assert 1e-3 < diff.max() < 0.15
            assert np.abs(got - want).max() < 0.005 * want.mean()  # measured 0.16 % of the mean
        else:
            assert diff.max() == 0.0 and np.array_equal(got, want)
    clear_pose_caches()


def test_far_mesh_gives_none_and_keeps_the_readout():
    high = _scene(center=(0.0, 1.5, 0.0), n_frames=3)
    assert contact_rows_at_time(high, 0.0) is None
    assert contact_rows_at_time(_scene(dataclasses.replace(RAYS, contact_visibility="field")), 0.0) is None
    r = Renderer(high)
    for f in range(3):
        r.frame(f)
    assert r.contact_computations == 1 and r.readout_frames == 3
    low = Renderer(_scene(n_frames=3))
    for f in range(3):
        _, times = low.frame(f)
    assert low.readout_frames == 0 and "contact_ms" in times


def test_renderer_reuses_static_contact_and_matches_render():
    scene = _scene(n_frames=3)
    want = np.asarray(render(scene, 1).irradiance)
    r = Renderer(scene)
    for f in range(3):
        got = np.asarray(r.frame(f)[0].irradiance)
    assert r.contact_computations == 1
    np.testing.assert_allclose(got, want, rtol=2e-6, atol=1e-6)
    pieces = np.asarray(Renderer(scene, chunk=7).frame(1)[0].irradiance)
    np.testing.assert_allclose(pieces, want, rtol=2e-6, atol=1e-6)


def test_render_keeps_the_rows_of_a_scene_it_has_seen(monkeypatch):
    import jshadow.scene as scene_mod

    calls = []
    made = scene_mod.contact_rows_at_time
    monkeypatch.setattr(scene_mod, "contact_rows_at_time", lambda *a: calls.append(1) or made(*a))
    scene_mod.clear_pose_caches()
    scene = _scene(n_frames=3)
    first = np.asarray(render(scene, 1).irradiance)
    again = np.asarray(render(scene, 1).irradiance)
    assert len(calls) == 1
    np.testing.assert_array_equal(again, first)
    # another pose, another receiver plane or another light: made anew
    render(_scene(center=(0.0, 0.56, 0.0), n_frames=3), 1)
    render(dataclasses.replace(scene, environment=Environment(f32(2.0, 1.0, 1.0))), 1)
    assert len(calls) == 3
    scene_mod.clear_pose_caches()
    render(scene, 1)
    assert len(calls) == 4
    # a traced time: made in the trace, nothing kept
    jax.jit(lambda t: render_at(scene, t).irradiance)(jnp.float32(0.5))
    assert len(calls) == 5 and len(scene_mod._CONTACT) == 1


def test_deforming_mesh_is_cast_every_frame():
    occ = icosphere_occluder(C, R, Twist(jnp.float32(0.0), jnp.float32(1.0), 1), subdiv=2)
    scene = Scene(RAYS, plane(n=9, size=2.0), (occ,), (), SKY, n_frames=3)
    r = Renderer(scene)
    for f in range(3):
        got = np.asarray(r.frame(f)[0].irradiance)
        np.testing.assert_allclose(got, np.asarray(render(scene, f).irradiance), rtol=2e-6, atol=1e-6)
    assert r.contact_computations == 3
    # under jit with a traced time the rows are made in the trace: the same frame
    jitted = np.asarray(jax.jit(lambda t: render_at(scene, t).irradiance)(jnp.float32(1.0)))
    np.testing.assert_allclose(jitted, got, rtol=2e-6, atol=1e-6)


def test_differentiating_contact_rows_raises_and_field_differentiates():
    def loss(y, method):
        occ = icosphere_occluder((0.0, 0.0, 0.0), R, subdiv=2)
        occ = dataclasses.replace(occ, center=jnp.stack([0.0, y, 0.0]).astype(jnp.float32))
        scene = Scene(method, plane(n=9, size=2.0), (occ,), (), SKY)
        return jnp.sum(render(scene).irradiance)

    with pytest.raises(ValueError, match="contact_visibility = 'field'"):
        jax.grad(loss)(jnp.float32(0.55), RAYS)
    assert "contact_visibility = 'field'" in CONTACT_NO_DERIVATIVE
    g = jax.grad(loss)(jnp.float32(0.55), dataclasses.replace(RAYS, contact_visibility="field"))
    assert np.isfinite(float(g)) and float(g) != 0.0


def _config(**method):
    return {
        "receiver": {"type": "plane", "center": [0, 0, 0], "size": [2, 2], "resolution": [8, 8]},
        "occluder": [{"type": "mesh", "shape": "icosphere", "center": [0, 0.55, 0], "radius": 0.5}],
        "environment": {"type": "constant", "radiance": [1, 1, 1]},
        "method": method,
    }


def test_config_reads_checks_and_chooses_contact_visibility():
    def chosen(config):
        return build_scene(config_from_dict(config)).method.contact_visibility

    assert chosen(_config()) == "rays"
    assert chosen(_config(preset="paper")) == "field"
    assert chosen(_config(contact_visibility="field")) == "field"
    with pytest.raises(ConfigError, match="contact_visibility"):
        config_from_dict(_config(contact_visibility="exact"))
    # a deforming mesh's rows are cast every frame: where they take few enough ray-triangle tests
    bending = _config()
    bending["occluder"][0]["deform"] = {"type": "bend", "amount": [0.0, 0.5], "axis": "x", "toward": "y"}
    assert chosen(bending) == "rays"
    tests = {}
    for res in (8, 400):
        bending["receiver"]["resolution"] = [res, res]
        scene = build_scene(config_from_dict(bending))
        tests[res] = contact_ray_tests(scene.occluders, scene.receivers.points, math.prod(CONTACT_GRID))
        want = "rays" if tests[res] <= AUTO_CONTACT_TESTS else "field"
        assert scene.method.contact_visibility == want
    assert 0 < tests[8] <= AUTO_CONTACT_TESTS < tests[400]
    sphere = _config()
    sphere["occluder"] = [{"type": "sphere", "center": [0, 0.55, 0], "radius": 0.5}]
    assert chosen(sphere) == "field"
    with pytest.raises(ValueError, match="contact_visibility"):
        dataclasses.replace(RAYS, contact_visibility="yes")
