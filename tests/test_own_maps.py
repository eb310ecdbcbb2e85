"""Own-vertex visibility from entry-face depth images and local rays (``self_visibility = "maps"``).

Claims tested: the rings of faces about each vertex; the local rays equal the watertight any-hit
test restricted to the same faces, with ``t_min``; the entry-face images cover what all faces
cover, on meshes of either orientation, and their depth is the front-most entry of the line through
each pixel centre (a convex mesh: its far side); the vertices' lamp visibility equals exact rays on
a convex mesh (facing directions) and differs from them on little of the bunny's cos-weighted
directions; the transfer of a convex mesh is the clamped cosine; on a torus over a plane "maps"
is within 3.5 % relative RMSE of the reference at its vertices, where the field is off by more than
10 %, and a finer ``self_maps_grid`` at more pixels is closer still; a Renderer of a deforming
mesh makes them every frame, a traced pose is cast by rays, an open mesh is refused; the image
groups' face counts are padded to few sizes.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import random_dirs
from test_raycast import _asset
from test_scene import SMALL
from test_self_visibility import _scene, _torus

from jshadow.geometry import Twist, icosphere, load_mesh, normalize_to_unit_sphere, vertex_normals
from jshadow.reference import reference
from jshadow.runner import Renderer
from jshadow.scene import render
from jshadow.sh import clamped_cosine
from jshadow.visibility import (
    lamp_images,
    near_any_hit,
    ray_fan_any_hit,
    ray_triangle_any_hit,
    ring_faces,
    vertex_lamp_visibility,
    vertex_transfer_maps,
)
from jshadow.visibility._lamps import _padded_count

MAPS = dataclasses.replace(SMALL, self_visibility="maps")


@pytest.fixture(scope="module")
def bunny():
    m = load_mesh(_asset("bunny_small.obj"), dtype=jnp.float32)
    return normalize_to_unit_sphere(m.vertices) * 0.7 + jnp.asarray([0.2, 1.0, -0.1]), jnp.asarray(m.faces)


def _exact_lamp_rays(v, f, d, lift):
    n = vertex_normals(v, f)
    hit = ray_fan_any_hit(v + lift * n, jnp.broadcast_to(d, (v.shape[0], *d.shape)), v, f, t_min=lift)
    return 1.0 - np.asarray(hit, np.float64), np.maximum(np.asarray(n @ d.T), 0.0)


def test_rings_hold_the_faces_around_each_vertex_and_grow():
    m = icosphere(1)
    f = np.asarray(m.faces)
    one, two = ring_faces(f, m.vertices.shape[0], 1), ring_faces(f, m.vertices.shape[0], 2)
    for vtx in range(m.vertices.shape[0]):
        around = set(np.flatnonzero((f == vtx).any(1)).tolist())
        assert set(one[vtx][one[vtx] >= 0].tolist()) == around
        touching = {i for i in range(f.shape[0]) if set(f[i]) & set(f[sorted(around)].reshape(-1))}
        assert set(two[vtx][two[vtx] >= 0].tolist()) == touching
    assert one.shape[1] <= 6 < two.shape[1]
    with pytest.raises(ValueError, match="rings"):
        ring_faces(f, m.vertices.shape[0], 0)
    with pytest.raises(ValueError, match="faces"):
        ring_faces(f[:, :2], m.vertices.shape[0])


def test_local_rays_are_the_watertight_test_on_the_same_faces(bunny, rng):
    v, f = bunny
    local = ring_faces(np.asarray(f), v.shape[0], 2)[::7]  # every 7th vertex's rings
    origins = v[::7] + jnp.asarray(rng.normal(0, 0.02, (local.shape[0], 3)), jnp.float32)
    d = jnp.asarray(random_dirs(rng, (40,)), jnp.float32)  # 40: not a multiple of the chunk
    for t_min in (0.0, 0.01):
        got = np.asarray(near_any_hit(v, f, jnp.asarray(local), origins, d, t_min))
        for i in range(0, local.shape[0], 5):
            faces = f[local[i][local[i] >= 0]]
            want = np.asarray(
                ray_triangle_any_hit(
                    jnp.broadcast_to(origins[i], d.shape), d, v, faces, t_min=t_min, t_max=jnp.inf
                )
            )
            assert np.mean(got[i] != want) <= 1 / 40  # a ray grazing a shared edge within rounding
        assert 0.02 < got.mean() < 0.9


def test_entry_images_cover_the_same_pixels_and_hold_the_far_side_of_a_convex_mesh(rng):
    m = icosphere(2)
    v = m.vertices * 0.8 + jnp.asarray([0.1, 0.5, 0.0])
    f = jnp.asarray(m.faces)
    d = jnp.asarray(random_dirs(rng, (5,)), jnp.float32)
    res = 32
    full, entry = lamp_images(v, f, d, res), lamp_images(v, f, d, res, entry_only=True)
    np.testing.assert_array_equal(np.asarray(full.covered), np.asarray(entry.covered))
    flipped = lamp_images(v, f[:, ::-1], d, res, entry_only=True)  # inward faces: the same entries
    np.testing.assert_allclose(np.asarray(flipped.front), np.asarray(entry.front), atol=1e-5)
    # the line through a pixel centre enters a convex mesh once, on its far side from the lamp
    u = -entry.radius + (jnp.arange(res, dtype=jnp.float32) + 0.5) * 2 * entry.radius / res
    for k in range(d.shape[0]):
        p = entry.center + u[None, :, None] * entry.e1[k] + u[:, None, None] * entry.e2[k]
        p = np.asarray(p.reshape(-1, 3), np.float64)
        tri = np.asarray(v[f], np.float64)
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        dk = np.asarray(d[k], np.float64) / np.linalg.norm(np.asarray(d[k]))
        depth = np.full(p.shape[0], -np.inf)
        for t, nt in zip(tri, n, strict=True):
            if nt @ dk >= 0:
                continue  # not an entry face
            s = ((t[0] - p) @ nt) / (dk @ nt)  # the line's parameter at the face's plane
            q = p + s[:, None] * dk
            inside = np.all(
                [np.cross(t[(j + 1) % 3] - t[j], q - t[j]) @ nt >= -1e-9 for j in range(3)], axis=0
            )
            depth = np.where(inside, np.maximum(depth, ((q - np.asarray(entry.center)) @ dk)), depth)
        got = np.asarray(entry.front[k]).reshape(-1)
        hit = np.isfinite(depth)
        np.testing.assert_array_equal(np.isfinite(got), hit)
        np.testing.assert_allclose(got[hit], depth[hit], atol=2e-5)
        assert 0.3 < hit.mean() < 0.9


def test_vertex_lamp_visibility_against_exact_rays(bunny, rng):
    # a convex mesh: every facing direction is free, and the images and local rays agree
    m = icosphere(2)
    v, f = m.vertices * 0.8, jnp.asarray(m.faces)
    d = jnp.asarray(random_dirs(rng, (24,)), jnp.float32)
    lift = 1e-4
    img = lamp_images(v, f, d, 64, entry_only=True)
    got = np.asarray(vertex_lamp_visibility(img, v, f, ring_faces(np.asarray(f), v.shape[0]), lift))
    exact, cos = _exact_lamp_rays(v, f, d, lift)
    facing = cos > 1e-3
    np.testing.assert_array_equal(got[facing], exact[facing])
    assert np.all(got[facing] == 1.0)
    # the bunny: little of the cos-weighted directions wrong, and far less than images alone
    v, f = bunny
    d = jnp.asarray(random_dirs(rng, (64,)), jnp.float32)
    img = lamp_images(v, f, d, 128, entry_only=True)
    local = ring_faces(np.asarray(f), v.shape[0])
    exact, cos = _exact_lamp_rays(v, f, d, lift)

    def wrong(local, margin):
        vis = np.asarray(vertex_lamp_visibility(img, v, f, local, lift, margin))
        return np.sum(np.abs(vis - exact) * cos)

    shadowed = np.sum((1 - exact) * cos)
    # measured: 4.9 % of the shadowed cos-weighted directions wrong, 26 % by the images alone
    assert wrong(local, 3.0) < 0.08 * shadowed
    assert wrong(local, 3.0) < 0.3 * wrong(local[:, :0], 0.0)
    with pytest.raises(ValueError, match="entry"):
        vertex_lamp_visibility(lamp_images(v, f, d, 16), v, f, local, lift)


def test_transfer_of_a_convex_mesh_is_the_clamped_cosine():
    m = icosphere(2)
    v, f = m.vertices * 0.8, jnp.asarray(m.faces)
    got = vertex_transfer_maps(v, f, 4, ring_faces(np.asarray(f), v.shape[0]), 1e-4)
    want = clamped_cosine(vertex_normals(v, f), 4)
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=1e-5)


def test_maps_shade_the_torus_vertices_near_the_reference():
    occ = _torus()
    ref = reference(_scene(SMALL, occ), 1024, jax.random.PRNGKey(0))
    r = np.asarray(ref.irradiance, np.float64)[9:, 0]

    def rel_rmse(method):
        e = np.asarray(render(_scene(method, occ)).irradiance, np.float64)[9:, 0]
        return np.sqrt(np.mean((e - r) ** 2) / np.mean(r**2))

    fine = dataclasses.replace(MAPS, self_maps_grid=(12, 24), self_maps_resolution=96)
    maps, finer, field = rel_rmse(MAPS), rel_rmse(fine), rel_rmse(SMALL)
    # measured: maps 2.7 % (its 8 x 16 sphere grid is the limit), field 24.8 % (rays at 12 x 48: 0.60 %)
    assert field > 0.10
    assert maps < 0.035
    assert finer < 0.8 * maps, (finer, maps)  # the method's grid and pixels are the ones used


def test_a_deforming_mesh_makes_its_maps_every_frame_and_a_traced_pose_is_cast():
    occ = _torus(Twist(0.0, 1.0, axis="y"), sections=(12, 6))
    scene = _scene(MAPS, occ, n=2, n_frames=2)
    rend = Renderer(scene)
    first, last = (np.asarray(rend.frame(f)[0].irradiance) for f in range(2))
    assert rend.self_visibility_computations == 2
    assert np.abs(first[4:] - last[4:]).max() > 1e-3
    np.testing.assert_allclose(last, np.asarray(render(scene, 1).irradiance), rtol=1e-5, atol=1e-6)
    # under jit the pose is traced: the transfer is cast by rays, the same quantity
    rays = dataclasses.replace(MAPS, self_visibility="rays")
    jitted = jax.jit(lambda s: render(s, 1).irradiance)
    np.testing.assert_allclose(
        np.asarray(jitted(scene)), np.asarray(jitted(_scene(rays, occ, 2, 2))), atol=1e-6
    )


def test_maps_refuse_an_open_mesh():
    occ = _torus(sections=(12, 6))
    opened = dataclasses.replace(occ, faces=occ.faces[1:])
    with pytest.raises(ValueError, match="closed"):
        render(_scene(MAPS, opened, n=2))


def test_padded_counts_are_few_and_close():
    counts = np.arange(1, 5000)
    padded = np.asarray([_padded_count(int(n)) for n in counts])
    assert np.all(padded >= counts) and np.all(padded <= 1.25 * counts + 1)
    # an octave of counts compiles at most five shapes: 1024, 1280, 1536, 1792 and 2048
    assert sorted(set(padded[(counts >= 1024) & (counts < 2048)].tolist())) == [1024, 1280, 1536, 1792, 2048]


def test_lamp_rays_are_exact_above_each_vertex_plane_and_zero_below(bunny):
    """The own vertices' lamp rays (``self_visibility = "rays"``, ``jshadow.scene._lamp_rays``):
    toward a lamp above the vertex's tangent plane the exact ray's answer, tested against only the
    faces above the plane for a concrete mesh and against every face under ``jit`` (the same
    values); toward one on or below it 0, which the shading weighs by zero (its exact ray, into the
    surface, is free for some)."""
    from jshadow.scene import _lamp_rays

    v, f = bunny
    d = jnp.asarray(random_dirs(np.random.default_rng(3), (40,)), jnp.float32)
    lift = 1e-3
    got = np.asarray(_lamp_rays(np.asarray(v), np.asarray(f), d, lift))
    traced = np.asarray(jax.jit(lambda x: _lamp_rays(x, f, d, lift))(v))
    exact, cos = _exact_lamp_rays(v, f, d, lift)
    up = cos > 0
    np.testing.assert_array_equal(got, traced)
    np.testing.assert_array_equal(got[up], exact[up])
    assert 0.2 < exact[up].mean() < 0.95
    assert np.all(got[~up] == 0) and exact[~up].max() == 1.0
