"""Derivatives of the occlusion-image lookups (``light_visibility = "images"``).

Claims tested: the coverage images equal the binary occlusion images in value; their vertex
derivative, weighted by ``Y J`` per pixel, is the SH derivative of the same pass, and per view and
in 4 × 4 blocks it follows central differences of 8× supersampled images (the box-filtered
coverage it is the derivative of); it vanishes for translations and scalings (the images are
invariant); a read's slope is 1/2 on the two pixels beside an edge and telescopes to the jump;
through ``render`` a mesh sphere's gradients with respect to the light's centre, its own centre
and its radius match those of the closed-form lens of the analytic sphere path; a deformation's
gradient follows central differences of an exact ray-cast visible fraction; the lookup's
gradients batch and are finite at its singular points, and a render's with own-vertex receivers
and a light on the occluder's axis; the lookups' written-out tangent equals JAX's derivative of the
same lookups read through ``_read`` for every input, alone and together, forward and reverse,
with per-origin and shared ray fans. (``jshadow fit`` through the option, and a sphere occluder's
refusal: tests/test_light_images.py.)
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import BATCH_SHAPES
from test_light_images import IMAGES, LIGHT, _icosphere_world, _light_scene
from test_scene import SMALL, f32, icosphere_occluder, plane

from jshadow.entities import Environment, MeshOccluder, Scene, SphereLight, SphereOccluder
from jshadow.geometry import Taper, Twist
from jshadow.sampling import stratified_cone_components
from jshadow.scene import light_visible_fractions, occluder_images, render, render_at
from jshadow.visibility import (
    OcclusionImages,
    bsv_and_coverage_edgescan_diff,
    bsv_mesh_edgescan_diff,
    image_ray_visibility,
    occlusion_images,
    ray_fan_any_hit,
)
from jshadow.visibility._edgescan import _basis_weights, edgescan_occlusion
from jshadow.visibility._images import _coverage_lookup, _fan_lookup, _read

GRID, DIRS, SHELL = (6, 8), (32, 32), 1.5


def _lumpy(rng, subdiv=2):
    """An icosphere with radii jittered by ±5 % and axes scaled (1, 0.8, 0.7): no two vertices
    tie for the bounding sphere (a perfect sphere's radius has no derivative there)."""
    x, f = _ico_mesh(subdiv)
    x = x * (1 + 0.05 * rng.uniform(-1, 1, (len(x), 1))) * np.array([1.0, 0.8, 0.7])
    return x * 0.6 + np.array([0.0, 1.1, 0.0]), f


def _ico_mesh(subdiv):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdiv)
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces)


_JVPS: dict = {}  # one compiled jvp per mesh topology: a new closure each call compiled it anew


def _coverage_jvp(v, f, dv):
    f = np.asarray(f)
    key = (f.shape, f.tobytes(), jnp.asarray(v).dtype)
    if key not in _JVPS:

        def run(x, dx):
            return jax.jvp(lambda w: bsv_and_coverage_edgescan_diff(w, f, 4, GRID, DIRS, SHELL), (x,), (dx,))

        _JVPS[key] = jax.jit(run)
    return _JVPS[key](jnp.asarray(v), jnp.asarray(dv))


def _cos(a, b):
    a, b = np.ravel(a), np.ravel(b)
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


@pytest.mark.usefixtures("x64")
def test_coverage_is_the_binary_image_and_its_derivative_the_sh_derivative_per_pixel(rng):
    v, f = _lumpy(rng)
    rel = v - np.array([0.0, 1.1, 0.0])
    dv = np.stack([rel[:, 1] ** 2, np.zeros(len(v)), rel[:, 0] * rel[:, 1]], -1)  # a bend
    (coeffs, cov), (dcoeffs, dcov) = _coverage_jvp(v, f, dv)
    occ, _ = edgescan_occlusion(jnp.asarray(v), f, GRID, DIRS, SHELL)
    np.testing.assert_array_equal(np.asarray(cov), np.asarray(occ).astype(np.float64))
    c2, dc2 = jax.jvp(
        lambda w: bsv_mesh_edgescan_diff(w, f, 4, GRID, DIRS, SHELL), (jnp.asarray(v),), (jnp.asarray(dv),)
    )
    np.testing.assert_array_equal(np.asarray(coeffs), np.asarray(c2))
    np.testing.assert_allclose(np.asarray(dcoeffs), np.asarray(dc2), rtol=1e-12, atol=1e-12)
    # Σ_pixels d cov · (w Y)(pixel centre) against the SH derivative's bilinear corner table:
    # the same nodes, only the table differs (measured 1.5 % here, 1.7 % for a random motion of an
    # icosphere)
    w_y = np.asarray(_basis_weights(DIRS, SHELL, 4, jnp.float64))  # (N_x·N_y, n²), column-major
    views = GRID[0] * GRID[1]
    d_o = np.swapaxes(np.asarray(dcov).reshape(views, *DIRS), -1, -2).reshape(views, -1) @ w_y
    want = -np.asarray(dcoeffs).reshape(views, -1)
    assert np.linalg.norm(d_o - want) < 0.04 * np.linalg.norm(want)


@pytest.mark.usefixtures("x64")
def test_coverage_derivative_follows_supersampled_differences(rng):
    v, f = _lumpy(rng)
    rel = v - np.array([0.0, 1.1, 0.0])

    def supersampled(x, s=8):
        o, _ = edgescan_occlusion(jnp.asarray(x), f, GRID, (DIRS[0] * s, DIRS[1] * s), SHELL)
        return np.asarray(o, np.float64).reshape(-1, DIRS[0], s, DIRS[1], s).mean((2, 4))

    def blocks(a):
        return a.reshape(-1, DIRS[0] // 4, 4, DIRS[1] // 4, 4).sum((2, 4))

    # measured on this mesh: view totals cosine 0.9984 / 0.988, 4×4 blocks 0.961 / 0.877 (stretch /
    # bend)
    for dv, view_cos, block_cos in [
        (rel * np.array([1.0, 0.0, 0.0]), 0.995, 0.93),
        (np.stack([rel[:, 1] ** 2, np.zeros(len(v)), rel[:, 0] * rel[:, 1]], -1), 0.95, 0.8),
    ]:
        _, (_, dcov) = _coverage_jvp(v, f, dv)
        ours = np.asarray(dcov).reshape(-1, *DIRS)
        h = 3e-3
        fd = (supersampled(v + h * dv) - supersampled(v - h * dv)) / (2 * h)
        assert _cos(fd.sum((1, 2)), ours.sum((1, 2))) > view_cos
        assert abs(ours.sum() / fd.sum() - 1) < 0.1 or abs(ours.sum() - fd.sum()) < 0.02 * np.abs(fd).sum()
        assert _cos(blocks(fd), blocks(ours)) > block_cos
    # translations and scalings about the centre leave the images as they are
    for dv in (np.broadcast_to([0.3, 0.2, -0.5], v.shape), rel):
        _, (_, dcov) = _coverage_jvp(v, f, np.ascontiguousarray(dv))
        assert np.abs(np.asarray(dcov)).max() < 1e-9


def test_render_at_refuses_images_without_their_bsvs():
    occ, _ = _icosphere_world(subdiv=1)
    scene = _light_scene(occ, IMAGES, n=2)
    with pytest.raises(ValueError, match="bsvs"):
        render_at(scene, 0.0, images=(None,))


def test_read_slope_is_half_beside_an_edge_and_telescopes_to_the_jump():
    img = np.zeros((2, 8, 8), np.float32)
    img[:, :, 4:6] = 1.0  # a band two pixels wide: a rise between pixels 3 and 4, a fall after 5
    flat, k = jnp.asarray(img.reshape(-1)), jnp.asarray([[1]])

    def slope(u):
        g = jax.grad(lambda uu: _read(flat, k, uu, jnp.full((1, 1), 3.5), 8, 8).sum())(jnp.full((1, 1), u))
        return float(g[0, 0])

    got = [slope(u + 0.5) for u in range(-1, 9)]  # every pixel of a row and one beyond each side
    np.testing.assert_allclose(got, [0, 0, 0, 0, 0.5, 0.5, -0.5, -0.5, 0, 0])
    assert sum(got[:6]) == 1.0 and sum(got[6:]) == -1.0  # each whole jump, over its two pixels
    assert float(_read(flat, k, jnp.full((1, 1), 4.2), jnp.full((1, 1), 3.5), 8, 8).sum()) == 1.0
    assert float(_read(flat, k, jnp.full((1, 1), 9.0), jnp.full((1, 1), 3.5), 8, 8).sum()) == 0.0


def _mesh_and_sphere_gradients(subdiv, n):
    """Gradients of a weighted plane sum through the images (mesh sphere) and through the closed
    form (analytic sphere), with respect to the light's centre, the occluder's centre and radius."""
    occ, _ = _icosphere_world(subdiv=subdiv)
    sphere = SphereOccluder(f32(0.0, 1.1, 0.0), jnp.float32(0.6))

    def loss(o, method, dl, dc, dr):
        light = SphereLight(LIGHT.center + dl, LIGHT.radius, LIGHT.radiance)
        o = dataclasses.replace(o, center=o.center + dc, radius=o.radius + dr)
        scene = dataclasses.replace(_light_scene(o, method, n=n), lights=(light,))
        e = render(scene).irradiance[:, 0]
        return jnp.sum(jnp.linspace(0.5, 1.5, e.shape[0], dtype=e.dtype) * e)

    z, z0 = jnp.zeros(3, jnp.float32), jnp.float32(0.0)
    mesh = jax.jit(jax.grad(lambda *a: loss(occ, IMAGES, *a), argnums=(0, 1, 2)))
    closed = jax.grad(lambda *a: loss(sphere, SMALL, *a), argnums=(0, 1, 2))
    return mesh(z, z, z0), closed(z, z, z0)


def test_render_gradients_match_the_closed_form_lens():
    """A mesh sphere shadowing a sphere light through the images: its gradients against the
    analytic path's exact lens of two caps (measured at 24² receivers, subdivision 3: light 1.7 %,
    occluder centre 8 % relative error)."""
    (gl, gc, gr), (wl, wc, wr) = _mesh_and_sphere_gradients(subdiv=3, n=24)
    print("light", np.asarray(gl), np.asarray(wl), "centre", np.asarray(gc), np.asarray(wc), "radius", gr, wr)
    assert _cos(gl, wl) > 0.995 and np.linalg.norm(gl - wl) < 0.05 * np.linalg.norm(wl)
    assert _cos(gc, wc) > 0.97 and np.linalg.norm(gc - wc) < 0.2 * np.linalg.norm(wc)
    assert abs(float(gr) / float(wr) - 1) < 0.2


def _tapered_scene(rng, kappa):
    """A lumpy mesh, elongated toward the light and tapered by κ along it (widening toward the
    light), over a 10² plane (float64)."""
    x, f = _ico_mesh(2)
    x = x * (1 + 0.05 * rng.uniform(-1, 1, (len(x), 1))) * np.array([0.7, 1.0, 0.6])
    unit = jnp.asarray(x / np.linalg.norm(x, axis=1).max())
    occ = MeshOccluder(
        unit, jnp.asarray(f, jnp.int32), jnp.asarray([0.0, 1.1, 0.0]), jnp.float64(0.6), Taper(kappa)
    )
    light = SphereLight(jnp.asarray([0.5, 3.2, 0.3]), jnp.float64(0.45), jnp.ones(3))
    method = dataclasses.replace(IMAGES, directions=(32, 32))
    scene = Scene(method, plane(n=10), (occ,), (light,), Environment(jnp.zeros(3)))
    return jax.tree_util.tree_map(
        lambda a: a.astype(jnp.float64) if isinstance(a, jax.Array) and a.dtype == jnp.float32 else a, scene
    )


@pytest.mark.usefixtures("x64")
def test_deformation_gradient_follows_exact_ray_differences():
    """A tapering mesh's visible fraction of a sphere light, summed over the plane: the images'
    derivative with respect to the taper against central differences of the same fraction from
    exact ray casts over 32 × 64 cap directions (its converged forward; h = 0.05 and 0.1 agree to
    1-2 %). Measured: -4.51 against -4.77 on this mesh, -4.78 against -4.52 on another jitter.
    Motions that grow the bounding sphere while the shadow shrinks (a stretch toward the light)
    make the silhouette term and the read points' motion cancel in large part, and at this plane's
    100 receivers their difference was -1.14 to 0.75 against 1.5 (BENCHMARKS.md "Gradients through the
    occlusion images")."""

    def ours(kappa):
        scene = _tapered_scene(np.random.default_rng(0), kappa)
        images = (occluder_images(scene.occluders[0], 0.0, scene),)
        pts, nrm = scene.receivers.points, scene.receivers.normals
        return jnp.sum(light_visible_fractions(scene, images, pts, nrm)[0])

    def exact(kappa):
        scene = _tapered_scene(np.random.default_rng(0), kappa)
        occ, light = scene.occluders[0], scene.lights[0]
        pts, nrm = scene.receivers.points, scene.receivers.normals
        dx, dy, dz = stratified_cone_components(light.center - pts, light.radius, (32, 64))
        dirs = jnp.stack([dx, dy, dz], -1)
        vis = 1.0 - ray_fan_any_hit(pts, dirs, occ.vertices(0.0), occ.faces).astype(jnp.float64)
        cos = jnp.maximum(jnp.einsum("nkc,nc->nk", dirs, nrm), 0.0)
        return float(jnp.sum(jnp.sum(vis * cos, -1) / jnp.sum(cos, -1)))

    k0, h = 0.3, 0.1
    g = float(jax.grad(ours)(jnp.float64(k0)))
    fd = (exact(k0 + h) - exact(k0 - h)) / (2 * h)
    print(f"taper: images {g:.4f}, exact-ray differences {fd:.4f}")
    assert abs(g - fd) < 0.12 * abs(fd)


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_coverage_lookups_batch_match_the_binary_ones_and_have_finite_gradients(shape, rng):
    occ, v = _icosphere_world(subdiv=1)
    img = occlusion_images(v, occ.faces, (6, 8), (8, 8), 1.5)
    cov = OcclusionImages(img.occluded.astype(jnp.float32), img.center, img.radius, img.shell)
    o = jnp.asarray(rng.normal(size=(*shape, 3)) * 0.3 + np.array([0.0, -1.5, 0.0]), jnp.float32)
    d = jnp.asarray(np.array([0.0, 1.1, 0.0]) + rng.normal(size=(*shape, 3)) * 0.3, jnp.float32) - o
    d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
    want = image_ray_visibility(img, o, d)
    got = image_ray_visibility(cov, o, d)
    assert got.shape == shape
    np.testing.assert_array_equal(np.asarray(got), np.asarray(want))  # the same values
    g = jax.grad(lambda a, b: jnp.sum(image_ray_visibility(cov, a, b)), argnums=(0, 1))(o, d)
    assert all(x.shape == (*shape, 3) and np.all(np.isfinite(np.asarray(x))) for x in g)


@pytest.mark.parametrize("reads", ["nearest", "bilinear"])
def test_coverage_lookup_gradient_is_finite_at_singular_points(reads):
    occ, v = _icosphere_world(subdiv=1)
    img = occlusion_images(v, occ.faces, (6, 8), (8, 8), 1.5)
    cov = OcclusionImages(img.occluded.astype(jnp.float32), img.center, img.radius, img.shell, reads=reads)
    c, r = np.asarray(img.center), float(img.radius)
    cases = [  # origin, direction
        (c + [0.0, 0.0, -3.0], [0.0, 0.0, 1.0]),  # through the centre, entering at a pole
        (c + [0.0, -3.0, 0.0], [0.0, 1.0, 0.0]),  # through the centre at the equator
        (c + [0.0, -3.0, 0.0], [1.0, 0.0, 0.0]),  # perpendicular: b = 0
        (c + [0.0, -0.9, 0.0], [0.0, 1.0, 0.0]),  # on the shell itself
        (c + [r, -3.0, 0.0], [0.0, 1.0, 0.0]),  # tangent to the bounding sphere (the cut's ramp)
        (c, [0.0, 1.0, 0.0]),  # at the centre
    ]
    for o, d in cases:
        g = jax.grad(lambda o_, d_: image_ray_visibility(cov, o_, d_), argnums=(0, 1))(
            jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32)
        )
        assert all(np.all(np.isfinite(np.asarray(x))) for x in g), (o, d)


def test_render_gradients_are_finite_for_own_vertices_and_an_axial_light():
    """Receivers inside the bounding sphere (the occluder's own vertices, ``self_shadow``) and a
    light straight above the occluder's centre: finite gradients through the images."""
    occ = icosphere_occluder((0, 1.1, 0), 0.6, Twist(jnp.float32(0.3), jnp.float32(0.3), 1), subdiv=2)
    scene = dataclasses.replace(_light_scene(occ, IMAGES, n=6), self_shadow=True)

    def loss(a, c):
        o = dataclasses.replace(occ, deform=Twist(a, a, 1))
        light = SphereLight(c, LIGHT.radius, LIGHT.radiance)
        return jnp.sum(render(dataclasses.replace(scene, occluders=(o,), lights=(light,))).irradiance)

    ga, gc = jax.jit(jax.grad(loss, argnums=(0, 1)))(jnp.float32(0.3), f32(0.0, 3.2, 0.0))
    assert np.isfinite(float(ga)) and np.all(np.isfinite(np.asarray(gc)))
    assert float(gc[1]) < 0  # raising the light darkens everything below it


def _lookup_case(rng, shared_dirs):
    """An ellipsoid's coverage images (float64) and 300 origins below it with fans of 6 rays toward
    it: the arguments of :func:`_fan_lookup` after ``shell``. ``shared_dirs``: one (1, 6) fan shared
    by every origin, as the environment lights' lookups pass it."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=2)
    v = jnp.asarray(m.vertices * [0.6, 0.4, 0.5] + [0.0, 1.1, 0.0], jnp.float64)
    img = occlusion_images(v, jnp.asarray(m.faces, jnp.int32), (6, 8), (8, 8), 1.5)
    o = jnp.asarray(rng.normal(size=(300, 3)) * 0.4 + [0.0, -1.0, 0.0])
    d = jnp.asarray([0.0, 1.0, 0.0]) + jnp.asarray(rng.normal(size=(1 if shared_dirs else 300, 6, 3)) * 0.25)
    d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
    axis = jnp.broadcast_to(d[:, 0], o.shape)
    cov = img.occluded.astype(jnp.float64)
    return (cov, img.center, img.radius, o, d[..., 0], d[..., 1], d[..., 2], axis)


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("shared_dirs", [False, True])
@pytest.mark.parametrize("bilinear", [False, True])
def test_written_out_tangent_is_the_reference_derivative(shared_dirs, bilinear, rng):
    """The coverage lookups' tangent, written out (:func:`_coverage_lookup`), against JAX's own
    derivative of the same lookups read through :func:`_read` (``reference=True``), or for bilinear
    reads (``light_images = "coverage"``) of the same bilinear lookups: equal to rounding along
    every input alone (a tangent of only the centre, only the radius, ... — the symbolic zeros of
    the others), along all together, and in reverse mode for every input."""
    args = _lookup_case(rng, shared_dirs)

    def ours(*a):
        return _coverage_lookup(1.5, bilinear, *a)

    def reference(*a):
        return _fan_lookup(1.5, *a, reference=not bilinear, bilinear=bilinear)[0]

    tangents = [jnp.asarray(rng.normal(size=np.shape(a))) for a in args]
    for i in range(len(args)):  # one input at a time: the others' tangents are symbolic zeros
        others = tuple(x for j, x in enumerate(args) if j != i)

        def along(fn, i=i, others=others):
            return lambda value: fn(*others[:i], value, *others[i:])

        v1, t1 = jax.jvp(along(ours), (args[i],), (tangents[i],))
        v0, t0 = jax.jvp(along(reference), (args[i],), (tangents[i],))
        np.testing.assert_array_equal(np.asarray(v1), np.asarray(v0))
        scale = float(jnp.max(jnp.abs(t0)))
        assert scale > 0, i
        np.testing.assert_allclose(np.asarray(t1), np.asarray(t0), atol=1e-12 * scale, err_msg=str(i))
    _, t1 = jax.jvp(ours, args, tuple(tangents))
    _, t0 = jax.jvp(reference, args, tuple(tangents))
    np.testing.assert_allclose(np.asarray(t1), np.asarray(t0), atol=1e-12 * float(jnp.max(jnp.abs(t0))))
    w = jnp.asarray(rng.normal(size=t0.shape))
    argnums = tuple(range(len(args)))
    g1 = jax.grad(lambda *a: jnp.sum(w * ours(*a)), argnums)(*args)
    g0 = jax.grad(lambda *a: jnp.sum(w * reference(*a)), argnums)(*args)
    for a, b, arg in zip(g1, g0, args, strict=True):
        assert a.shape == arg.shape
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-12 * float(jnp.max(jnp.abs(b))))
    # the images, the centre and the radius together, the rays fixed (a mesh's vertices and its
    # placement: for bilinear reads the tangent of _bilinear_placement_tangent)
    rays = args[3:]
    _, t1 = jax.jvp(lambda *p: ours(*p, *rays), args[:3], tuple(tangents[:3]))
    _, t0 = jax.jvp(lambda *p: reference(*p, *rays), args[:3], tuple(tangents[:3]))
    np.testing.assert_allclose(np.asarray(t1), np.asarray(t0), atol=1e-12 * float(jnp.max(jnp.abs(t0))))
    for argnums in ((0,), (1,), (2,), (0, 2), (0, 1, 2)):
        g1 = jax.grad(lambda *p: jnp.sum(w * ours(*p, *rays)), argnums)(*args[:3])
        g0 = jax.grad(lambda *p: jnp.sum(w * reference(*p, *rays)), argnums)(*args[:3])
        for a, b in zip(g1, g0, strict=True):
            scale = float(jnp.max(jnp.abs(b)))
            assert scale > 0, argnums
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-12 * scale, err_msg=str(argnums))
