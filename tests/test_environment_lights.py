"""A lat-long map's bright part as distant lights shadowed through the occlusion images
(``[method] environment_lights``; :mod:`jshadow.envlights`).

Claims tested: the median cut labels every pixel, makes equal-weight halves and keeps subtrees
consecutive, and rejects bad input; the split is exact (rest + bright part = the map, the lights'
energies sum to the bright part's, the irradiance maps add up) and clamps the rest at the
threshold; a mesh sphere under a map with a small bright "sun" matches a brute-force sum over the
map's pixels with exact ray casts far better than the n-band path; an occluder's own vertices are
marked for the n-band fallback and the plane's are not; the Renderer's paths agree with
``render``; the irradiance is homogeneous of degree 1 in the radiance (its gradient works) and
the receivers' derivative is finite and non-zero; config keys are read and checked; a traced
image is refused in words; a deforming mesh with own-vertex rays renders under jit with a traced
time as it does eagerly.
"""

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_scene import SMALL, f32, icosphere_occluder, plane

from jshadow.config import ConfigError, build_scene, config_from_dict
from jshadow.entities import Environment, Method, Scene, latlong_to_dir
from jshadow.envlights import median_cut, split_environment
from jshadow.geometry import Twist
from jshadow.lights import environment_irradiance_map, environment_sh
from jshadow.runner import Renderer
from jshadow.scene import (
    environment_visible_fraction,
    own_rows_at_time,
    render,
    render_at,
    scene_images,
    scene_lighting,
)
from jshadow.visibility import ray_fan_any_hit

SPLIT = dataclasses.replace(SMALL, light_visibility="images", environment_lights=8)
SUN = np.array([0.35, 0.9, 0.25]) / np.linalg.norm([0.35, 0.9, 0.25])


def _sun_map(h=32, w=64, sky=0.1, sun=400.0):
    """A dim constant sky with the 2 × 2 pixels nearest SUN at ``sun`` (with a warm tint)."""
    v = (np.arange(h) + 0.5) / h
    u = (np.arange(w) + 0.5) / w
    uu, vv = np.meshgrid(u, v)
    d = np.asarray(latlong_to_dir(jnp.asarray(uu), jnp.asarray(vv)))
    img = np.full((h, w, 3), sky, np.float32)
    near = np.argsort(-(d @ SUN).ravel())[:4]
    img.reshape(-1, 3)[near] = np.float32([sun, 0.9 * sun, 0.8 * sun])
    return img


def test_median_cut_labels_halves_and_order():
    rng = np.random.default_rng(0)
    w = rng.uniform(0.5, 1.5, (16, 32))
    labels = median_cut(w, 8)
    assert labels.shape == w.shape and set(np.unique(labels)) == set(range(8))
    e = np.bincount(labels.ravel(), weights=w.ravel())
    # every cut halves within one row or column of its region
    assert e.max() / e.min() < 1.5
    # depth-first order: the first cut's two halves are labels 0..3 and 4..7, each one rectangle
    for half in (labels < 4, labels >= 4):
        rows, cols = np.nonzero(half)
        assert half[rows.min() : rows.max() + 1, cols.min() : cols.max() + 1].all()
    one = np.zeros((4, 8))
    one[1, 2] = 1.0  # a single bright pixel: one region holds all of it
    e1 = np.bincount(median_cut(one, 16).ravel(), weights=one.ravel(), minlength=16)
    assert np.count_nonzero(e1) == 1
    with pytest.raises(ValueError, match="power of two"):
        median_cut(w, 6)
    with pytest.raises(ValueError, match="non-negative"):
        median_cut(-w, 4)


def test_split_is_exact_and_clamps_the_rest():
    img = _sun_map()
    env = Environment(f32(1.0, 0.5, 2.0), jnp.asarray(img), "hdr")
    rest, lights = split_environment(env, 8, threshold=4.0)
    h, w = img.shape[:2]
    edges = np.cos(np.pi * np.arange(h + 1) / h)
    omega = ((edges[:-1] - edges[1:]) * 2 * np.pi / w)[:, None, None]
    mean_lum = float((img.mean(-1, keepdims=True) * omega).sum() / (4 * np.pi))
    assert float(jnp.max(jnp.mean(rest.image, -1))) <= 4.0 * mean_lum * (1 + 1e-5)
    bright = img - np.asarray(rest.image)
    assert np.all(bright >= -1e-4)
    want = (bright * omega).sum((0, 1)) * np.asarray(env.radiance)
    np.testing.assert_allclose(np.asarray(lights.energy).sum(0), want, rtol=1e-4)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(lights.directions), axis=-1), 1.0, atol=1e-5)
    # the lights sit at the sun; the irradiance maps and the SH of the parts add up to the map's
    hot = np.asarray(lights.energy)[:, 0] > 0
    assert np.all(np.asarray(lights.directions)[hot] @ SUN > math.cos(math.radians(8)))
    full = environment_irradiance_map(env).values
    parts = environment_irradiance_map(rest).values + lights.unoccluded.values
    np.testing.assert_allclose(np.asarray(parts), np.asarray(full), rtol=1e-4)
    np.testing.assert_allclose(
        np.asarray(
            environment_sh(rest, 4) + environment_sh(Environment(env.radiance, jnp.asarray(bright), "hdr"), 4)
        ),
        np.asarray(environment_sh(env, 4)),
        rtol=1e-4,
        atol=1e-4,
    )
    with pytest.raises(ValueError, match="lat-long"):
        split_environment(Environment(f32(1, 1, 1)), 8)
    with pytest.raises(ValueError, match="threshold"):
        split_environment(env, 8, threshold=0.0)
    with pytest.raises(ValueError, match="concrete"):
        jax.jit(lambda im: split_environment(Environment(env.radiance, im, "hdr"), 8)[1].energy)(env.image)


def _sun_scene(method, n=8, self_shadow=False):
    occ = icosphere_occluder((0.0, 1.1, 0.0), 0.6, subdiv=2)
    env = Environment(f32(1.0, 1.0, 1.0), jnp.asarray(_sun_map()), "hdr")
    return Scene(method, plane(n=n, size=3.0), (occ,), (), env, self_shadow=self_shadow)


def _brute_force(scene, sub=2, points=None, normals=None):
    """Σ over the map's pixels (``sub``² directions each) of L ω cos⁺ V, V by exact ray casts from
    ``points`` (default: the plane's receivers)."""
    img = np.asarray(scene.environment.image, np.float64)
    h, w = img.shape[:2]
    v = (np.arange(h * sub) + 0.5) / (h * sub)
    u = (np.arange(w * sub) + 0.5) / (w * sub)
    uu, vv = np.meshgrid(u, v)
    d = np.asarray(latlong_to_dir(jnp.asarray(uu), jnp.asarray(vv)), np.float64)
    edges = np.cos(np.pi * np.arange(h * sub + 1) / (h * sub))
    omega = np.broadcast_to(((edges[:-1] - edges[1:]) * 2 * np.pi / (w * sub))[:, None], d.shape[:2])
    rad = np.repeat(np.repeat(img, sub, 0), sub, 1)
    keep = rad.mean(-1) > 0
    d, omega, rad = d[keep], omega[keep], rad[keep]
    occ = scene.occluders[0]
    pts = scene.receivers.points if points is None else points
    normals = scene.receivers.normals if normals is None else normals
    hit = np.asarray(
        ray_fan_any_hit(
            pts,
            jnp.broadcast_to(jnp.asarray(d, jnp.float32), (pts.shape[0], *d.shape)),
            occ.vertices(0.0),
            occ.faces,
        )
    )
    cos = np.maximum(np.asarray(normals, np.float64) @ d.T, 0.0)
    return (cos * (1.0 - hit) * omega) @ rad


def test_sun_shadow_matches_brute_force_far_better_than_n_bands():
    scene = _sun_scene(SPLIT)
    truth = _brute_force(scene)
    ours = np.asarray(render(scene).irradiance, np.float64)
    n_band = np.asarray(render(dataclasses.replace(scene, method=SMALL)).irradiance, np.float64)
    mean = truth.mean()

    def rel(x):
        return float(np.sqrt(np.mean((x - truth) ** 2)) / mean)

    print(f"sun shadow against the pixel sum: environment lights {rel(ours):.2%}, n-band {rel(n_band):.2%}")
    assert truth.min() < 0.5 * truth.max()  # the sun's shadow falls on the plane
    assert rel(ours) < 0.04
    assert rel(ours) < 0.33 * rel(n_band)


def _exact_fraction(lights, occ, pts, nrm):
    """(N, 3) energy- and cosine-weighted visible fraction of the lights by exact rays to ``occ``."""
    d = lights.directions
    free = ~np.asarray(
        ray_fan_any_hit(pts, jnp.broadcast_to(d, (pts.shape[0], *d.shape)), occ.vertices(0.0), occ.faces)
    )
    cos = np.maximum(np.asarray(nrm) @ np.asarray(d).T, 0.0)
    energy = np.asarray(lights.energy, np.float64)
    return ((cos * free) @ energy) / (cos @ energy)


def test_lamp_images_give_the_lights_exact_visibility():
    """With ``lamp_images`` the K lights are looked up in orthographic images along their
    directions: the plane's visible fraction of them is that of exact rays toward the K directions
    up to the pixels at the shadows' edges (interpolated there), closer than the shell images'
    lookups; a Renderer makes
    them once for a rigid mesh (its frames equal render's); without the option there are none."""
    from jshadow.scene import environment_visible_fraction, scene_images, scene_lighting, with_lamp_images

    lamps = dataclasses.replace(SPLIT, environment_lights=32, lamp_images=64)
    scene = _sun_scene(lamps, n=16)
    lights = scene_lighting(scene).env_lights
    pts, nrm = scene.receivers.points, scene.receivers.normals
    occ = scene.occluders[0]
    exact = _exact_fraction(lights, occ, pts, nrm)
    assert exact.min() < 0.5  # the sun's shadow falls on the plane

    def fraction(images):
        return np.asarray(environment_visible_fraction(scene, images, lights, pts, nrm)[0], np.float64)

    images = with_lamp_images(scene, 0.0, scene_images(scene, 0.0))
    assert images[0].lamps.covered.shape == (32, 64, 64)
    ours, shell = fraction(images), fraction(scene_images(scene, 0.0))
    err, err_shell = np.abs(ours - exact), np.abs(shell - exact)
    print(
        f"visible fraction against exact rays: lamp images mean {err.mean():.4f} max {err.max():.3f}, "
        f"shell images mean {err_shell.mean():.4f} max {err_shell.max():.3f}"
    )
    # measured: 4.3 % of the receivers differ at all (within a pixel of a shadow edge, where the
    # lookup interpolates), RMS 0.030 and max 0.30 against the shell's 0.036 and 0.47
    assert np.mean(err > 1e-6) < 0.05
    assert np.sqrt(np.mean(err**2)) < np.sqrt(np.mean(err_shell**2)) and err.max() < err_shell.max()
    plain = _sun_scene(SPLIT)
    assert with_lamp_images(plain, 0.0, scene_images(plain, 0.0))[0].lamps is None
    small = _sun_scene(lamps, n=6)
    r = Renderer(small)
    a, _ = r.frame(0)
    b, _ = r.frame(0)
    assert r.image_computations == 1
    want = np.asarray(render(small).irradiance)
    for x in (a, b):  # the second frame is read out of the field's table, with the lamps' offset
        np.testing.assert_allclose(np.asarray(x.irradiance), want, atol=1e-5 * np.abs(want).max())


def test_receivers_within_a_mesh_sphere_read_its_lamp_images():
    """A flat lens whose bounding sphere reaches below the plane while the lens stays above it: the
    plane's receivers within the sphere are not routed to the n-band path (``inside`` False, as
    before for the shell's images they were) and their visible fraction of the lamps is that of
    exact rays, up to the pixels at the shadows' edges."""
    import trimesh

    from jshadow.entities import MeshOccluder
    from jshadow.geometry import normalize_to_unit_sphere
    from jshadow.scene import with_lamp_images

    m = trimesh.creation.icosphere(subdivisions=3)
    unit = normalize_to_unit_sphere(jnp.asarray(m.vertices * np.asarray([1.0, 0.3, 1.0]), jnp.float32))
    occ = MeshOccluder(unit, jnp.asarray(m.faces, jnp.int32), f32(0.0, 0.5, 0.0), jnp.float32(0.8))
    lamps = dataclasses.replace(SPLIT, environment_lights=32, lamp_images=96)
    env = Environment(f32(1.0, 1.0, 1.0), jnp.asarray(_sun_map()), "hdr")
    scene = Scene(lamps, plane(n=24, size=3.0), (occ,), (), env)
    lights = scene_lighting(scene).env_lights
    pts, nrm = scene.receivers.points, scene.receivers.normals
    images = with_lamp_images(scene, 0.0, scene_images(scene, 0.0))
    within = np.linalg.norm(np.asarray(pts - images[0].center), axis=1) < float(images[0].radius)
    assert within.sum() > 40 and float(jnp.min(occ.vertices(0.0)[:, 1])) > 0.2
    fraction, inside = environment_visible_fraction(scene, images, lights, pts, nrm)
    assert not np.any(np.asarray(inside))
    exact = _exact_fraction(lights, occ, pts, nrm)
    assert exact[within].min() < 0.5  # the lens shadows receivers within its sphere
    err = np.abs(np.asarray(fraction, np.float64) - exact)
    # measured: 6.6 % of them differ at all (within a pixel of a shadow edge), RMS 0.052
    assert np.mean(err[within] > 1e-6) < 0.15 and np.sqrt(np.mean(err[within] ** 2)) < 0.08


def test_own_vertices_fall_back_and_the_plane_does_not():
    scene = _sun_scene(SPLIT, n=5, self_shadow=True)
    out = render(scene)
    points, normals = out.points, out.normals
    lighting = scene_lighting(scene)
    _, inside = environment_visible_fraction(
        scene, scene_images(scene, 0.0), lighting.env_lights, points, normals
    )
    n_plane = scene.receivers.points.shape[0]
    assert not np.any(np.asarray(inside[:n_plane])) and np.all(np.asarray(inside[n_plane:]))
    assert np.all(np.isfinite(np.asarray(out.irradiance)))
    # the own vertices' bright part is the n-band path's: close to the unsplit render there
    unsplit = render(dataclasses.replace(scene, method=SMALL)).irradiance[n_plane:]
    scale = float(jnp.mean(unsplit))
    assert float(jnp.sqrt(jnp.mean((out.irradiance[n_plane:] - unsplit) ** 2))) < 0.05 * scale


@pytest.mark.parametrize("own", ["rays", "light_rays"])
def test_own_vertices_with_rays_see_the_lights_exactly(own):
    """With ``self_visibility = "rays"`` or "light_rays" the own vertices' bright part uses exact
    rays toward the lights: against the brute-force pixel sum at those vertices it beats the n-band
    fallback. "light_rays" keeps the field's visibility for the rest (the same own-vertex rows for
    the lights as "rays", no visibility SH cast), and the Renderer casts a rigid shape once."""
    rays = _sun_scene(dataclasses.replace(SPLIT, self_visibility=own), n=3, self_shadow=True)
    fallback = dataclasses.replace(rays, method=SPLIT)
    rows = own_rows_at_time(rays, 0.0)
    full = own_rows_at_time(
        dataclasses.replace(rays, method=dataclasses.replace(SPLIT, self_visibility="rays")), 0.0
    )
    assert (rows[0] is None) == (own == "light_rays")
    np.testing.assert_array_equal(np.asarray(rows[2]), np.asarray(full[2]))
    out = render(rays)
    n_plane = rays.receivers.points.shape[0]
    pts, nrm = out.points[n_plane:], out.normals[n_plane:]
    truth = _brute_force(rays, points=pts, normals=nrm)
    mean = truth.mean()

    def rel(x):
        return float(np.sqrt(np.mean((np.asarray(x[n_plane:], np.float64) - truth) ** 2)) / mean)

    with_rays, without = rel(out.irradiance), rel(render(fallback).irradiance)
    print(f"own vertices against the pixel sum: rays {with_rays:.2%}, n-band fallback {without:.2%}")
    assert with_rays < 0.03 and with_rays < 0.5 * without
    r = Renderer(rays)
    got, _ = r.frame(0)
    np.testing.assert_allclose(
        np.asarray(got.irradiance), np.asarray(out.irradiance), atol=1e-5 * float(mean)
    )
    again, _ = r.frame(
        0
    )  # read out of the field's table, the lamps' terms (and the cast transfer's) an offset
    assert r.self_visibility_computations == 1
    assert r.readout_frames == 1
    np.testing.assert_allclose(
        np.asarray(again.irradiance), np.asarray(out.irradiance), atol=1e-5 * float(mean)
    )

    def moved(dy):  # the own vertices move: their binary rays have no derivative to give
        occ = rays.occluders[0]
        o = dataclasses.replace(occ, center=occ.center + dy * jnp.asarray([0.0, 1.0, 0.0], jnp.float32))
        return jnp.sum(render(dataclasses.replace(rays, occluders=(o,))).irradiance)

    with pytest.raises(ValueError, match="light_rays"):
        jax.grad(moved)(jnp.float32(0.0))
    b, _ = Renderer(rays, split_stages=True, chunk=64).frame(0)
    np.testing.assert_allclose(np.asarray(b.irradiance), np.asarray(out.irradiance), atol=1e-5 * float(mean))


def test_renderer_paths_agree():
    scene = _sun_scene(SPLIT, n=6, self_shadow=True)
    ref = np.asarray(render(scene).irradiance)
    r = Renderer(scene)
    a, times = r.frame(0)
    assert r.image_computations == 1 and "light_images_ms" in times
    b, _ = Renderer(scene, split_stages=True, chunk=16).frame(0)
    scale = float(np.abs(ref).max())
    for x in (a, b):
        np.testing.assert_allclose(np.asarray(x.irradiance), ref, atol=1e-5 * scale)


def test_radiance_and_geometry_gradients_work():
    scene = _sun_scene(SPLIT, n=4)

    def total(radiance):
        env = dataclasses.replace(scene.environment, radiance=radiance)
        return jnp.sum(render(dataclasses.replace(scene, environment=env)).irradiance)

    r0 = f32(1.0, 0.7, 0.4)
    value, g = jax.jit(jax.value_and_grad(total))(r0)
    # irradiance is linear in each channel's radiance: Euler's identity for degree-1 homogeneity
    np.testing.assert_allclose(float(jnp.dot(g, r0)), float(value), rtol=1e-4)
    # the visible fraction's derivative with respect to the receivers goes through the coverage
    # images (the read points' motion; accuracy in tests/test_image_lookup_grad.py)
    scene = _sun_scene(SPLIT, n=12)  # receivers in the sun's penumbra (at 4², none is)
    images, lights = scene_images(scene, 0.0), scene_lighting(scene).env_lights
    pts, nrm = scene.receivers.points, scene.receivers.normals

    def fraction(shift):
        return jnp.sum(environment_visible_fraction(scene, images, lights, pts + shift, nrm)[0])

    g = float(jax.grad(fraction)(jnp.float32(0.0)))
    assert np.isfinite(g) and g != 0.0  # moving the receivers moves them in the sun's shadow
    assert float(fraction(jnp.float32(0.0))) < 3.0 * pts.shape[0]  # some of the sun is hidden


def test_config_keys_are_read_and_checked():
    base = {
        "occluder": [{"type": "mesh", "shape": "egg", "subdivisions": 1, "center": [0, 1, 0], "radius": 0.5}],
        "environment": {"type": "constant", "radiance": [1, 1, 1]},
        "receiver": {"type": "plane", "center": [0, 0, 0], "size": [2, 2], "resolution": [2, 2]},
    }
    m = config_from_dict(
        {
            **base,
            "method": {"light_visibility": "images", "environment_lights": 16, "environment_threshold": 2.5},
        }
    ).method.to_method()
    assert m.environment_lights == 16 and m.environment_threshold == 2.5
    with pytest.raises(ConfigError, match="light_visibility = 'images'"):
        config_from_dict({**base, "method": {"light_visibility": "sh", "environment_lights": 8}})
    with pytest.raises(ConfigError, match="environment_lights.*light_visibility = 'auto' does not take"):
        build_scene(config_from_dict({**base, "method": {"environment_lights": 8}}))  # a constant sky
    with pytest.raises(ConfigError, match="power of two"):
        config_from_dict({**base, "method": {"light_visibility": "images", "environment_lights": 12}})
    with pytest.raises(ConfigError, match="environment_threshold"):
        config_from_dict({**base, "method": {"environment_threshold": -1.0}})
    assert Method().environment_lights == 0  # off by default: not differentiable in geometry


def test_deforming_mesh_with_rays_under_jit_and_in_the_renderer():
    """A twisting mesh with own-vertex rays toward the lights: under ``jax.jit`` with the time
    traced, the casts and images are made in the trace and give the Renderer's frame (concrete
    casts; up to grazing rays that the two may decide differently); the Renderer casts every frame."""
    occ = icosphere_occluder((0, 1.1, 0), 0.6, Twist(jnp.float32(0.0), jnp.float32(1.0), 1), subdiv=1)
    env = Environment(f32(1.0, 1.0, 1.0), jnp.asarray(_sun_map()), "hdr")
    small = dict(bsv_grid=(6, 8), directions=(8, 8), self_visibility_grid=(4, 8))
    method = dataclasses.replace(SPLIT, self_visibility="rays", **small)
    scene = Scene(method, plane(n=3, size=3.0), (occ,), (), env, self_shadow=True, n_frames=3)
    jitted = np.asarray(jax.jit(lambda t: render_at(scene, t).irradiance)(jnp.float32(0.5)))
    r = Renderer(scene)
    frames = [np.asarray(r.frame(f)[0].irradiance) for f in range(3)]  # t = 0, 0.5, 1: concrete casts
    assert r.self_visibility_computations == 3  # a deforming mesh: cast every frame
    scale = float(np.abs(frames[1]).max())
    np.testing.assert_allclose(jitted, frames[1], atol=1e-3 * scale)
    assert np.abs(frames[2] - frames[0]).max() > 1e-3 * scale  # the twist changes the shading


def test_region_spread_is_the_regions_second_moment_by_quadrature(rng):
    """EnvironmentLights.spread against the second moment of each region's directions about its
    light, integrated over 12 × 12 sub-pixels (uniform in θ and φ, weighted by solid angle)."""
    h, w = 16, 32
    img = rng.uniform(0.0, 1.0, (h, w, 3)).astype(np.float32)
    img[3:6, 7:11] += 40.0  # a lamp a few pixels wide, so that some regions are single pixels
    env = Environment(f32(1.0, 1.0, 1.0), jnp.asarray(img), "hdr")
    _, lights = split_environment(env, 16, threshold=1.0)
    spread = np.asarray(lights.spread, np.float64)
    dirs_k = np.asarray(lights.directions, np.float64)
    # the regions and weights split_environment used (median cut of the luminance excess)
    edges = np.cos(np.pi * np.arange(h + 1) / h)
    omega = (edges[:-1] - edges[1:]) * 2 * np.pi / w
    lum = img.astype(np.float64).mean(-1)
    tau = 1.0 * float((lum * omega[:, None]).sum() / (4 * np.pi))
    weight = np.maximum(lum - tau, 0.0) * omega[:, None]
    labels = median_cut(weight, 16)
    s = 12
    sub = (np.arange(s) + 0.5) / s
    want = np.zeros((16, 3, 3))
    total = np.zeros(16)
    for i in range(h):
        theta = np.pi * (i + sub) / h
        for j in range(w):
            if weight[i, j] <= 0:
                continue
            phi = 2 * np.pi * (j + sub) / w
            t, p = np.meshgrid(theta, phi, indexing="ij")
            d = np.stack([np.sin(t) * np.cos(p), np.cos(t), -np.sin(t) * np.sin(p)], -1).reshape(-1, 3)
            a = np.sin(t).reshape(-1)  # solid angle per sub-pixel ∝ sin θ
            k = labels[i, j]
            delta = d - dirs_k[k]
            delta -= (delta @ dirs_k[k])[:, None] * dirs_k[k]
            m = (a[:, None, None] * delta[:, :, None] * delta[:, None, :]).sum(0) / a.sum()
            want[k] += weight[i, j] * m
            total[k] += weight[i, j]
    want /= np.maximum(total, 1e-300)[:, None, None]
    full = total > 0
    # single pixels split into themselves and an empty region, which carries nothing
    assert 0 < np.count_nonzero(~full) < 16 and np.all(spread[~full] == 0)
    single = np.bincount(labels[weight > 0], minlength=16) == 1
    assert np.any(single & full), "the lamp's pixels should be regions of their own"
    spread, want = spread[full], want[full]
    dirs_k = dirs_k[full]
    # traces (the mean squared angle) within 3 %, and every entry within 3 % of the largest
    np.testing.assert_allclose(
        np.trace(spread, axis1=1, axis2=2), np.trace(want, axis1=1, axis2=2), rtol=0.03
    )
    scale = np.abs(want).max((1, 2))[:, None, None]
    assert np.all(np.abs(spread - want) <= 0.03 * scale)
    # symmetric, positive semi-definite, next to nothing along the light's own direction (the
    # pixels' own widths lie in their tangent planes, not quite the light's)
    np.testing.assert_allclose(spread, np.swapaxes(spread, 1, 2), atol=1e-7)
    assert np.all(np.linalg.eigvalsh(spread) > -1e-9)
    assert np.all(
        np.abs(np.einsum("ki,kij,kj->k", dirs_k, spread, dirs_k)) < 1e-2 * np.trace(spread, axis1=1, axis2=2)
    )


def test_own_rows_cast_the_transfer_and_lamps_of_a_pose_once(monkeypatch):
    """With ``self_visibility = "rays"`` and lamps, :func:`own_rows_at_time` casts each pose's
    transfer and lamp visibility in one cast (:func:`jshadow.scene.occluder_own_casts`), neither
    apart; with "light_rays" the lamps alone."""
    import jshadow.scene as scene_module

    calls = []
    for name in ("vertex_visibility_sh", "vertex_transfer_and_lamps", "_lamp_rays"):
        real = getattr(scene_module, name)
        counted = lambda *a, _r=real, _n=name, **k: calls.append(_n) or _r(*a, **k)  # noqa: E731
        monkeypatch.setattr(scene_module, name, counted)
    for own, want in (("rays", ["vertex_transfer_and_lamps"]), ("light_rays", ["_lamp_rays"])):
        scene = _sun_scene(dataclasses.replace(SPLIT, self_visibility=own), n=2, self_shadow=True)
        scene_module.clear_pose_caches()
        calls.clear()
        rows = own_rows_at_time(scene, 0.0)
        assert calls == want and (rows[0] is None) == (own == "light_rays")
        own_rows_at_time(scene, 0.0)
        assert calls == want  # kept
