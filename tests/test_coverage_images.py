"""Coverage images (``jshadow.visibility.scan_coverage``, ``[method] light_images = "coverage"``).

Claims tested: the column (row) coverage of every pixel is the fraction of its centre line inside
the occluded region, checked against the edge-scan's own centre samples at 32× the rows (columns);
the images lie in [0, 1] and equal the 0/1 samples wherever no boundary crosses a pixel's lines;
their derivative with respect to the vertices is the exact one (central differences converge to
it in float64); lookups that read them bilinearly have the exact derivative of what they compute
(a deformation and the light's position, against central differences of the same forward pass);
the renderer and ``render`` agree; the config key is read and checked.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_image_lookup_grad import _tapered_scene
from test_light_images import IMAGES, LIGHT
from test_scene import icosphere_occluder, plane

from jshadow.config import ConfigError, config_from_dict
from jshadow.entities import Environment, Method, Scene
from jshadow.geometry import egg
from jshadow.runner import Renderer
from jshadow.scene import light_visible_fractions, occluder_images, render
from jshadow.visibility import edgescan_scan_slots, edgescan_slots, scan_coverage
from jshadow.visibility._edgescan import edgescan_occlusion

GRID, DIRS = (6, 10), (16, 16)


def _lumpy_egg(dtype=np.float32):
    m = egg(2)
    return (np.asarray(m.vertices, np.float64) * [1.0, 0.7, 1.2] + 0.1).astype(dtype), np.asarray(m.faces)


@pytest.mark.parametrize("scans", ["columns", "rows"])
def test_coverage_is_the_fraction_of_each_scan_line_inside_the_shadow(scans):
    v, f = _lumpy_egg()
    cov = np.asarray(scan_coverage(v, f, GRID, DIRS, 1.5, scans=scans))
    binary = np.asarray(edgescan_occlusion(jnp.asarray(v), f, GRID, DIRS, 1.5)[0]).astype(np.float64)
    s = 32  # the same lines sampled 32 times as densely by the edge-scan itself
    if scans == "columns":
        fine = np.asarray(edgescan_occlusion(jnp.asarray(v), f, GRID, (DIRS[0] * s, DIRS[1]), 1.5)[0])
        fine = fine.reshape(*GRID, DIRS[0], s, DIRS[1]).mean(3)
    else:
        fine = np.asarray(edgescan_occlusion(jnp.asarray(v), f, GRID, (DIRS[0], DIRS[1] * s), 1.5)[0])
        fine = fine.reshape(*GRID, DIRS[0], DIRS[1], s).mean(4)
    err = np.abs(cov - fine)
    print(
        f"{scans}: max {err.max():.4f}, mean {err.mean():.2e};",
        f"0/1 samples: mean {np.abs(binary - fine).mean():.2e}",
    )
    assert cov.shape == binary.shape
    assert cov.min() >= -1e-6 and cov.max() <= 1 + 1e-6
    assert err.max() < 1.5 / s  # a boundary crossing's position within half a fine sample
    assert err.mean() < 0.1 * np.abs(binary - fine).mean()
    moved = np.abs(cov - binary) > 1e-6
    assert 0.01 < moved.mean() < 0.5  # only pixels a boundary crosses differ from the samples


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("scans", ["both", "split"])
def test_coverage_derivative_is_exact(scans):
    v0, f = _lumpy_egg(np.float64)
    rng = np.random.default_rng(1)
    dv = rng.normal(size=v0.shape) * 0.05 + np.array([0.3, -0.2, 0.1])
    w = jnp.asarray(rng.uniform(0.5, 1.5, (*GRID, *DIRS)))
    slots = edgescan_slots(v0, f, GRID, DIRS, 1.5, margin=3.0)
    scan_slots = edgescan_scan_slots(v0, f, GRID, DIRS, 1.5, slots=slots, margin=3.0)

    def loss(x):
        return jnp.sum(
            w * scan_coverage(x, f, GRID, DIRS, 1.5, scans=scans, slots=slots, scan_slots=scan_slots)
        )

    v0j, dvj = jnp.asarray(v0), jnp.asarray(dv)
    _, tangent = jax.jit(lambda x, d: jax.jvp(loss, (x,), (d,)))(v0j, dvj)
    grad = jax.jit(jax.grad(loss))(v0j)
    np.testing.assert_allclose(float(jnp.sum(grad * dvj)), float(tangent), rtol=1e-10)
    lj = jax.jit(loss)
    errs = [
        abs(float((lj(v0j + h * dvj) - lj(v0j - h * dvj)) / (2 * h)) / float(tangent) - 1)
        for h in (1e-3, 1e-4)
    ]
    print(f"jvp {float(tangent):.6f}; central differences off by {errs}")
    assert errs[1] < 2e-4 and errs[1] < errs[0]  # converging to it as h shrinks


def _coverage_scene(kappa, light_center=None):
    scene = _tapered_scene(np.random.default_rng(0), kappa)
    scene = dataclasses.replace(scene, method=dataclasses.replace(scene.method, light_images="coverage"))
    if light_center is not None:
        scene = dataclasses.replace(
            scene, lights=(dataclasses.replace(scene.lights[0], center=light_center),)
        )
    return scene


def _fraction_sum(scene):
    images = (occluder_images(scene.occluders[0], 0.0, scene),)
    pts, nrm = scene.receivers.points, scene.receivers.normals
    return jnp.sum(light_visible_fractions(scene, images, pts, nrm)[0])


@pytest.mark.usefixtures("x64")
def test_coverage_lookups_have_the_exact_derivative_of_their_forward_pass():
    """The visible fractions of a sphere light through coverage images, read bilinearly: their
    derivative with respect to a deformation (the taper κ: the vertices and the bounding sphere move)
    and to the light's position equals central differences of the same forward pass. The forward
    pass is piecewise smooth (kinks where a read point or a crossing passes a pixel centre), so the
    differences converge to it at small steps: h = 1e-5 in float64 (at 1e-3 a kink within the
    step moves the light's x component by half)."""
    k0 = 0.3
    g = float(jax.grad(lambda k: _fraction_sum(_coverage_scene(k)))(jnp.float64(k0)))
    fd = [
        float(_fraction_sum(_coverage_scene(k0 + h)) - _fraction_sum(_coverage_scene(k0 - h))) / (2 * h)
        for h in (1e-5,)
    ]
    print(f"taper: grad {g:.6f}, central differences {fd}")
    assert abs(fd[0] - g) < 1e-4 * abs(g)

    c0 = jnp.asarray([0.5, 3.2, 0.3])
    gl = np.asarray(jax.grad(lambda c: _fraction_sum(_coverage_scene(k0, c)))(c0))
    h = 1e-5
    fdl = [
        (
            float(_fraction_sum(_coverage_scene(k0, c0 + h * e)))
            - float(_fraction_sum(_coverage_scene(k0, c0 - h * e)))
        )
        / (2 * h)
        for e in np.eye(3)
    ]
    print("light position: grad", gl, "central differences", fdl)
    np.testing.assert_allclose(gl, fdl, rtol=1e-4, atol=1e-5 * np.abs(gl).max())


def test_renderer_and_render_agree_with_coverage_images():
    occ = icosphere_occluder((0.0, 1.1, 0.0), 0.6)
    method = dataclasses.replace(IMAGES, light_images="coverage")
    scene = Scene(method, plane(n=8), (occ,), (LIGHT,), Environment(jnp.full(3, 0.3, jnp.float32)))
    a = np.asarray(render(scene).irradiance)
    b = np.asarray(Renderer(scene, progress=False).frame(0)[0].irradiance)
    samples = np.asarray(render(dataclasses.replace(scene, method=IMAGES)).irradiance)
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
    assert np.abs(a - samples).max() > 1e-4  # the coverage is read, not the 0/1 samples
    assert np.abs(a - samples).max() < 0.05 * np.abs(samples).max()


def test_light_images_key_is_read_and_checked():
    base = {"receiver": {"type": "plane", "center": [0, 0, 0], "size": [2, 2], "resolution": [2, 2]}}
    cfg = config_from_dict({**base, "method": {"light_visibility": "images", "light_images": "coverage"}})
    assert cfg.method.to_method().light_images == "coverage"
    assert config_from_dict(base).method.to_method().light_images == "samples"
    with pytest.raises(ConfigError, match="light_images"):
        config_from_dict({**base, "method": {"light_images": "bilinear"}})
    with pytest.raises(ValueError, match="light_images"):
        Method(light_images="area")


def test_sizes_too_small_grow_on_concrete_poses_and_raise_under_a_trace():
    v, f = _lumpy_egg()
    want = np.asarray(scan_coverage(v, f, GRID, DIRS, 1.5))
    small_slots, small_scan = (64, 32, 8, 2), (64, 32, 8, 2, 64)
    got = np.asarray(scan_coverage(v, f, GRID, DIRS, 1.5, slots=small_slots, scan_slots=small_scan))
    np.testing.assert_allclose(got, want, atol=1e-6)
    # a mesh never seen concretely with these sizes: under a trace its overflow raises at run time
    m = egg(1)
    v1, f1 = np.asarray(m.vertices, np.float32), np.asarray(m.faces)

    def traced(x):
        return scan_coverage(x, f1, GRID, DIRS, 1.5, slots=small_slots, scan_slots=small_scan)

    with pytest.raises(Exception, match="overflowed"):
        jax.block_until_ready(jax.jit(traced)(jnp.asarray(v1)))
