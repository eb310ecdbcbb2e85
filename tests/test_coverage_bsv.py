"""The BSV projected from coverage images (``[method] bsv_images = "coverage"``).

Claims tested: projecting 0/1 images with ``coverage_sh`` gives exactly the edge-scan's BSV; the
coverage BSV is close to it; a frame rendered with it has the exact derivative of its own forward
pass (central differences of the same renders converge to the gradient in float64), with the
sphere light through the n-band path and with the light's images read from the same coverage;
the renderer and ``render`` agree; the config key is read and checked.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_coverage_images import DIRS, GRID, _lumpy_egg
from test_image_lookup_grad import _tapered_scene
from test_light_images import IMAGES, LIGHT
from test_scene import icosphere_occluder, plane

from jshadow.config import ConfigError, build_scene, config_from_dict
from jshadow.entities import Environment, Method, Scene
from jshadow.geometry import MeshWarning
from jshadow.runner import Renderer
from jshadow.scene import render
from jshadow.visibility import bsv_mesh_edgescan, coverage_sh, scan_coverage
from jshadow.visibility._edgescan import edgescan_occlusion


def test_coverage_sh_of_the_samples_is_the_edgescan_bsv_and_of_the_coverage_close_to_it():
    v, f = _lumpy_egg()
    bsv = np.asarray(bsv_mesh_edgescan(jnp.asarray(v), f, 5, GRID, DIRS, 1.5).coeffs)
    samples = edgescan_occlusion(jnp.asarray(v), f, GRID, DIRS, 1.5)[0].astype(jnp.float32)
    np.testing.assert_allclose(np.asarray(coverage_sh(samples, 5, DIRS, 1.5)), bsv, atol=2e-5)
    cov = np.asarray(coverage_sh(scan_coverage(v, f, GRID, DIRS, 1.5, scans="split"), 5, DIRS, 1.5))
    diff = np.abs(cov - bsv).max() / np.abs(bsv).max()
    print(f"coverage BSV against the samples' BSV: largest difference {diff:.2e} of the largest coefficient")
    assert 1e-5 < diff < 0.02  # antialiased, not the same images
    split = np.asarray(scan_coverage(v, f, GRID, DIRS, 1.5, scans="split"))
    binary = np.asarray(samples)
    assert split.min() > -0.05 and split.max() < 1.05  # a weighted coverage: near [0, 1]
    crossed = np.abs(np.asarray(scan_coverage(v, f, GRID, DIRS, 1.5)) - binary) > 1e-6
    np.testing.assert_allclose(split[~crossed], binary[~crossed], atol=1e-6)  # uncrossed: the samples
    with pytest.raises(ValueError, match="pixels"):
        coverage_sh(samples, 5, (DIRS[0], DIRS[1] + 1), 1.5)


def _scene(kappa, light_visibility):
    scene = _tapered_scene(np.random.default_rng(0), kappa)
    method = dataclasses.replace(
        scene.method,
        light_visibility=light_visibility,
        light_images="coverage",
        bsv_images="coverage",
        dtype="float64",
    )
    env = Environment(jnp.full(3, 0.3, jnp.float64))  # the BSV shadows the sky in both settings
    return dataclasses.replace(scene, method=method, environment=env)


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("light_visibility", ["sh", "images"])
def test_frame_with_the_coverage_bsv_has_the_exact_derivative_of_its_forward_pass(light_visibility):
    """A weighted sum of the frame's irradiance as a function of the mesh's taper κ (its vertices
    and bounding sphere move): ``jax.grad`` against central differences of the same renders at
    h = 1e-5 (float64; the forward pass is piecewise smooth, with kinks where a boundary crossing
    passes a pixel centre, so a much larger step can straddle one). With "images" the BSV and the
    light's images come from one coverage."""
    k0 = 0.3
    w = jnp.asarray(np.random.default_rng(2).uniform(0.5, 1.5, (100, 3)))

    def loss(k):
        return jnp.sum(w * render(_scene(k, light_visibility)).irradiance)

    g = float(jax.grad(loss)(jnp.float64(k0)))
    h = 1e-5
    fd = float(loss(k0 + h) - loss(k0 - h)) / (2 * h)
    print(f"{light_visibility}: grad {g:.7f}, central differences {fd:.7f}")
    assert abs(g) > 1e-3
    assert abs(fd - g) < 1e-4 * abs(g)


@pytest.mark.parametrize("light_visibility", ["sh", "images"])
def test_renderer_and_render_agree_with_the_coverage_bsv(light_visibility):
    occ = icosphere_occluder((0.0, 1.1, 0.0), 0.6)
    samples = dataclasses.replace(IMAGES, light_visibility=light_visibility)
    method = dataclasses.replace(samples, light_images="coverage", bsv_images="coverage")
    env = Environment(jnp.full(3, 0.3, jnp.float32))
    scene = Scene(method, plane(n=8), (occ,), (LIGHT,), env)
    a = np.asarray(render(scene).irradiance)
    b = np.asarray(Renderer(scene, progress=False).frame(0)[0].irradiance)
    s = np.asarray(render(dataclasses.replace(scene, method=samples)).irradiance)
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    assert 1e-5 * np.abs(s).max() < np.abs(a - s).max() < 0.05 * np.abs(s).max()


def test_bsv_images_key_is_read_and_checked():
    base = {"receiver": {"type": "plane", "center": [0, 0, 0], "size": [2, 2], "resolution": [2, 2]}}
    assert config_from_dict({**base, "method": {"bsv_images": "coverage"}}).method.to_method().bsv_images == (
        "coverage"
    )
    assert config_from_dict(base).method.bsv_images == "auto"
    assert config_from_dict(base).method.to_method().bsv_images == "samples"
    with pytest.raises(ConfigError, match="bsv_images"):
        config_from_dict({**base, "method": {"bsv_images": "area"}})
    with pytest.raises(ConfigError, match="bsv_gradient"):
        config_from_dict({**base, "method": {"bsv_images": "coverage", "bsv_gradient": "image"}})
    with pytest.raises(ValueError, match="bsv_images"):
        Method(bsv_images="bilinear")
    with pytest.raises(ConfigError, match="shell > 1"):
        config_from_dict({**base, "method": {"bsv_images": "coverage", "preset": "paper"}})


def test_a_mesh_the_edge_scan_cannot_sample_is_refused_with_the_coverage_bsv():
    """An open mesh (an icosphere missing a face) has no edge-scan, so no coverage: a clear error."""
    occ = icosphere_occluder((0.0, 1.1, 0.0), 0.6)
    occ = dataclasses.replace(occ, faces=occ.faces[1:])
    method = dataclasses.replace(IMAGES, light_visibility="sh", bsv_images="coverage")
    scene = Scene(method, plane(n=4), (occ,), (LIGHT,), Environment(jnp.full(3, 0.3, jnp.float32)))
    with pytest.raises(ValueError, match="edge-scan"):
        render(scene)


def test_bsv_images_auto_is_coverage_where_a_config_fits_a_mesh_deformation(tmp_path):
    # "auto" (the config default): the coverage BSV where [fit] fits a mesh's deformation and the
    # edge-scan applies; the samples for rendering alone, fitted lights, the paper's shell, an
    # explicit choice and an open mesh.
    (tmp_path / "open.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 2\nf 1 3 2\nf 1 2 4\nf 1 4 3\n")
    egg = {"type": "mesh", "shape": "egg", "subdivisions": 1, "center": [0, 1, 0], "radius": 0.5}
    egg["deform"] = {"type": "bend", "amount": 0.3}
    base = {
        "occluder": [egg],
        "light": [{"type": "sphere", "center": [0.5, 3, 0.3], "radius": 0.3, "radiance": [9, 9, 9]}],
        "receiver": {"type": "plane", "center": [0, 0, 0], "size": [2, 2], "resolution": [2, 2]},
    }
    bend = {"params": ["occluder.0.deform.amount"], "target_values": [0.8]}
    light = {"params": ["light.0.center"], "target_values": [[0.0, 3.0, 0.0]]}

    def chosen(d):
        return build_scene(config_from_dict(d, root=tmp_path)).method.bsv_images

    assert chosen({**base, "fit": bend}) == "coverage"
    assert chosen(base) == "samples"
    assert chosen({**base, "fit": light}) == "samples"
    assert chosen({**base, "fit": bend, "method": {"preset": "paper"}}) == "samples"
    assert chosen({**base, "fit": bend, "method": {"bsv_gradient": "image"}}) == "samples"
    assert chosen({**base, "fit": bend, "method": {"bsv_images": "samples"}}) == "samples"
    opened = {"type": "mesh", "file": "open.obj", "center": [2, 1, 0], "radius": 0.3}
    with pytest.warns(MeshWarning, match="open"):
        assert chosen({**base, "occluder": [egg, opened], "fit": bend}) == "samples"


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("light_images", [None, "coverage"])
def test_moving_a_mesh_occluder_leaves_its_samplers_out_of_the_derivative(light_images, monkeypatch):
    """The BSV and the occlusion images do not change when a mesh occluder moves (they are sampled
    about its own sphere), so the gradient with respect to its position needs none of their
    derivative machinery: the samplers are given the vertices with the centre held constant
    (``scene._sampler_vertices``). Default method (samples BSV, image-plane silhouette derivative;
    with "coverage", the light also shadowed through the coverage images, read bilinearly): the
    silhouette derivative's sizes are never measured (its rule never runs), and the gradient
    equals central differences of the same renders (float64, h = 1e-5: the forward pass is smooth
    in the position, the BSV and the images being fixed)."""
    from jshadow import scene as scene_module

    base = _tapered_scene(np.random.default_rng(0), 0.3)
    method = dataclasses.replace(base.method, light_visibility="sh", dtype="float64")
    if light_images is not None:
        method = dataclasses.replace(method, light_visibility="images", light_images=light_images)
    scene = dataclasses.replace(base, method=method, environment=Environment(jnp.full(3, 0.3, jnp.float64)))
    w = jnp.asarray(np.random.default_rng(3).uniform(0.5, 1.5, (100, 3)))

    def loss(c):
        moved = eqx.tree_at(lambda s: s.occluders[0].center, scene, c)
        return jnp.sum(w * render(moved).irradiance)

    c0 = scene.occluders[0].center
    loss(c0)  # concrete: the forward pass's sizes
    monkeypatch.setattr(scene_module, "_PENDING", {})
    kept = {k: v for k, v in scene_module._SLOTS.items() if k[0] != "image"}
    monkeypatch.setattr(scene_module, "_SLOTS", kept)
    g = np.asarray(jax.grad(loss)(c0))
    assert not [k for k in scene_module._SLOTS if k[0] == "image"]  # no silhouette derivative ran
    h = 1e-5
    fd = np.array([float(loss(c0 + h * e) - loss(c0 - h * e)) / (2 * h) for e in np.eye(3)])
    print(f"{light_images}: grad {g}, central differences {fd}")
    assert np.abs(g).max() > 1e-2
    # the bilinear reads' derivative jumps where a ray crosses a pixel-centre line, and among the
    # 100 receivers' cap rays the ±h steps straddle some (measured: 1.7e-4 of the largest component)
    tol = 1e-7 if light_images is None else 1e-3
    np.testing.assert_allclose(g, fd, rtol=0, atol=tol * np.abs(g).max())
