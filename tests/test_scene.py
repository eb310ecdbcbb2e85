"""Shadow-field rendering: closed forms, invariances, the BSV path against the analytic sphere."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from jshadow.entities import (
    Environment,
    MeshOccluder,
    Method,
    Receivers,
    Scene,
    SphereLight,
    SphereOccluder,
)
from jshadow.field import bsv_visibility_sh, sphere_visibility_sh
from jshadow.geometry import normalize_to_unit_sphere
from jshadow.runner import Renderer
from jshadow.scene import occlusion_table, render, render_at
from jshadow.visibility import bsv_sample_points, bsv_sphere


def plane(n=9, size=4.0, y=0.0):
    xs = np.linspace(-size / 2, size / 2, n)
    x, z = np.meshgrid(xs, xs)
    pts = np.stack([x.ravel(), np.full(x.size, y), z.ravel()], -1).astype(np.float32)
    nrm = np.tile(np.float32([0, 1, 0]), (x.size, 1))
    return Receivers(jnp.asarray(pts), jnp.asarray(nrm), jnp.full(3, 0.8, jnp.float32), (n, n))


def f32(*v):
    return jnp.asarray(v, jnp.float32)


def icosphere_occluder(center, radius, deform=None, subdiv=2):
    m = trimesh.creation.icosphere(subdivisions=subdiv)
    unit = normalize_to_unit_sphere(jnp.asarray(m.vertices, jnp.float32))
    return MeshOccluder(unit, jnp.asarray(m.faces, jnp.int32), f32(*center), jnp.float32(radius), deform)


SMALL = Method(bsv_grid=(12, 20), directions=(16, 16))


def test_unoccluded_constant_environment_gives_pi_l():
    L = f32(1.0, 0.5, 0.25)
    scene = Scene(method=SMALL, receivers=plane(), environment=Environment(L))
    out = render(scene)
    np.testing.assert_allclose(out.irradiance, np.pi * np.broadcast_to(L, out.irradiance.shape), rtol=1e-5)
    np.testing.assert_allclose(out.radiance, out.irradiance * 0.8 / np.pi, rtol=1e-6)


@pytest.mark.parametrize("bands, rtol", [(4, 0.07), (8, 0.02)])
def test_unoccluded_sphere_light_matches_closed_form(bands, rtol):
    # E = π sin²α cos β for a light of unit radiance fully above the horizon; the only error is the
    # band limit of the clamped cosine (its odd bands vanish, even ones decay like l^-2.5)
    c, r = f32(0.5, 3.0, 0.0), jnp.float32(0.4)
    light = SphereLight(c, r, f32(1, 1, 1))
    scene = Scene(method=Method(sh_bands=bands), receivers=plane(), lights=(light,))
    out = render(scene)
    rel = np.asarray(c) - np.asarray(out.points)
    d = np.linalg.norm(rel, axis=-1)
    exact = np.pi * (0.4 / d) ** 2 * rel[:, 1] / d
    np.testing.assert_allclose(out.irradiance[:, 0], exact, rtol=rtol)


def test_far_occluders_have_no_effect():
    L = f32(1.0, 1.0, 1.0)
    base = Scene(method=SMALL, receivers=plane(), environment=Environment(L))
    far = (SphereOccluder(f32(0, 1e4, 0), jnp.float32(1.0)), icosphere_occluder((1e4, 0, 0), 1.0))
    out0, out1 = render(base), render(eqx_replace(base, occluders=far))
    np.testing.assert_allclose(out1.irradiance, out0.irradiance, rtol=1e-4)


def eqx_replace(scene, **kw):
    fields = {f: getattr(scene, f) for f in ("method", "receivers", "occluders", "lights", "environment")}
    fields.update(self_shadow=scene.self_shadow, n_frames=scene.n_frames)
    fields.update(kw)
    return Scene(**fields)


@pytest.mark.usefixtures("x64")
def test_bsv_path_is_exact_on_the_shell_at_sample_points():
    # k = 1 (M = I) and receivers exactly at the BSV sample points: no interpolation, so the BSV path
    # must reproduce the analytic sphere visibility up to float rounding (checks frames + rotation).
    n = 4
    c, r = jnp.asarray([0.3, 1.0, -0.2]), jnp.asarray(0.5)
    bsv = bsv_sphere(c, r, n=n, grid=(12, 20), shell=1.5)
    pts, _ = bsv_sample_points(c, r, grid=(12, 20), shell=1.5)
    scene = Scene(method=Method(shell=1.5, dtype="float64"), receivers=plane())
    got = bsv_visibility_sh(bsv, occlusion_table(scene), pts)
    want = sphere_visibility_sh(c, r, pts, n)
    np.testing.assert_allclose(got, want, atol=1e-9)


def _sphere_scene(sphere_path_method=SMALL):
    return Scene(
        method=sphere_path_method,
        receivers=plane(n=15),
        occluders=(SphereOccluder(f32(0.0, 1.2, 0.0), jnp.float32(0.5)),),
        environment=Environment(f32(1, 1, 1)),
    )


def test_sphere_bsv_path_close_to_analytic():
    scene = _sphere_scene()
    exact = np.asarray(render(scene).irradiance[:, 0])
    via_bsv = np.asarray(render(scene, sphere_path="bsv").irradiance[:, 0])
    rel_rmse = np.sqrt(np.mean((via_bsv - exact) ** 2)) / exact.mean()
    print(f"sphere r=0.5 at y=1.2, paper model, BSV path vs analytic: relative RMSE {rel_rmse:.3%}")
    # the paper's square-silhouette model: DESIGN.md §2 calibrates ≈ 8 % for this scene
    assert rel_rmse < 0.12
    assert np.all(np.isfinite(via_bsv))


def test_rotating_the_scene_rotates_the_result():
    def scene_rotated(a):
        R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]], np.float32)
        rec = plane(n=7)
        rec = Receivers(rec.points @ R.T, rec.normals @ R.T, rec.albedo, rec.grid_shape)
        occ = SphereOccluder(f32(*(R @ np.float32([0.4, 1.0, 0.1]))), jnp.float32(0.4))
        light = SphereLight(f32(*(R @ np.float32([1.0, 3.0, 0.5]))), jnp.float32(0.3), f32(5, 5, 5))
        return Scene(SMALL, rec, (occ,), (light,), Environment(f32(1, 1, 1)))

    e0 = np.asarray(render(scene_rotated(0.0)).irradiance)
    e1 = np.asarray(render(scene_rotated(0.7)).irradiance)
    np.testing.assert_allclose(e1, e0, rtol=2e-4, atol=2e-4 * e0.max())


def test_self_shadowing_darkens_the_inside_of_a_torus():
    m = trimesh.creation.torus(major_radius=1.0, minor_radius=0.4, major_sections=24, minor_sections=12)
    unit = normalize_to_unit_sphere(jnp.asarray(m.vertices, jnp.float32))
    occ = MeshOccluder(unit, jnp.asarray(m.faces, jnp.int32), f32(0, 2.0, 0), jnp.float32(1.0))
    scene = Scene(SMALL, plane(n=3), (occ,), (), Environment(f32(1, 1, 1)), self_shadow=True)
    out = render(scene)
    e = np.asarray(out.irradiance[9:, 0])
    v = np.asarray(m.vertices)
    rho = np.hypot(v[:, 0], v[:, 1])  # trimesh's torus axis is z
    inner, outer = rho < 0.7, rho > 1.3
    assert e[inner].mean() < 0.9 * e[outer].mean()
    assert np.all(np.isfinite(np.asarray(out.irradiance)))


def test_renderer_reuses_bsv_of_rigid_occluders():
    occ = icosphere_occluder((0, 1.2, 0), 0.5, subdiv=1)
    scene = Scene(SMALL, plane(n=5), (occ,), (), Environment(f32(1, 1, 1)), n_frames=3)
    rend = Renderer(scene)
    outs = [rend.frame(f)[0] for f in range(3)]
    assert rend.bsv_computations == 1
    np.testing.assert_array_equal(outs[0].irradiance, outs[2].irradiance)
    np.testing.assert_allclose(outs[1].irradiance, render_at(scene, 0.5).irradiance, rtol=1e-5)


def test_renderer_bsv_of_a_deforming_mesh_is_one_call_equal_to_the_two_step_path():
    # the renderer's per-frame BSV of a deforming mesh computes the vertices and their edge-scan BSV
    # in one compiled call (bsv_mesh_edgescan_of); it must equal the vertices-then-bsv_mesh path bit
    # for bit with the same slots: measured on the first pose, grown after an overflow (and shared
    # with that path), without compiling the two-step path at all
    from jshadow.geometry import Twist
    from jshadow.scene import _vertices_at, bsv_input_vertices, mesh_bsv
    from jshadow.visibility import _edgescan as es
    from jshadow.visibility import bsv_mesh

    occ = icosphere_occluder((0, 1.2, 0), 0.5, Twist(0.0, 2.5), subdiv=2)
    m = Method(bsv_grid=(6, 10), directions=(16, 16))
    scene = Scene(m, plane(n=3), (occ,), (), Environment(f32(1, 1, 1)), n_frames=4)
    faces = np.asarray(occ.faces)
    kw = dict(n=m.field_bands, grid=m.bsv_grid, directions=m.directions, shell=m.shell)
    config = (m.bsv_grid, m.directions, m.shell)
    rows = occ.unit_vertices.shape[0] + 6  # the vertices and the placed centre's anchors
    key = es._rest_key(faces, rows, jnp.float32, *config)

    def two_step(t):
        v = bsv_input_vertices(occ, _vertices_at(occ, jnp.float32(t)), m)
        assert v.shape[0] == rows
        return bsv_mesh(v, faces, method=m.bsv_method, **kw).coeffs

    es._REST_SLOTS.pop(key, None)  # this topology unseen: the first call measures its slots
    compiles = es._run_jit._cache_size()
    got = {t: mesh_bsv(occ, t, scene, differentiable=False) for t in (0.0, 0.7)}
    assert es._run_jit._cache_size() == compiles  # the two-step path's edge-scan was never compiled
    measured = es._REST_SLOTS[key]
    for t, bsv in got.items():  # 0.7: twisted beyond the measured pose (grown slots if it overflows)
        np.testing.assert_array_equal(np.asarray(bsv.coeffs), np.asarray(two_step(t)))

    # slots far too small: the call overflows, grows them, reruns, and the two-step path starts from
    # the grown slots too
    es._REST_SLOTS[key] = (1, 1, 1, 1)
    repaired = mesh_bsv(occ, 1.0, scene, differentiable=False).coeffs
    np.testing.assert_array_equal(np.asarray(repaired), np.asarray(two_step(1.0)))
    es._REST_SLOTS[key] = measured
    table = es._cached_edge_table(faces, rows)
    tiny = es._check_slots((1, 1, 1, 1), *es._slot_bounds(table, m.bsv_grid, m.directions))
    grown = es._GROWN[es._grown_key(table, *config, tiny)]
    assert grown != tiny and grown[0] > tiny[0]


def test_outputs_finite_with_receivers_on_and_inside_occluders():
    occ = SphereOccluder(f32(0, 0.0, 0), jnp.float32(0.5))  # the plane cuts the sphere
    light = SphereLight(f32(0, 0.25, 0), jnp.float32(0.1), f32(1, 1, 1))  # light inside the occluder
    scene = Scene(
        SMALL,
        plane(n=9, size=2.0),
        (occ, icosphere_occluder((0.0, 0.0, 0.0), 0.7)),
        (light,),
        Environment(f32(1, 1, 1)),
    )
    out = render(scene)
    assert np.all(np.isfinite(np.asarray(out.irradiance)))
    g = jax.jit(
        jax.grad(
            lambda c: render(
                eqx_replace(scene, lights=(SphereLight(c, light.radius, light.radiance),))
            ).irradiance.sum()
        )
    )(light.center)
    assert np.all(np.isfinite(np.asarray(g)))
    assert math.isfinite(float(out.irradiance.sum()))


@pytest.mark.parametrize("unrolled", [16, 2])
def test_grouped_bsv_occluders_equal_one_by_one(unrolled, monkeypatch):
    # several BSV occluders of the same shape: traced one by one up to _UNROLLED_FIELDS, beyond it
    # under one lax.map (unrolled=2 sends these three there); both must equal the field one by one
    import jshadow.scene as sc
    from jshadow.scene import occluder_visibilities, scene_bsvs

    monkeypatch.setattr(sc, "_UNROLLED_FIELDS", unrolled)

    occ = tuple(
        SphereOccluder(f32(x, 1.0 + 0.2 * x, -x), jnp.float32(0.3 + 0.1 * x)) for x in (-1.0, 0.0, 1.0)
    )
    scene = Scene(SMALL, plane(n=6), occ, (), Environment(f32(1, 1, 1)))
    bsvs = scene_bsvs(scene, 0.0, sphere_path="bsv")
    pts = scene.receivers.points
    vis, dist = occluder_visibilities(scene, bsvs, pts)
    table = occlusion_table(scene)
    for v, d, b in zip(vis, dist, bsvs, strict=True):
        want = bsv_visibility_sh(b, table, pts, scene.method.sh_bands)
        np.testing.assert_allclose(v, want, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(
            d, np.linalg.norm(np.asarray(pts) - np.asarray(b.center), axis=-1), rtol=1e-6
        )
    # a lone BSV occluder; its distances come from the field too
    one = Scene(SMALL, plane(n=6), occ[:1], (), Environment(f32(1, 1, 1)))
    (v1,), (d1,) = occluder_visibilities(one, bsvs[:1], pts)
    np.testing.assert_allclose(v1, vis[0], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(d1, dist[0], rtol=1e-6)


@pytest.mark.parametrize("shape", [(), (1,), (3, 1, 2)])
def test_field_equals_interpolate_then_extrapolate_then_rotate(shape):
    # bsv_visibility_sh interpolates M_{k_t}·BSV trilinearly; the textbook order (interpolate the BSV,
    # interpolate and apply M_k, rotate) must give the same numbers — at the poles, the centre, on
    # the shell and beyond the table too
    from jshadow.field import frame_to_world, interpolate_bsv, unit_visibility
    from jshadow.scaling import mk_apply, mk_in_range, mk_table
    from jshadow.visibility import BSV

    with jax.enable_x64(True):
        rng = np.random.default_rng(4)
        table = mk_table(n=5, num=16, d_min=0.2, d_max=8.0, model="sphere", dtype=jnp.float64)
        coeffs, center = jnp.asarray(rng.normal(size=(12, 20, 25))), jnp.asarray([0.1, -0.2, 0.3])
        bsv = BSV(coeffs, center, jnp.asarray(0.8), jnp.asarray(1.2))
        special = np.array([[0, 0, 2.0], [0, 0, -2.0], [0, 0, 0], [1.2, 0, 0], [0, 30.0, 0], [0.01, 0, 0]])
        pts = np.concatenate([special, rng.normal(size=(200, 3)) * 3]) + np.asarray(bsv.center)
        got = bsv_visibility_sh(bsv, table, jnp.asarray(pts), bands=4)
        rel = pts - np.asarray(bsv.center)
        d = np.linalg.norm(rel, axis=-1)
        rho = np.hypot(rel[:, 0], rel[:, 1])
        th, ph = jnp.asarray(np.arctan2(rho, rel[:, 2])), jnp.asarray(np.arctan2(rel[:, 1], rel[:, 0]))
        k = jnp.asarray(1.2 / np.maximum(d, 1e-300))
        want = frame_to_world(mk_apply(table, k, interpolate_bsv(bsv.coeffs, th, ph))[:, :16], th, ph)
        want = jnp.where(mk_in_range(table, k)[:, None], want, unit_visibility((len(pts),), 4, want.dtype))
        np.testing.assert_allclose(got, want, atol=1e-12)
        # a single ring of samples (T = 1): the second θ row is the same ring, with weight 0
        thin = BSV(coeffs[:1, :5], center, jnp.asarray(0.8), jnp.asarray(1.2))
        want1 = frame_to_world(mk_apply(table, k, interpolate_bsv(thin.coeffs, th, ph))[:, :16], th, ph)
        want1 = jnp.where(mk_in_range(table, k)[:, None], want1, unit_visibility((len(pts),), 4, want1.dtype))
        got1 = bsv_visibility_sh(thin, table, jnp.asarray(pts), bands=4)
        np.testing.assert_allclose(got1, want1, atol=1e-12)
        one = jnp.asarray(pts[7 : 7 + max(1, math.prod(shape))]).reshape(*shape, 3)
        out = bsv_visibility_sh(bsv, table, one, bands=4)
        assert out.shape == (*shape, 16)
        np.testing.assert_allclose(out.reshape(-1, 16), got[7 : 7 + max(1, math.prod(shape))], atol=1e-12)


def _shared_normal_scene(shading):
    # a plane (one shared normal) then points with their own normals, an HDR-like environment, a
    # sphere light and two occluders: every term of combine that depends on the normal
    rng = np.random.default_rng(7)
    rec = plane(n=7)
    extra = rng.normal(size=(9, 3)).astype(np.float32) * 0.4 + np.float32([0.3, 0.6, 0.1])
    nrm = rng.normal(size=(9, 3)).astype(np.float32)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    pts = jnp.concatenate([rec.points, jnp.asarray(extra)])
    rec = Receivers(pts, jnp.concatenate([rec.normals, jnp.asarray(nrm)]), rec.albedo)
    img = jnp.asarray(rng.uniform(0.2, 3.0, size=(16, 32, 3)).astype(np.float32))
    env = Environment(f32(1.0, 0.8, 0.6), img, kind="hdr")
    occ = (
        SphereOccluder(f32(0.2, 1.0, 0.0), jnp.float32(0.4)),
        SphereOccluder(f32(-0.6, 1.4, 0.3), jnp.float32(0.3)),
    )
    light = SphereLight(f32(1.0, 3.0, 0.5), jnp.float32(0.5), f32(2.0, 2.0, 2.0))
    return Scene(Method(bsv_grid=(12, 20), directions=(16, 16), shading=shading), rec, occ, (light,), env)


@pytest.mark.parametrize(
    "shading, sphere_path, occluders", [("ratio", "bsv", 2), ("product", "analytic", 2), ("ratio", "bsv", 1)]
)
def test_combine_shared_normal_equals_per_receiver(shading, sphere_path, occluders):
    # the plane's receivers share one normal: computing their transfer, unoccluded irradiance,
    # environment shading vector and "multiply by T" matrix once must give what the per-receiver
    # path gives (every setting sends the sphere light through the SH product with the transfer;
    # one occluder takes the shared path's select after the GEMM, two their product)
    from functools import partial

    from jshadow.scene import combine, occluder_visibilities, scene_bsvs, scene_lighting, shared_normal_count

    scene = _shared_normal_scene(shading)
    scene = eqx_replace(scene, occluders=scene.occluders[:occluders])
    pts, nrm = scene.receivers.points, scene.receivers.normals
    assert shared_normal_count(nrm) == 49
    vis, dist = occluder_visibilities(scene, scene_bsvs(scene, 0.0, sphere_path), pts)
    lighting = scene_lighting(scene)
    run = jax.jit(
        partial(combine, scene, lighting=lighting, analytic_spheres=sphere_path == "analytic"),
        static_argnames="shared_normal",
    )
    general = np.asarray(run(pts, nrm, vis, dist))
    for shared in (20, 49):  # the plane split in two groups, and the whole plane
        got = run(pts, nrm, vis, dist, shared_normal=shared)
        np.testing.assert_allclose(got, general, rtol=2e-5, atol=2e-5)
    plane = general[:49].sum(-1)
    assert plane.min() < 0.9 * plane.max()  # the plane holds shadowed and lit receivers


def test_combine_shared_normal_gradient_equals_per_receiver():
    # the light-position gradient through the shared-normal terms (cap, "multiply by T₀", ratio) is
    # the per-receiver one (constant environment: cheap to compile)
    from jshadow.scene import combine, occluder_visibilities, scene_bsvs, scene_lighting

    base = _shared_normal_scene("ratio")  # 2 bands: the products compile quickly
    env = Environment(f32(0.5, 0.5, 0.5))
    scene = eqx_replace(base, method=Method(sh_bands=2, shading="ratio"), environment=env)
    pts, nrm = scene.receivers.points, scene.receivers.normals
    vis, dist = occluder_visibilities(scene, scene_bsvs(scene, 0.0), pts)  # analytic spheres, whose
    # light shadow goes through the SH products below (analytic_spheres=False)
    lighting = scene_lighting(scene)

    def loss(c, shared):
        lit = eqx_replace(scene, lights=(SphereLight(c, jnp.float32(0.5), f32(2.0, 2.0, 2.0)),))
        return combine(lit, pts, nrm, vis, dist, lighting, False, shared_normal=shared).sum()

    grad = jax.jit(jax.grad(loss), static_argnums=1)
    c0 = f32(1.0, 3.0, 0.5)
    g49 = grad(c0, 49)
    assert float(jnp.abs(g49).max()) > 0
    np.testing.assert_allclose(g49, grad(c0, 0), rtol=1e-4, atol=1e-4 * float(jnp.abs(g49).max()))


def test_environment_rows_equal_the_three_operand_einsum(x64, rng):
    from jshadow.scene import _env_rows

    for n2 in (4, 16):
        v, t = rng.normal(size=(37, n2)), rng.normal(size=(37, n2))
        m = rng.normal(size=(3, n2, n2))
        want = np.einsum("ni,cik,nk->nc", v, m, t)
        got = np.asarray(_env_rows(jnp.asarray(v), jnp.asarray(m), jnp.asarray(t)))
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_shared_normal_count():
    from jshadow.scene import shared_normal_count

    up, side = [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]
    assert shared_normal_count(np.asarray([up, up, side, up], np.float32)) == 2
    assert shared_normal_count(np.asarray([up] * 5, np.float32)) == 5
    assert shared_normal_count(np.zeros((0, 3), np.float32)) == 0
    assert jax.jit(lambda x: jnp.float32(shared_normal_count(x)))(jnp.ones((4, 3))) == 0  # traced: none
