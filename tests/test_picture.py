"""draw_scene: the per-frame picture shows the plane's radiance, the occluders and the lights."""

import io
from types import SimpleNamespace

import imageio.v3 as iio
import jax.numpy as jnp
import numpy as np

from jshadow.entities import Method, Receivers, Scene, SphereLight, SphereOccluder
from jshadow.picture import draw_scene, exposure_for, tonemap


def _scene(lights=()):
    n = 9
    g = np.linspace(-2.0, 2.0, n, dtype=np.float32)
    x, z = np.meshgrid(g, g)
    pts = np.stack([x.ravel(), np.zeros(n * n, np.float32), z.ravel()], -1)
    rec = Receivers(jnp.asarray(pts), jnp.tile(jnp.float32([0, 1, 0]), (n * n, 1)), jnp.full(3, 0.8), (n, n))
    occ = (SphereOccluder(jnp.float32([0.0, 1.0, 0.0]), jnp.float32(0.5)),)
    return Scene(Method(), rec, occ, lights)


def _png(scene, radiance, **kw):
    buf = io.BytesIO()
    draw_scene(buf, scene, SimpleNamespace(radiance=radiance), 0.0, **kw)
    return iio.imread(buf.getvalue(), extension=".png")


def test_draw_scene_shows_the_plane_radiance_and_the_occluder():
    scene = _scene()
    bright = _png(scene, np.ones((81, 3), np.float32))
    dark = _png(scene, np.full((81, 3), 0.05, np.float32))
    assert bright.shape[:2] == (480, 640) and bright.dtype == np.uint8
    # the plane covers much of the picture and follows the radiance; the sphere does not
    differs = np.any(bright[..., :3] != dark[..., :3], axis=-1)
    assert 0.2 < differs.mean() < 0.95
    assert bright[..., :3].astype(float).mean() > dark[..., :3].astype(float).mean() + 40
    # a dark band in the plane's middle rows shows as a darker region than the same rows lit
    half = np.ones((9, 9, 3), np.float32)
    half[3:6] = 0.0
    banded = _png(scene, half.reshape(-1, 3))
    assert banded[..., :3].astype(float).sum() < bright[..., :3].astype(float).sum()


def test_draw_scene_draws_lights_in_their_colour_and_writes_files(tmp_path):
    red = SphereLight(jnp.float32([1.5, 2.0, 0.0]), jnp.float32(0.3), jnp.float32([5.0, 0.0, 0.0]))
    scene = _scene((red,))
    rad = np.full((81, 3), 0.5, np.float32)
    img = _png(scene, rad, exposure=exposure_for(rad), title="x")
    without = _png(_scene(), rad, exposure=exposure_for(rad), title="x")
    new = np.any(img[..., :3] != without[..., :3], axis=-1)
    assert new.sum() > 50  # the light is drawn
    r, g, b = (img[..., i][new].astype(float).mean() for i in range(3))
    assert r > 150 and r > 3 * max(g, b)
    path = tmp_path / "f.png"
    draw_scene(path, scene, SimpleNamespace(radiance=rad), 0.0, exposure=exposure_for(rad), title="x")
    np.testing.assert_array_equal(iio.imread(path), img)


def test_tonemap_is_monotone_and_bounded():
    x = np.linspace(0.0, 100.0, 1001)[:, None].repeat(3, 1)
    y = tonemap(x, 1.0)
    assert np.all(np.diff(y[:, 0].astype(float)) >= 0) and y.min() >= 0 and y.max() <= 255
