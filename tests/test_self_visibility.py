"""Self-shadowing by rays at the occluders' own vertices (``[method] self_visibility = "rays"``).

Claims tested: the ray-cast visibility of a convex mesh at its vertices is the complement of each
vertex's tangent cone (closed form); on a torus lying over a plane the rays' irradiance at the
vertices is within 1.2 % relative RMSE of the Monte Carlo reference, where the field's inward
extrapolation is off by more than 10 %; the Renderer's one-call, split and chunked paths and
``render`` agree; a shape that does not change is cast once, a deforming one every frame, and
``render`` reuses the cast of a pose it has seen; the option is refused under differentiation with
respect to the vertices (``jshadow fit`` says so in one line) and free elsewhere; the config keys
are read and checked, and ``jshadow render`` reports the cast's time and count.
"""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from test_scene import SMALL, f32, plane

import jshadow.geometry
from jshadow import sh
from jshadow.config import ConfigError, config_from_dict
from jshadow.entities import Environment, MeshOccluder, Method, Scene, SphereLight
from jshadow.geometry import Twist, normalize_to_unit_sphere
from jshadow.reference import reference
from jshadow.runner import Renderer
from jshadow.scene import occluder_own_visibility, render, self_visibility_owners
from jshadow.visibility import cap_sh_projection, vertex_visibility_sh

GRID = (8, 16)  # ray directions per vertex in the tests: fast, and the same code path as 12 × 48
RAYS = dataclasses.replace(SMALL, self_visibility="rays", self_visibility_grid=GRID)


def _torus(deform=None, sections=(24, 12)):
    """A torus of 288 vertices lying flat (axis +y) over the plane, radius 0.8 at height 1."""
    m = trimesh.creation.torus(
        major_radius=1.0, minor_radius=0.4, major_sections=sections[0], minor_sections=sections[1]
    )
    unit = normalize_to_unit_sphere(jnp.asarray(m.vertices, jnp.float32))
    unit = unit @ jnp.asarray([[1, 0, 0], [0, 0, -1], [0, 1, 0]], jnp.float32).T  # axis z -> y
    return MeshOccluder(unit, jnp.asarray(m.faces, jnp.int32), f32(0, 1.0, 0), jnp.float32(0.8), deform)


def _scene(method, occ, n=3, n_frames=1):
    return Scene(
        method, plane(n=n), (occ,), (), Environment(f32(1, 1, 1)), self_shadow=True, n_frames=n_frames
    )


def test_convex_mesh_sees_the_complement_of_each_tangent_cone():
    """From a vertex of a convex polyhedron a ray hits the mesh iff it points into the tangent cone
    {ω : n_f · ω < 0 for every face f at the vertex}; projected with the same rule, the SH of the
    whole-sphere cast agree, and the hemisphere cast is the hemisphere about the vertex normal."""
    m = trimesh.creation.icosphere(subdivisions=1)
    rot = np.asarray(trimesh.transformations.random_rotation_matrix(np.random.default_rng(3).random(3)))
    v = (m.vertices @ rot[:3, :3].T).astype(np.float64)
    faces = np.asarray(m.faces)
    nf = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    nf /= np.linalg.norm(nf, axis=-1, keepdims=True)
    grid = (12, 24)
    dirs, w = sh.sphere_grid(*grid, np.float32)
    d = np.asarray(dirs, np.float64)
    visible = np.ones((len(v), len(d)))
    for i in range(len(v)):
        into = np.all(nf[np.any(faces == i, axis=1)] @ d.T < 0, axis=0)
        visible[i, into] = 0.0
    assert 0.3 < visible.mean() < 0.7  # about the outer half-space at every vertex
    expected = np.asarray(sh.project(jnp.asarray(visible, jnp.float32), dirs, w, 4))
    vj, fj = jnp.asarray(v, jnp.float32), jnp.asarray(faces)
    got = np.asarray(vertex_visibility_sh(vj, fj, 4, grid, hemisphere=False))
    np.testing.assert_allclose(got, expected, atol=2e-5)

    # over the normal hemisphere (the default): every direction above the area-weighted normal's
    # plane leaves a convex mesh, so V is the hemisphere about n, whose SH is its zonal projection
    # turned to n by the addition theorem: c_lm = z_l · √(4π / (2l + 1)) · Y_lm(n)
    nv = np.zeros_like(v)
    for k in range(3):
        np.add.at(nv, faces[:, k], np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]]))
    nv /= np.linalg.norm(nv, axis=-1, keepdims=True)
    zonal = np.asarray(cap_sh_projection(jnp.float32(0.0), 4))
    l_of = np.repeat(np.arange(4), 2 * np.arange(4) + 1)
    scale = zonal[l_of * l_of + l_of] * np.sqrt(4 * np.pi / (2 * l_of + 1))
    expected = scale * np.asarray(sh.sh_basis(jnp.asarray(nv, jnp.float32), 4))
    np.testing.assert_allclose(np.asarray(vertex_visibility_sh(vj, fj, 4, (6, 12))), expected, atol=2e-5)


def test_the_transfer_of_a_convex_mesh_is_the_clamped_cosine():
    """Every direction above a convex mesh's vertex normal leaves it, so the cast transfer
    ``V·max(0, n·ω)`` is the clamped cosine about n (:func:`jshadow.sh.clamped_cosine`): exact for
    the hemisphere rule, lifted off the surface or not."""
    m = trimesh.creation.icosphere(subdivisions=2)
    v, f = jnp.asarray(m.vertices, jnp.float32), jnp.asarray(m.faces)
    nv = np.asarray(jshadow.geometry.vertex_normals(v, f))
    want = np.asarray(sh.clamped_cosine(jnp.asarray(nv), 4))
    for offset in (None, 1e-4):
        got = np.asarray(vertex_visibility_sh(v, f, 4, (6, 12), offset=offset, transfer=True))
        np.testing.assert_allclose(got, want, atol=2e-5)
    whole = np.asarray(vertex_visibility_sh(v, f, 4, (24, 48), hemisphere=False, transfer=True))
    assert np.abs(whole - want).max() < 0.02  # the whole-sphere rule is not exact at the cut


def test_rays_shade_the_own_vertices_by_their_cast_transfer():
    """Under a constant sky of radiance 1 an own vertex's irradiance is ``∫ V(ω) max(0, n·ω) dω``;
    render's rows equal that integral done here on the same directions with the watertight ray
    test from origins lifted by the reference's ε (:func:`jshadow.entities.surface_offset`, which
    the reference renderer uses), and the plane's rows are the field's."""
    from jshadow.entities import receivers_at, surface_offset
    from jshadow.visibility._raycast import _onb, ray_triangle_any_hit

    occ = _torus(sections=(12, 6))
    scene = _scene(RAYS, occ, n=2)
    e = np.asarray(render(scene).irradiance, np.float64)
    pts, nrm = (np.asarray(x) for x in receivers_at(scene))
    v, f = pts[4:], np.asarray(occ.faces)
    lift = float(surface_offset(scene, 0.0))
    size = np.ptp(np.concatenate([pts, np.asarray(occ.vertices(0.0))]), axis=0).max()
    assert lift == pytest.approx(10 * np.finfo(np.float32).eps * 100 * size, rel=1e-6)
    local, w = (np.asarray(x) for x in sh.hemisphere_grid(*GRID, jnp.float32))
    e1, e2 = (np.asarray(x) for x in _onb(jnp.asarray(nrm[4:])))
    dirs = np.einsum("vij,kj->vki", np.stack([e1, e2, nrm[4:]], -1), local).astype(np.float32)
    origins = np.broadcast_to((v + lift * nrm[4:])[:, None], dirs.shape).astype(np.float32)
    hit = np.asarray(ray_triangle_any_hit(origins, dirs, v.astype(np.float32), f, t_min=lift))
    want = ((~hit) * (w * local[:, 2])).sum(1)
    assert 0.2 < want.min() / np.pi < 0.9  # the torus's inner vertices see little of the sky
    np.testing.assert_allclose(e[4:, 0], want, rtol=2e-5, atol=1e-5)
    field = np.asarray(render(_scene(SMALL, occ, n=2)).irradiance)
    np.testing.assert_array_equal(field[:4], e[:4])


def test_a_concrete_cast_tests_the_faces_above_each_vertex_and_equals_the_traced_one():
    """A concrete mesh's cast (each vertex's fan against the faces above its tangent plane,
    :func:`jshadow.visibility.hemisphere_fan_any_hit`) gives the coefficients of the traced cast
    (every face, as under ``jit``): the visibility and the transfer, lifted or not."""
    occ = _torus(sections=(16, 8))
    v = np.asarray(occ.unit_vertices) * 0.8
    f = np.asarray(occ.faces)
    for offset, transfer in ((None, False), (np.float32(1e-3), True)):
        concrete = vertex_visibility_sh(v, f, 3, GRID, offset=offset, transfer=transfer)
        traced = jax.jit(
            lambda x, o=offset, t=transfer: vertex_visibility_sh(x, f, 3, GRID, offset=o, transfer=t)
        )(v)
        assert float(jnp.std(concrete[:, 0])) > 0.05  # the hole's vertices see less than the rim's
        np.testing.assert_allclose(np.asarray(concrete), np.asarray(traced), rtol=0, atol=1e-6)


def test_rays_fix_the_torus_self_shadowing_that_the_field_misses():
    occ = _torus()
    ref = reference(_scene(SMALL, occ), 1024, jax.random.PRNGKey(0))
    r = np.asarray(ref.irradiance, np.float64)[9:, 0]
    assert np.sqrt(np.mean(np.asarray(ref.irradiance_stderr)[9:, 0] ** 2)) < 0.01 * np.sqrt(np.mean(r**2))

    def rel_rmse(method):
        e = np.asarray(render(_scene(method, occ)).irradiance, np.float64)[9:, 0]
        return np.sqrt(np.mean((e - r) ** 2) / np.mean(r**2))

    field = rel_rmse(SMALL)
    rays = rel_rmse(dataclasses.replace(RAYS, self_visibility_grid=(12, 48)))
    # measured: field 24.8 %, rays 0.60 % (8 x 16 directions over the hemisphere: 0.77 %; the rays'
    # visibility SH in place of their transfer, before the transfer: 0.57 and 0.97 %)
    assert field > 0.10
    assert rays < 0.012


def test_renderer_paths_agree_and_reuse_the_cast_of_a_rigid_mesh():
    scene = _scene(RAYS, _torus(), n=5, n_frames=2)
    rend = Renderer(scene)
    (a, times), (b, _) = rend.frame(0), rend.frame(1)
    assert rend.self_visibility_computations == 1 and rend.bsv_computations == 1
    assert "self_visibility_ms" in times
    np.testing.assert_array_equal(np.asarray(a.irradiance), np.asarray(b.irradiance))
    whole = np.asarray(render(scene).irradiance)
    tol = 8 * np.finfo(np.float32).eps * np.abs(whole).max()
    np.testing.assert_allclose(np.asarray(a.irradiance), whole, rtol=0, atol=tol)
    split = Renderer(scene, chunk=100, split_stages=True).frame(0)[0]  # 25 + 288 rows: 4 pieces
    np.testing.assert_allclose(np.asarray(split.irradiance), whole, rtol=0, atol=tol)
    # the rays changed the vertices' rows only
    field = np.asarray(render(_scene(SMALL, _torus(), n=5)).irradiance)
    np.testing.assert_array_equal(field[:25], whole[:25])
    assert np.abs(field[25:] - whole[25:]).max() > 0.1


def test_a_rigid_mesh_with_rays_is_read_out_with_its_transfer_as_an_offset():
    """Frames after the first of a scene that does not change are read out of the field's table;
    what the cast transfer changes at the own vertices is a constant offset (the same numbers)."""
    scene = _scene(RAYS, _torus(), n=5, n_frames=3)
    rend = Renderer(scene)
    frames = [np.asarray(rend.frame(f)[0].irradiance) for f in range(3)]
    assert rend.readout_frames == 3 and rend.readout_reason is None  # prepared at the first frame
    whole = np.asarray(render(scene).irradiance)
    for e in frames:
        np.testing.assert_allclose(e, whole, rtol=0, atol=1e-5 * np.abs(whole).max())


def test_a_deforming_mesh_is_cast_every_frame():
    occ = _torus(Twist(0.0, 1.0, axis="y"), sections=(12, 6))
    rend = Renderer(_scene(RAYS, occ, n=2, n_frames=2))
    first, last = (np.asarray(rend.frame(f)[0].irradiance) for f in range(2))
    assert rend.self_visibility_computations == 2 and rend.bsv_computations == 2
    assert np.abs(first[4:] - last[4:]).max() > 1e-3  # the twisted vertices see another mesh


def test_owners_mark_each_mesh_vertex_row():
    scene = _scene(RAYS, _torus(sections=(12, 6)), n=2)
    owners = self_visibility_owners(scene)
    assert owners.shape == (4 + 72,)
    assert np.all(owners[:4] == -1) and np.all(owners[4:] == 0)


def test_differentiating_the_rays_with_respect_to_vertices_raises():
    scene = _scene(RAYS, _torus(sections=(12, 6)), n=2)

    def own(amount):  # what render() casts per mesh occluder
        occ = _torus(Twist(amount, amount, axis="y"), sections=(12, 6))
        return jnp.sum(occluder_own_visibility(occ, 0.0, scene))

    with pytest.raises(ValueError, match="self_visibility = 'field'"):
        jax.grad(own)(jnp.float32(0.3))
    assert np.isfinite(float(own(jnp.float32(0.3))))


def test_jit_and_radiance_gradient_of_render_with_rays():
    occ = _torus(sections=(12, 6))

    def irradiance(radiance):
        return render(Scene(RAYS, plane(n=2), (occ,), (), Environment(radiance), self_shadow=True)).irradiance

    eager = np.asarray(irradiance(f32(1, 1, 1)))
    jitted = np.asarray(jax.jit(irradiance)(f32(1, 1, 1)))
    # eager and compiled XLA round differently (measured: 8e-5 of the largest value)
    np.testing.assert_allclose(jitted, eager, rtol=0, atol=5e-4 * np.abs(eager).max())
    # with respect to anything but the vertices the cast is a constant: E is linear in the radiance
    g = jax.jit(jax.grad(lambda r: jnp.sum(irradiance(r)[:, 0])))(f32(1, 1, 1))
    np.testing.assert_allclose(np.asarray(g), [eager[:, 0].sum(), 0.0, 0.0], rtol=1e-4, atol=1e-3)


def test_rays_under_a_traced_light_centre():
    """The rays' lift depends on the scene's extent, lights included: a traced light centre (jit,
    grad) casts with a traced lift instead of the cache, and gives the eager numbers."""
    occ = _torus(sections=(12, 6))

    def total(c):
        light = SphereLight(c, jnp.float32(0.3), f32(5, 5, 5))
        scene = Scene(RAYS, plane(n=2), (occ,), (light,), Environment(f32(1, 1, 1)), self_shadow=True)
        return jnp.sum(render(scene).irradiance)

    c = f32(0.5, 3.0, 0.2)
    eager = float(total(c))
    value, g = jax.jit(jax.value_and_grad(total))(c)  # one traced program for both
    np.testing.assert_allclose(float(value), eager, rtol=1e-4)
    assert np.all(np.isfinite(np.asarray(g))) and np.abs(np.asarray(g)).max() > 0


def test_config_reads_and_checks_self_visibility():
    base = {
        "occluder": [{"type": "mesh", "shape": "egg", "subdivisions": 1, "center": [0, 1, 0], "radius": 0.5}],
        "receiver": {
            "type": "plane",
            "center": [0, 0, 0],
            "size": [2, 2],
            "resolution": [2, 2],
            "self_shadow": True,
        },
    }
    cfg = config_from_dict({**base, "method": {"self_visibility": "rays", "self_visibility_grid": [6, 10]}})
    method = cfg.method.to_method()
    assert method.self_visibility == "rays" and method.self_visibility_grid == (6, 10)
    assert config_from_dict(base).method.to_method().self_visibility == "field"
    with pytest.raises(ConfigError, match="self_visibility"):
        config_from_dict({**base, "method": {"self_visibility": "ray"}})
    with pytest.raises(ConfigError, match="self_visibility_grid"):
        config_from_dict({**base, "method": {"self_visibility_grid": [1, 10]}})
    with pytest.raises(ValueError, match="self_visibility"):
        Method(self_visibility="exact")


EGG = (
    "[method]\ndirections = [8, 8]\nbsv_grid = [6, 8]\n"
    'self_visibility = "rays"\nself_visibility_grid = [6, 12]\n'
    '[environment]\ntype = "constant"\n'
    '[[occluder]]\ntype = "mesh"\nshape = "egg"\nsubdivisions = 1\n'
    "center = [0.0, 1.0, 0.0]\nradius = 0.5\n"
    '[receiver]\ntype = "plane"\ncenter = [0.0, 0.0, 0.0]\nsize = [3.0, 3.0]\nresolution = [4, 4]\n'
    "self_shadow = true\n[animation]\nframes = 2\n"
)


def test_cli_render_reports_the_cast_once_for_a_rigid_mesh(tmp_path, capsys):
    from jshadow.cli import main

    cfg = tmp_path / "egg.toml"
    cfg.write_text(EGG)
    assert main(["render", str(cfg), "--out", str(tmp_path / "r")]) == 0
    t = json.loads((tmp_path / "r" / "timings.json").read_text())
    assert t["self_visibility_computations"] == 1 and t["bsv_computations"] == 1
    first, second = t["per_frame"]
    assert first["self_visibility_ms"] > second["self_visibility_ms"] >= 0
    # the receivers next to the egg (contact_visibility "auto": rays for a rigid mesh) are a stage too
    assert second["total_ms"] == pytest.approx(
        second["bsv_ms"] + second["self_visibility_ms"] + second["contact_ms"] + second["shading_ms"]
    )
    assert "own-vertex rays" in capsys.readouterr().out


def test_render_casts_a_pose_once_and_reuses_it(monkeypatch):
    import jshadow.scene as scene_module

    calls = []
    cast = scene_module.vertex_visibility_sh
    monkeypatch.setattr(
        scene_module, "vertex_visibility_sh", lambda *a, **k: calls.append(a[3]) or cast(*a, **k)
    )
    occ = _torus(sections=(10, 5))  # a pose no other test casts
    first = np.asarray(render(_scene(RAYS, occ, n=2)).irradiance)
    again = np.asarray(render(_scene(RAYS, occ, n=2)).irradiance)
    brighter = Scene(RAYS, plane(n=2), (occ,), (), Environment(f32(2, 2, 2)), self_shadow=True)
    np.testing.assert_allclose(np.asarray(render(brighter).irradiance), 2 * first, rtol=1e-6)
    np.testing.assert_array_equal(again, first)
    assert calls == [GRID]  # one cast for three renders of the same pose
    render(_scene(dataclasses.replace(RAYS, self_visibility_grid=(6, 12)), occ, n=2))
    assert calls == [GRID, (6, 12)]  # another grid is another cast


def test_cli_fit_of_a_mesh_parameter_with_rays_is_a_one_line_error(tmp_path, capsys):
    from jshadow.cli import main

    cfg = tmp_path / "fit.toml"
    cfg.write_text(
        EGG.replace("frames = 2", "frames = 1")
        + '[fit]\nparams = ["occluder.0.center"]\ntarget_values = [[0.1, 1.0, 0.0]]\nsteps = 2\n'
    )
    assert main(["fit", str(cfg), "--out", str(tmp_path / "f")]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if "error" in line]  # not the progress bar
    assert len(err) == 1 and err[0].startswith("jshadow fit: error: ")
    assert "self_visibility = 'field'" in err[0]


def test_transfer_and_lamps_from_one_cast_equal_the_two_casts(monkeypatch):
    """:func:`jshadow.visibility.vertex_transfer_and_lamps` (each vertex's grid and its lamps in
    one fan) gives the transfer of :func:`vertex_visibility_sh` and the lamp visibility of the
    scene's lamp rays bit for bit, on a torus whose hole shadows itself; the scene's
    :func:`occluder_own_casts` keeps both, so the two functions apart then cast nothing; traced,
    it falls back to them."""
    import jshadow.scene as scene_module
    from jshadow.scene import occluder_own_casts, occluder_own_light_visibility
    from jshadow.visibility import vertex_transfer_and_lamps

    occ = _torus(sections=(14, 7))
    v = np.asarray(occ.unit_vertices) * 0.8
    f = np.asarray(occ.faces)
    u = np.random.default_rng(3).normal(size=(37, 3))
    lamps = (u / np.linalg.norm(u, axis=-1, keepdims=True)).astype(np.float32)
    lift = np.float32(1e-3)
    transfer, vis = vertex_transfer_and_lamps(v, f, 3, GRID, lift, lamps)
    np.testing.assert_array_equal(
        np.asarray(transfer), np.asarray(vertex_visibility_sh(v, f, 3, GRID, offset=lift, transfer=True))
    )
    apart = np.asarray(scene_module._lamp_rays(v, f, jnp.asarray(lamps), lift))
    np.testing.assert_array_equal(np.asarray(vis), apart)
    above = np.asarray(jshadow.geometry.vertex_normals(jnp.asarray(v), jnp.asarray(f))) @ lamps.T > 0
    assert np.all(apart[~above] == 0) and 0.1 < apart[above].mean() < 0.95  # the hole blocks some
    with pytest.raises(ValueError, match="concrete"):
        jax.jit(lambda x: vertex_transfer_and_lamps(x, f, 3, GRID, lift, lamps))(v)

    scene = _scene(RAYS, occ, n=2)
    d = jnp.asarray(lamps)
    scene_module.clear_pose_caches()
    both = occluder_own_casts(occ, 0.0, scene, d)
    calls = []
    monkeypatch.setattr(scene_module, "vertex_visibility_sh", lambda *a, **k: calls.append(a))
    monkeypatch.setattr(scene_module, "_lamp_rays", lambda *a, **k: calls.append(a))
    np.testing.assert_array_equal(np.asarray(occluder_own_visibility(occ, 0.0, scene)), np.asarray(both[0]))
    np.testing.assert_array_equal(
        np.asarray(occluder_own_light_visibility(occ, 0.0, scene, d)), np.asarray(both[1])
    )
    assert calls == []  # both kept by the one cast
    monkeypatch.undo()
    joint = []
    real = scene_module.vertex_transfer_and_lamps
    monkeypatch.setattr(
        scene_module, "vertex_transfer_and_lamps", lambda *a, **k: joint.append(a) or real(*a, **k)
    )
    traced = jax.jit(lambda t: occluder_own_casts(occ, t, scene, d)[1])(jnp.float32(0.0))
    assert joint == []  # the pose is traced: the two functions, each by rays against every face
    np.testing.assert_array_equal(np.asarray(traced), np.asarray(both[1]))
