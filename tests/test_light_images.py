"""Sphere lights shadowed through the BSV's occlusion images (``[method] light_visibility = "images"``).

Claims tested: the stratified cap nodes lie in the cap, batch, and integrate the cap's mean cosine
(closed form); a ray looked up in the images of a convex mesh agrees with an exact ray cast for all
but a few rays near the silhouette, and rays that miss the bounding sphere are free; a mesh sphere
and a sphere light through the images match the closed-form lens of the analytic sphere path within
1.5 % relative RMSE, where the n-band path is off by more than 3 %; ``render`` and the Renderer's
one-call, split and chunked paths agree, images (and the visible fractions made from them) are
made once for a rigid shape and every frame for a deforming one; derivatives with respect to
radiance, lights and meshes work and a sphere occluder's refuses, and the lookup's own gradient is
finite at its singular points; jit with a traced time equals eager; config keys are read and
checked, and ``light_visibility = "auto"`` (the config default) takes the images exactly where they
apply; ``jshadow render`` reports the images' time and count, ``jshadow fit`` of a light position
runs and of a sphere occluder's centre says in one line that its ray test has no derivative;
sphere occluders alone keep the exact lens.
"""

import dataclasses
import json
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import BATCH_SHAPES
from test_scene import SMALL, f32, icosphere_occluder, plane

from jshadow.config import ConfigError, config_from_dict
from jshadow.entities import Environment, Method, Scene, SphereLight, SphereOccluder
from jshadow.geometry import MeshWarning, Twist
from jshadow.runner import Renderer
from jshadow.sampling import stratified_sphere_cone
from jshadow.scene import render, render_at
from jshadow.visibility import image_fan_visibility, image_ray_visibility, occlusion_images, ray_fan_any_hit

IMAGES = dataclasses.replace(SMALL, light_visibility="images")
LIGHT = SphereLight(f32(1.2, 3.2, 0.6), jnp.float32(0.45), f32(30.0, 30.0, 30.0))


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_stratified_cone_nodes_lie_in_the_cap_and_integrate_its_mean_cosine(shape, rng):
    to_c = rng.normal(size=(*shape, 3)) * 3.0
    radius = np.abs(rng.normal(size=shape)) + 0.2
    d = np.asarray(stratified_sphere_cone(jnp.asarray(to_c), jnp.asarray(radius), (6, 10)))
    assert d.shape == (*shape, 60, 3)
    axis = to_c / np.linalg.norm(to_c, axis=-1, keepdims=True)
    cos = np.einsum("...kc,...c->...k", d, axis)
    dist = np.linalg.norm(to_c, axis=-1)
    cos_a = np.sqrt(np.clip(1.0 - (radius / dist) ** 2, 0.0, 1.0))
    cos_a = np.where(radius >= dist, -1.0, cos_a)  # inside: the whole sphere
    assert np.all(cos >= cos_a[..., None] - 1e-5)
    # the mean of cos over a cap uniform in solid angle is (1 + cos α)/2, the midpoint rule is exact
    np.testing.assert_allclose(cos.mean(-1), (1.0 + cos_a) / 2.0, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-5)


def test_stratified_cone_inside_and_degenerate():
    d = np.asarray(stratified_sphere_cone(jnp.zeros(3), 1.0, (4, 8)))  # a zero axis: any axis, no NaN
    assert np.all(np.isfinite(d)) and d.shape == (32, 3)
    with pytest.raises(ValueError, match="strata"):
        stratified_sphere_cone(jnp.ones(3), 1.0, (0, 8))


def _icosphere_world(center=(0.0, 1.1, 0.0), radius=0.6, subdiv=3):
    occ = icosphere_occluder(center, radius, subdiv=subdiv)
    return occ, occ.vertices(0.0)


def test_lookup_agrees_with_exact_rays_on_a_convex_mesh(rng):
    occ, v = _icosphere_world(subdiv=2)
    img = occlusion_images(v, occ.faces, (12, 20), (32, 32), 1.5)
    pts = jnp.asarray(np.c_[rng.uniform(-2, 2, 200), np.zeros(200), rng.uniform(-2, 2, 200)], jnp.float32)
    target = jnp.asarray(
        np.c_[rng.uniform(-1, 1, (200, 16, 1)), np.full((200, 16, 1), 1.1), rng.uniform(-1, 1, (200, 16, 1))]
    )
    dirs = target - pts[:, None, :]
    dirs = (dirs / jnp.linalg.norm(dirs, axis=-1, keepdims=True)).astype(jnp.float32)
    exact = 1.0 - np.asarray(ray_fan_any_hit(pts, dirs, v, occ.faces), np.float64)
    looked = np.asarray(image_ray_visibility(img, pts[:, None, :], dirs), np.float64)
    assert 0.2 < exact.mean() < 0.8  # both outcomes are well represented
    wrong = np.abs(looked - exact) > 0.5
    assert wrong.mean() < 0.03, wrong.mean()  # only rays within a pixel of the silhouette
    # fans sharing their grid points (chosen around an axis ray) agree with the per-ray lookup
    axis = jnp.asarray([0.0, 1.1, 0.0]) - pts
    axis = axis / jnp.linalg.norm(axis, axis=-1, keepdims=True)
    fan = np.asarray(image_fan_visibility(img, pts, dirs, axis), np.float64)
    assert np.mean(np.abs(fan - looked)) < 0.03
    assert np.mean(np.abs(fan - exact) > 0.5) < 0.04
    # a ray whose line misses the bounding sphere, or that points away from it, is free
    away = image_ray_visibility(img, pts[:, None, :], -dirs)
    np.testing.assert_array_equal(np.asarray(away), 1.0)


def _light_scene(occluder, method, n=12, n_frames=1):
    return Scene(
        method, plane(n=n), (occluder,), (LIGHT,), Environment(f32(0.3, 0.3, 0.3)), n_frames=n_frames
    )


def test_mesh_sphere_matches_the_closed_form_lens():
    """The analytic path's blocked part of a sphere light by a sphere occluder is exact (the lens
    of two caps); a finely tessellated mesh sphere through the images must match it."""
    occ, _ = _icosphere_world(subdiv=4)
    exact = render(
        _light_scene(SphereOccluder(f32(0.0, 1.1, 0.0), jnp.float32(0.6)), IMAGES, n=16)
    ).irradiance
    ours = render(_light_scene(occ, IMAGES, n=16)).irradiance
    sh_path = render(_light_scene(occ, SMALL, n=16)).irradiance
    mean = float(jnp.mean(exact))

    def rel(x):
        return float(jnp.sqrt(jnp.mean((x - exact) ** 2))) / mean

    print(f"mesh sphere against the closed-form lens: images {rel(ours):.2%}, n-band {rel(sh_path):.2%}")
    assert rel(ours) < 0.015
    assert rel(sh_path) > 0.03
    # the lit/unlit contrast is there: the darkest receiver is well below the brightest
    assert float(jnp.min(ours)) < 0.5 * float(jnp.max(ours))


def test_paths_agree_and_images_are_reused():
    occ, _ = _icosphere_world(subdiv=2)
    scene = _light_scene(occ, IMAGES, n=9, n_frames=3)
    ref = np.asarray(render(scene, 1).irradiance)
    one = Renderer(scene)
    a, times = one.frame(1)
    c, _ = one.frame(2)
    # a rigid shape: its images, and the receivers' visible fractions made from them, once; the
    # frames read out of the field's table, the lights' image terms added as a constant offset
    assert one.image_computations == 1 and "light_images_ms" in times
    assert one.fraction_computations == 1
    assert one.readout_frames == 2 and one.readout_reason is None
    b, _ = Renderer(scene, split_stages=True, chunk=20).frame(1)
    scale = float(np.abs(ref).max())
    for x in (a, b, c):
        np.testing.assert_allclose(np.asarray(x.irradiance), ref, atol=1e-5 * scale)
    twist = _light_scene(
        icosphere_occluder((0, 1.1, 0), 0.6, Twist(jnp.float32(0.0), jnp.float32(1.0), 1)),
        IMAGES,
        n=5,
        n_frames=3,
    )
    r = Renderer(twist)
    for f in range(3):
        got, times = r.frame(f)
    assert r.image_computations == 3 and r.bsv_computations == 3
    assert r.fraction_computations == 0  # made with each frame's shading
    assert r.readout_frames == 0 and "occlusion images" in r.readout_reason
    # a deforming mesh's images come from its BSV's edge-scan pass (bsv_with_occlusion_images):
    # the same numbers as computing them apart, as render() does
    want = np.asarray(render(twist, 2).irradiance)
    np.testing.assert_allclose(np.asarray(got.irradiance), want, atol=1e-5 * float(np.abs(want).max()))


def test_derivatives_work_and_a_sphere_occluder_refuses():
    """Radiance, light and mesh derivatives go through the images (their accuracy:
    tests/test_image_lookup_grad.py); a sphere occluder's binary ray test refuses."""
    occ, _ = _icosphere_world(subdiv=2)
    scene = _light_scene(occ, IMAGES, n=5)

    def with_light(c, radiance):
        light = SphereLight(c, LIGHT.radius, radiance)
        return jnp.sum(render(dataclasses.replace(scene, lights=(light,))).irradiance)

    g = jax.grad(with_light, argnums=(0, 1))(LIGHT.center, LIGHT.radiance)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in g) and float(jnp.sum(g[1])) > 0
    assert float(g[0][1]) < 0  # raising the light above the plane darkens it (1/d²)

    def moved(dy, sphere):
        s = SphereOccluder(f32(1.5, 0.8, 1.5), jnp.float32(0.3))
        s = dataclasses.replace(s, center=s.center + jnp.asarray([0.0, 1.0, 0.0]) * sphere)
        o = dataclasses.replace(occ, center=occ.center + jnp.asarray([0.0, 1.0, 0.0]) * dy)
        return jnp.sum(render(dataclasses.replace(scene, occluders=(o, s))).irradiance)

    assert np.isfinite(float(jax.grad(moved)(jnp.float32(0.0), jnp.float32(0.0))))
    with pytest.raises(ValueError, match="light_visibility"):
        jax.grad(moved, argnums=1)(jnp.float32(0.0), jnp.float32(0.0))


def test_lookup_gradient_is_finite_at_singular_points():
    occ, v = _icosphere_world(subdiv=1)
    img = occlusion_images(v, occ.faces, (6, 8), (8, 8), 1.5)
    c = np.asarray(img.center)
    cases = [  # origin, direction
        (c + [0.0, 0.0, -3.0], [0.0, 0.0, 1.0]),  # through the centre, entering at a pole
        (c + [0.0, -3.0, 0.0], [0.0, 1.0, 0.0]),  # through the centre at the equator
        (c + [0.0, -3.0, 0.0], [1.0, 0.0, 0.0]),  # perpendicular: b = 0
        (c + [0.0, -0.9, 0.0], [0.0, 1.0, 0.0]),  # on the shell itself
    ]
    for o, d in cases:
        g = jax.grad(lambda o_, d_: image_ray_visibility(img, o_, d_), argnums=(0, 1))(
            jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32)
        )
        assert all(np.all(np.isfinite(np.asarray(x))) for x in g)


def test_config_keys_are_read_and_checked():
    base = {
        "occluder": [{"type": "mesh", "shape": "egg", "subdivisions": 1, "center": [0, 1, 0], "radius": 0.5}],
        "light": [{"type": "sphere", "center": [1, 3, 0], "radius": 0.3, "radiance": [5, 5, 5]}],
        "receiver": {"type": "plane", "center": [0, 0, 0], "size": [2, 2], "resolution": [2, 2]},
    }
    cfg = config_from_dict({**base, "method": {"light_visibility": "images", "light_cap": [2, 6]}})
    m = cfg.method.to_method()
    assert m.light_visibility == "images" and m.light_cap == (2, 6)
    with pytest.raises(ConfigError, match="light_visibility"):
        config_from_dict({**base, "method": {"light_visibility": "rays"}})
    with pytest.raises(ConfigError, match="light_cap"):
        config_from_dict({**base, "method": {"light_cap": [0, 4]}})
    with pytest.raises(ValueError, match="shell > 1"):
        Method(light_visibility="images", shell=1.0)
    assert math.isclose(Method().light_cap[0] * Method().light_cap[1], 32)


def test_light_visibility_auto_takes_the_images_where_they_apply(tmp_path, monkeypatch):
    """``light_visibility = "auto"`` and ``environment_lights = "auto"`` (the config defaults):
    the images for a sphere light, or a lat-long map over closed meshes (256 distant lights for the
    map over meshes that keep their shape, 64 over the small egg bent); the n-band path with a fit,
    the paper's preset or shell, the brute-force BSV, an open mesh, sphere occluders only, or
    nothing sharp to shadow; explicit choices are kept. ``self_visibility = "auto"``: "rays" for the
    own vertices of meshes that keep their shape, and of closed deforming meshes within
    ``AUTO_SELF_RAYS_PAIRS`` where no lamps are split off, "maps" for other closed deforming
    meshes, else "field"."""
    from pathlib import Path

    from jshadow.config import (
        AUTO_ENVIRONMENT_LIGHTS,
        AUTO_ENVIRONMENT_LIGHTS_DEFORMING,
        AUTO_ENVIRONMENT_LIGHTS_STATIC,
        AUTO_MAPS_GRID,
        AUTO_PENUMBRA_PAIRS,
        AUTO_SELF_RAYS_PAIRS,
        build_scene,
        own_ray_pairs,
    )
    from jshadow.config import _build as config_build

    hdr = str(Path(__file__).resolve().parents[1] / "assets" / "envmaps" / "studio_small_03_512x256.hdr")
    (tmp_path / "open.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 2\nf 1 3 2\nf 1 2 4\nf 1 4 3\n")
    egg = {"type": "mesh", "shape": "egg", "subdivisions": 1, "center": [0, 1, 0], "radius": 0.5}
    light = [{"type": "sphere", "center": [0.5, 3, 0.3], "radius": 0.3, "radiance": [9, 9, 9]}]
    base = {
        "occluder": [egg],
        "light": light,
        "environment": {"type": "constant", "radiance": [0.2, 0.2, 0.2]},
        "receiver": {"type": "plane", "center": [0, 0, 0], "size": [2, 2], "resolution": [2, 2]},
    }
    studio = {"type": "hdr", "file": hdr, "radiance": [1, 1, 1]}

    K = AUTO_ENVIRONMENT_LIGHTS_STATIC  # noqa: N806
    assert K == 256
    KM = AUTO_ENVIRONMENT_LIGHTS  # noqa: N806  (a deforming mesh whose images are cheap enough)
    KD = AUTO_ENVIRONMENT_LIGHTS_DEFORMING  # noqa: N806

    def chosen(d, own="field"):
        m = build_scene(config_from_dict(d, root=tmp_path)).method
        assert m.self_visibility == own
        return m.light_visibility, m.environment_lights

    assert chosen(base) == ("images", 0)
    assert chosen({**base, "environment": studio}) == ("images", K)
    # the own vertices among the receivers of meshes that keep their shape: their transfer (and
    # their view of the lamps) by rays, cast once, with or without anything sharp to shadow
    own = {**base["receiver"], "self_shadow": True}
    assert chosen({**base, "environment": studio, "receiver": own}, "rays") == ("images", K)
    assert chosen({**base, "receiver": own}, "rays") == ("images", 0)
    assert chosen({**base, "light": [], "receiver": own}, "rays") == ("sh", 0)  # a constant sky
    keep = {"self_visibility": "field"}
    assert chosen({**base, "environment": studio, "receiver": own, "method": keep}) == ("images", K)
    keep = {"self_visibility": "light_rays"}
    assert chosen({**base, "environment": studio, "receiver": own, "method": keep}, "light_rays") == (
        "images",
        K,
    )
    # a closed mesh that deforms: both from depth images and local rays, made every frame, unless
    # the environment reaches its vertices through their transfer alone (no lamps) and the mesh is
    # small enough to cast by rays every frame (this egg: 42 vertices x 80 faces)
    bent = [{**egg, "deform": {"type": "bend", "amount": [0.0, 0.5]}}]
    big = [{**bent[0], "subdivisions": 5}]  # 10242 x 20480 pairs: over the bound
    assert (
        own_ray_pairs(build_scene(config_from_dict({**base, "occluder": bent}, root=tmp_path)).occluders)
        == 42 * 80
    )
    assert own_ray_pairs(
        build_scene(config_from_dict({**base, "occluder": big}, root=tmp_path)).occluders
    ) > (AUTO_SELF_RAYS_PAIRS)
    assert chosen({**base, "occluder": bent, "receiver": own}, "rays") == ("images", 0)
    assert chosen({**base, "occluder": big, "receiver": own}, "maps") == ("images", 0)
    assert chosen({**base, "occluder": bent, "receiver": own, "environment": studio}, "maps") == (
        "images",
        KD,
    )
    assert chosen({**base, "occluder": bent, "receiver": own, "light": []}, "rays") == ("sh", 0)
    assert chosen({**base, "occluder": big, "receiver": own, "light": []}, "maps") == ("sh", 0)
    no_env = {k: v for k, v in base.items() if k != "environment"}
    assert chosen({**no_env, "occluder": bent, "receiver": own}, "maps") == ("images", 0)
    with monkeypatch.context() as mp:  # the bound decides
        mp.setattr(config_build, "AUTO_SELF_RAYS_PAIRS", 42 * 80 - 1)
        assert chosen({**base, "occluder": bent, "receiver": own}, "maps") == ("images", 0)

    def maps(d):
        m = build_scene(config_from_dict(d, root=tmp_path)).method
        return m.self_maps_grid, m.self_maps_resolution

    # "maps" with the environment through the transfer alone: the finer grid, at the pixels of the
    # mesh's edges (this coarse egg: the floor); lamps carry a map's bright part, or there is no
    # environment: the coarse grid; explicit keys kept, and checked
    fine, coarse = (AUTO_MAPS_GRID, 160), ((8, 16), 64)  # the finely tessellated egg: the ceiling
    assert maps({**base, "occluder": big, "receiver": own, "light": []}) == fine
    assert maps({**base, "occluder": big, "receiver": own}) == fine
    assert maps({**base, "occluder": bent, "receiver": own, "environment": studio}) == coarse
    assert maps({**no_env, "occluder": bent, "receiver": own}) == coarse
    assert maps({**base, "receiver": own}) == coarse  # "rays": the keys do not apply
    assert maps({**base, "occluder": bent, "receiver": own}) == coarse
    given = {"self_maps_grid": [6, 10], "self_maps_resolution": 48}
    assert maps({**base, "occluder": bent, "receiver": own, "method": given}) == ((6, 10), 48)
    with pytest.raises(ConfigError, match="self_maps_resolution"):
        config_from_dict({**base, "method": {"self_maps_resolution": 4}})
    with pytest.raises(ConfigError, match="self_maps_grid"):
        config_from_dict({**base, "method": {"self_maps_grid": [1, 8]}})
    # the n-band path asked for by name keeps the field (what it meant before "auto")
    assert chosen({**base, "receiver": own, "method": {"light_visibility": "sh"}}) == ("sh", 0)
    assert chosen({**base, "receiver": own, "method": {"preset": "paper"}}) == ("sh", 0)
    assert chosen({**base, "light": [], "environment": studio}) == ("images", K)
    assert chosen({**base, "light": []}) == ("sh", 0)  # a constant sky: nothing sharp
    # a deforming mesh: fewer lamps, their images made every frame, unless 128 lamps' images cost
    # few enough pixel tests per face (a finely tessellated mesh: small windows)
    bend = [{**egg, "deform": {"type": "bend", "amount": [0.0, 0.5]}}]
    assert chosen({**base, "occluder": bend, "light": [], "environment": studio}) == ("images", KD)
    fine = [{**bend[0], "subdivisions": 5}]
    assert chosen({**base, "occluder": fine, "light": [], "environment": studio}) == ("images", KM)
    assert chosen({**base, "occluder": bend, "environment": studio}) == ("images", KD)
    steady = [{**egg, "deform": {"type": "bend", "amount": [0.5, 0.5]}}]  # the same shape every frame
    assert chosen({**base, "occluder": steady, "light": [], "environment": studio}) == ("images", K)
    # under jit the amounts are traced: they may differ, so the shape counts as deforming
    traced = config_from_dict({**base, "occluder": steady, "light": [], "environment": studio}, root=tmp_path)
    method = eqx.filter_jit(lambda c: build_scene(c).method)(traced)
    assert (method.light_visibility, method.environment_lights) == ("images", KD)
    fit = {"params": ["light.0.center"], "target_values": [[0.0, 3.0, 0.0]]}
    assert chosen({**base, "environment": studio, "fit": fit}) == ("sh", 0)
    assert chosen({**base, "method": {"preset": "paper"}}) == ("sh", 0)
    assert chosen({**base, "method": {"shell": 1.0}}) == ("sh", 0)
    assert chosen({**base, "method": {"bsv_method": "brute"}}) == ("sh", 0)
    assert chosen({**base, "occluder": [{"type": "sphere", "center": [0, 1, 0], "radius": 0.4}]}) == ("sh", 0)
    opened = {"type": "mesh", "file": "open.obj", "center": [2, 1, 0], "radius": 0.3}
    with pytest.warns(MeshWarning, match="open"):
        assert chosen({**base, "occluder": [egg, opened]}) == ("sh", 0)
    assert chosen({**base, "environment": studio, "method": {"light_visibility": "sh"}}) == ("sh", 0)
    assert chosen({**base, "environment": studio, "method": {"environment_lights": 8}}) == ("images", 8)
    assert chosen({**base, "environment": studio, "method": {"environment_lights": 0}}) == ("images", 0)
    # an explicit "images" keeps what it meant before "auto": no environment lights unless given
    assert chosen({**base, "environment": studio, "method": {"light_visibility": "images"}}) == ("images", 0)
    with pytest.raises(ConfigError, match="environment_lights"):
        config_from_dict({**base, "method": {"environment_lights": "many"}})

    # directions and light_cap "auto": sharper images and more cap directions with the images
    def sizes(d):
        m = build_scene(config_from_dict(d, root=tmp_path)).method
        return m.directions, m.light_cap

    def lamps(d):
        return build_scene(config_from_dict(d, root=tmp_path)).method.lamp_images

    # lamp_images "auto": the map's lights in orthographic images where they are split off
    assert lamps({**base, "environment": studio}) == 128 and lamps(base) == 0
    assert lamps({**base, "environment": studio, "method": {"lamp_images": 0}}) == 0
    assert lamps({**base, "environment": studio, "method": {"light_visibility": "sh"}}) == 0
    with pytest.raises(ConfigError, match="lamp_images"):
        config_from_dict({**base, "method": {"lamp_images": 4}})

    def penumbrae(d):
        return build_scene(config_from_dict(d, root=tmp_path)).method.lamp_penumbrae

    # lamp_penumbrae "auto": widened lookups where the fixed receivers times the lamps are few
    # enough (this 2 × 2 plane and 256 lamps: 1024 pairs), else the plain one
    many = (AUTO_PENUMBRA_PAIRS // K) + 1  # receivers: one plane row too many
    wide = {**base["receiver"], "resolution": [many, 1]}
    assert penumbrae({**base, "environment": studio}) == "region"
    assert penumbrae({**base, "environment": studio, "receiver": wide}) == "none"
    assert penumbrae(base) == "none"  # no lamps
    assert penumbrae({**base, "environment": studio, "method": {"lamp_penumbrae": "none"}}) == "none"
    assert penumbrae(
        {**base, "environment": studio, "receiver": wide, "method": {"lamp_penumbrae": "region"}}
    ) == ("region")
    with pytest.raises(ConfigError, match="lamp_penumbrae"):
        config_from_dict({**base, "method": {"lamp_penumbrae": "soft"}})

    assert sizes(base) == ((64, 64), (8, 16))
    assert sizes({**base, "light": []}) == ((32, 32), (4, 8))  # the n-band path
    # a map's lamps have their own images: the shell's stay as the n-band path's
    assert sizes({**base, "light": [], "environment": studio}) == ((32, 32), (4, 8))
    assert sizes({**base, "method": {"preset": "paper"}}) == ((32, 32), (4, 8))
    assert sizes({**base, "method": {"light_visibility": "images"}}) == ((32, 32), (4, 8))
    assert sizes({**base, "method": {"directions": [16, 16], "light_cap": "auto"}}) == ((16, 16), (8, 16))
    assert sizes({**base, "method": {"light_cap": [2, 4]}}) == ((64, 64), (2, 4))
    with pytest.raises(ConfigError, match="directions"):
        config_from_dict({**base, "method": {"directions": "many"}})


def test_maps_resolution_follows_the_median_edge():
    """The own vertices' depth images are sized so the finest mesh's median edge spans about 3
    pixels of its bounding diameter, in steps of 32 within [64, 160]: the spot cow 160, the bunny
    96, a coarse or small mesh the floor, a finer one than the cow the ceiling."""
    from pathlib import Path
    from types import SimpleNamespace

    from jshadow.config import maps_resolution
    from jshadow.geometry import icosphere, load_mesh

    assets = Path(__file__).resolve().parents[1] / "assets"

    def mesh(m):
        return SimpleNamespace(unit_vertices=np.asarray(m.vertices), faces=np.asarray(m.faces))

    spot, bunny = (mesh(load_mesh(assets / f, dtype=jnp.float32)) for f in ("spot.obj", "bunny.obj"))
    small = mesh(load_mesh(assets / "bunny_small.obj", dtype=jnp.float32))
    assert maps_resolution([spot]) == 160 and maps_resolution([bunny]) == 96
    assert maps_resolution([small]) == 64 and maps_resolution([]) == 64
    assert maps_resolution([small, bunny]) == 96  # the finest mesh decides
    assert maps_resolution([mesh(icosphere(5))]) == 160  # capped


def test_lamp_tests_per_face_bound_the_deforming_lamps():
    """The lamp images' pixel tests per face (half the faces entering, each a stamp² window per
    direction): proportional to the lamps; the animated bunny's 64 lamps and the bending
    airplane's 128 on either side of :data:`AUTO_LAMP_TESTS_PER_FACE`; a traced mesh is inf."""
    from pathlib import Path
    from types import SimpleNamespace

    from jshadow.config import AUTO_LAMP_TESTS_PER_FACE, lamp_tests_per_face
    from jshadow.geometry import load_mesh

    assets = Path(__file__).resolve().parents[1] / "assets"

    def mesh(name):
        m = load_mesh(assets / name, dtype=jnp.float32)
        return SimpleNamespace(unit_vertices=np.asarray(m.vertices), faces=np.asarray(m.faces))

    bunny, airplane = mesh("bunny.obj"), mesh("airplane.obj")
    assert math.isclose(lamp_tests_per_face([bunny], 128, 128), 2 * lamp_tests_per_face([bunny], 64, 128))
    assert lamp_tests_per_face([bunny], 128, 128) > AUTO_LAMP_TESTS_PER_FACE
    assert lamp_tests_per_face([airplane], 128, 128) <= AUTO_LAMP_TESTS_PER_FACE
    assert lamp_tests_per_face([airplane, bunny], 128, 128) == lamp_tests_per_face([bunny], 128, 128)
    assert lamp_tests_per_face([], 128, 128) == 0.0

    def traced(v):
        t = SimpleNamespace(unit_vertices=v, faces=bunny.faces)
        return jnp.asarray(lamp_tests_per_face([t], 128, 128))

    assert np.isinf(jax.jit(traced)(jnp.asarray(bunny.unit_vertices)))


EGG_LIGHT = (
    '[method]\ndirections = [8, 8]\nbsv_grid = [6, 8]\nlight_visibility = "images"\nlight_cap = [2, 4]\n'
    '[environment]\ntype = "constant"\nradiance = [0.2, 0.2, 0.2]\n'
    '[[occluder]]\ntype = "mesh"\nshape = "egg"\nsubdivisions = 1\ncenter = [0.0, 1.0, 0.0]\nradius = 0.5\n'
    '[[light]]\ntype = "sphere"\ncenter = [0.5, 3.0, 0.2]\nradius = 0.3\nradiance = [10.0, 10.0, 10.0]\n'
    '[receiver]\ntype = "plane"\ncenter = [0.0, 0.0, 0.0]\nsize = [3.0, 3.0]\nresolution = [4, 4]\n'
)


def test_cli_render_reports_the_images_and_fit_refuses_a_sphere_occluder(tmp_path, capsys):
    from jshadow.cli import main

    cfg = tmp_path / "egg.toml"
    cfg.write_text(EGG_LIGHT + "[animation]\nframes = 2\n")
    assert main(["render", str(cfg), "--out", str(tmp_path / "r")]) == 0
    t = json.loads((tmp_path / "r" / "timings.json").read_text())
    assert t["light_image_computations"] == 1 and t["bsv_computations"] == 1  # a rigid egg: once
    assert t["light_fraction_computations"] == 1
    assert (t["light_visibility"], t["environment_lights"], t["self_visibility"]) == ("images", 0, "field")
    # given in [method]: directions and light_cap as set; no lamps to image
    assert (t["directions"], t["light_cap"], t["lamp_images"]) == ([8, 8], [2, 4], 0)
    assert all("light_images_ms" in f for f in t["per_frame"])
    assert "light images" in capsys.readouterr().out
    fit = tmp_path / "fit.toml"
    fit.write_text(
        EGG_LIGHT + '[fit]\nparams = ["light.0.center"]\ntarget_values = [[0.0, 3.0, 0.0]]\nsteps = 2\n'
    )
    assert main(["fit", str(fit), "--out", str(tmp_path / "f")]) == 0  # through the images' derivative
    report = json.loads((tmp_path / "f" / "fit.json").read_text())
    assert np.all(np.isfinite(report["params"]["light.0.center"]))
    capsys.readouterr()
    sphere = tmp_path / "sphere.toml"
    sphere.write_text(
        EGG_LIGHT
        + '[[occluder]]\ntype = "sphere"\ncenter = [1.0, 0.8, 1.0]\nradius = 0.3\n'
        + '[fit]\nparams = ["occluder.1.center"]\ntarget_values = [[1.0, 0.9, 1.0]]\nsteps = 2\n'
    )
    assert main(["fit", str(sphere), "--out", str(tmp_path / "s")]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if "error" in line]  # not the progress bar
    assert len(err) == 1 and err[0].startswith("jshadow fit: error: ")
    assert "light_visibility = 'sh'" in err[0]


def test_sphere_occluders_alone_keep_the_exact_lens():
    """With no mesh occluder there are no images to look up: the analytic path's exact lens is kept."""
    scene = _light_scene(SphereOccluder(f32(0.0, 1.1, 0.0), jnp.float32(0.6)), IMAGES, n=6)
    lens = render(dataclasses.replace(scene, method=SMALL)).irradiance
    np.testing.assert_array_equal(np.asarray(render(scene).irradiance), np.asarray(lens))


def test_jit_with_a_traced_time_matches_eager():
    """Under ``jax.jit`` with the animation time traced, the images of a deforming mesh are made
    inside the trace (the edge-scan's traced path) and give the eager frame."""
    occ = icosphere_occluder((0, 1.1, 0), 0.6, Twist(jnp.float32(0.0), jnp.float32(1.0), 1))
    scene = _light_scene(occ, IMAGES, n=5, n_frames=3)
    jitted = np.asarray(jax.jit(lambda t: render_at(scene, t).irradiance)(jnp.float32(0.5)))
    eager = np.asarray(render(scene, 1).irradiance)
    np.testing.assert_allclose(jitted, eager, atol=1e-5 * float(np.abs(eager).max()))
