"""Several occluders: the product of their visibilities, the environment's split last product
(``combine``) and the renderer's fused visibility chain (``visibility_chain``)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

import jshadow.scene as sc
from jshadow import sh
from jshadow.entities import Environment, MeshOccluder, Method, Receivers, Scene, SphereLight, SphereOccluder
from jshadow.field import unit_visibility
from jshadow.geometry import normalize_to_unit_sphere
from jshadow.runner import Renderer


def _f(*v, dtype=jnp.float32):
    return jnp.asarray(v, dtype)


def _receivers(dtype=jnp.float32):
    # a plane (one shared normal) and a few points with normals of their own: both groups of combine
    rng = np.random.default_rng(3)
    xs = np.linspace(-2.0, 2.0, 8)
    x, z = np.meshgrid(xs, xs)
    plane = np.stack([x.ravel(), np.zeros(x.size), z.ravel()], -1)
    extra = rng.normal(size=(7, 3)) * 0.3 + np.array([0.2, 0.4, -0.1])
    nrm = rng.normal(size=(7, 3))
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    pts = np.concatenate([plane, extra])
    normals = np.concatenate([np.tile([0.0, 1.0, 0.0], (plane.shape[0], 1)), nrm])
    return Receivers(jnp.asarray(pts, dtype), jnp.asarray(normals, dtype), jnp.full(3, 0.8, dtype))


def _scene(shading="ratio", lights=(), n=4, dtype=jnp.float32):
    """A mesh, a sphere through the BSV path or analytic, and a second sphere, over the receivers
    above, under a non-constant environment."""
    m = trimesh.creation.icosphere(subdivisions=1)
    unit = normalize_to_unit_sphere(jnp.asarray(m.vertices, dtype))
    mesh = MeshOccluder(
        unit, jnp.asarray(m.faces, jnp.int32), _f(0.6, 0.8, 0.3, dtype=dtype), jnp.asarray(0.45, dtype)
    )
    occ = (
        mesh,
        SphereOccluder(_f(-0.7, 0.7, 0.1, dtype=dtype), jnp.asarray(0.4, dtype)),
        SphereOccluder(_f(0.1, 0.9, -0.9, dtype=dtype), jnp.asarray(0.3, dtype)),
    )
    img = jnp.asarray(np.random.default_rng(5).uniform(0.2, 3.0, size=(16, 32, 3)), dtype)
    env = Environment(_f(1.0, 0.8, 0.6, dtype=dtype), img, kind="hdr")
    method = Method(
        sh_bands=n, bsv_grid=(12, 20), directions=(16, 16), shading=shading, dtype=jnp.dtype(dtype).name
    )
    return Scene(method, _receivers(dtype), occ, tuple(lights), env)


@pytest.mark.parametrize("sphere_path", ["analytic", "bsv"])
def test_environment_term_equals_the_full_product(sphere_path):
    # product shading: E_c = ⟨(V₁ ⊛ V₂ ⊛ V₃) ⊛ L_c, T⟩ with the products formed one by one in the
    # row layout (sh.sh_product), against combine's split last product (a bilinear form)
    scene = _scene("product")
    pts, nrm = scene.receivers.points, scene.receivers.normals
    vis, dist = sc.occluder_visibilities(scene, sc.scene_bsvs(scene, 0.0, sphere_path), pts)
    lighting = sc.scene_lighting(scene)
    v_all = sh.sh_product(sh.sh_product(vis[0], vis[1]), vis[2])
    t = sh.clamped_cosine(nrm, 4)
    env = lighting.env_sh.astype(jnp.float32)  # (n², 3)
    want = np.stack(
        [np.sum(np.asarray(sh.sh_product(v_all, env[:, c])) * np.asarray(t), -1) for c in range(3)], -1
    )
    for shared in (0, 64):
        got = sc.combine(
            scene, pts, nrm, vis, dist, lighting, sphere_path == "analytic", shared_normal=shared
        )
        np.testing.assert_allclose(got, want, rtol=2e-5, atol=2e-5 * np.abs(want).max())
    assert want[:64, 0].min() < 0.8 * want[:64, 0].max()  # shadowed and lit plane receivers


@pytest.mark.parametrize("shading", ["ratio", "product"])
def test_renderer_chain_equals_the_separate_fields(shading):
    # the one-call shading multiplies each visibility in as it is made (visibility_chain); the split
    # stages make them all, then combine them: the same numbers
    scene = _scene(shading)
    assert sc.uses_visibility_chain(scene)
    for path in ("analytic", "bsv"):
        one = Renderer(scene, sphere_path=path, static_readout=False).frame(0)[0].irradiance
        split = Renderer(scene, sphere_path=path, split_stages=True).frame(0)[0].irradiance
        np.testing.assert_allclose(one, split, rtol=1e-5, atol=1e-6 * float(np.abs(split).max()))


def test_chain_is_used_only_where_the_product_alone_is_needed():
    scene = _scene()
    assert sc.uses_visibility_chain(scene)
    light = SphereLight(_f(1.0, 3.0, 0.5), jnp.float32(0.5), _f(2.0, 2.0, 2.0))
    assert not sc.uses_visibility_chain(
        Scene(scene.method, scene.receivers, scene.occluders, (light,), scene.environment)
    )
    assert not sc.uses_visibility_chain(
        Scene(scene.method, scene.receivers, scene.occluders[:1], (), scene.environment)
    )
    assert not sc.uses_visibility_chain(scene, own=(jnp.zeros((1, 16)), jnp.zeros(1, jnp.int32)))
    # a sphere light's shadow needs each visibility: the renderer takes the separate fields and agrees
    lit = Scene(scene.method, scene.receivers, scene.occluders, (light,), scene.environment)
    one = Renderer(lit, static_readout=False).frame(0)[0].irradiance
    split = Renderer(lit, split_stages=True).frame(0)[0].irradiance
    np.testing.assert_allclose(one, split, rtol=1e-5, atol=1e-6 * float(np.abs(split).max()))
    with pytest.raises(ValueError, match="env_visibility"):
        pts, nrm = scene.receivers.points, scene.receivers.normals
        vis, dist = sc.occluder_visibilities(scene, sc.scene_bsvs(scene, 0.0), pts)
        sc.combine(scene, pts, nrm, vis, dist, env_visibility=(vis[0], vis[1]))


@pytest.mark.parametrize("unrolled", [16, 2])
def test_product_chain_both_branches_equal_the_row_products(unrolled, monkeypatch):
    # up to _UNROLLED_FIELDS factors one staged product after another, beyond one lax.scan
    monkeypatch.setattr(sc, "_UNROLLED_FIELDS", unrolled)
    rng = np.random.default_rng(11)
    vs = [jnp.asarray(rng.normal(size=(37, 16)), jnp.float32) for _ in range(4)]
    want = vs[0]
    for v in vs[1:]:
        want = sh.sh_product(want, v)
    for f in (sc._product, jax.jit(sc._product)):
        np.testing.assert_allclose(f(vs), want, rtol=1e-5, atol=1e-5 * float(np.abs(want).max()))
    assert sc._product(vs[:1]) is vs[0] and sc._product([]) is None


def test_split_last_product_gradient_matches_finite_differences():
    # d E / d (a sphere occluder's centre) through the split last product, float64, against central
    # differences (analytic spheres: smooth visibilities)
    with jax.enable_x64(True):
        scene = _scene("product", n=3, dtype=jnp.float64)
        scene = Scene(scene.method, scene.receivers, scene.occluders[1:], (), scene.environment)
        pts, nrm = scene.receivers.points, scene.receivers.normals
        lighting = sc.scene_lighting(scene)
        w = jnp.asarray(np.random.default_rng(2).uniform(size=(pts.shape[0], 3)))

        def loss(c):
            occ = (SphereOccluder(c, scene.occluders[0].radius), scene.occluders[1])
            s = Scene(scene.method, scene.receivers, occ, (), scene.environment)
            vis, dist = sc.occluder_visibilities(s, (None, None), pts)
            return jnp.sum(w * sc.combine(s, pts, nrm, vis, dist, lighting, shared_normal=64))

        c0 = scene.occluders[0].center
        g = np.asarray(jax.jit(jax.grad(loss))(c0))
        h = 1e-5
        fd = np.array([(loss(c0.at[i].add(h)) - loss(c0.at[i].add(-h))) / (2 * h) for i in range(3)])
        np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-8 * np.abs(fd).max())
        assert np.abs(g).max() > 0


@pytest.mark.parametrize("lit", [False, True])
def test_a_far_bsv_occluder_is_skipped_and_changes_nothing(lit):
    # a BSV occluder beyond the field's range of every receiver (8 shell radii): its visibility is
    # 1 and its field is not evaluated (a lax.cond on _reaches); the frame equals the frame without
    # it, through the fused chain (no light) and through the separate fields (a sphere light)
    light = (SphereLight(_f(1.0, 3.0, 0.5), jnp.float32(0.5), _f(2.0, 2.0, 2.0)),) if lit else ()
    base = _scene("ratio", lights=light)
    far = SphereOccluder(_f(0.0, 40.0, 0.0), jnp.float32(0.3))
    occ = base.occluders
    with_far = Scene(base.method, base.receivers, (occ[0], far, occ[1], occ[2]), light, base.environment)
    assert sc.uses_visibility_chain(with_far) == (not lit)
    bsvs = sc.scene_bsvs(with_far, 0.0, "bsv")
    table = sc.occlusion_table(with_far)
    pts = with_far.receivers.points
    assert not bool(sc._reaches(bsvs[1], table, pts))
    assert all(bool(sc._reaches(b, table, pts)) for b in bsvs[::2])
    got = Renderer(with_far, sphere_path="bsv", static_readout=False).frame(0)[0].irradiance
    want = Renderer(base, sphere_path="bsv", static_readout=False).frame(0)[0].irradiance
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7 * float(np.abs(want).max()))
    # the far occluder's visibility and distance from the general path: 1 and its true distance
    vis, dist = sc.occluder_visibilities(with_far, bsvs, pts)
    np.testing.assert_allclose(vis[1], unit_visibility((pts.shape[0],), 4, jnp.float32), atol=0)
    np.testing.assert_allclose(
        dist[1], np.linalg.norm(np.asarray(pts) - np.asarray(far.center), axis=-1), rtol=1e-6
    )
