"""Exact tests of the (vertex, lamp) pairs next to a silhouette in the entry-face images.

Claims tested: on the bunny the pairs the images leave ambiguous get the exact rays' answer, so
the vertices' lamp visibility errs on far fewer cos-weighted directions than the nearest pixel's
and adds no error of its own; the answer does not depend on the tile size the faces are binned by
(tiles of one pixel put faces over many tiles, the large-face path; one tile holds them all);
a sliver thinner than a pixel that covers no pixel centre beside a ray but some further along is
found and settled;
origins outside every image leave nothing to settle; in float64 too; a scene with
``self_visibility = "maps"`` settles its own vertices' lamps so.
"""

import jax.numpy as jnp
import numpy as np
import pytest
from conftest import random_dirs
from test_own_maps import _exact_lamp_rays, bunny  # noqa: F401 (fixture)

from jshadow.geometry import vertex_normals
from jshadow.visibility import (
    lamp_images,
    ray_triangle_any_hit,
    ring_faces,
    settle_ambiguous,
    vertex_lamp_visibility,
)

LIFT = 1e-4


@pytest.fixture(scope="module")
def setup(bunny):  # noqa: F811
    v, f = bunny
    d = jnp.asarray(random_dirs(np.random.default_rng(7), (48,)), jnp.float32)
    img = lamp_images(v, f, d, 64, entry_only=True)
    exact, cos = _exact_lamp_rays(v, f, d, LIFT)
    return v, f, d, img, exact, cos


def test_ambiguous_pairs_get_the_exact_answer(setup):
    v, f, d, img, exact, cos = setup
    local = ring_faces(np.asarray(f), v.shape[0])
    old = np.asarray(vertex_lamp_visibility(img, v, f, local, LIFT, 3.0))
    new = np.asarray(vertex_lamp_visibility(img, v, f, local, LIFT, 3.0, exact_ambiguous=True))
    facing = cos > 0
    wrong_old = np.sum(np.abs(old - exact) * cos)
    wrong_new = np.sum(np.abs(new - exact) * cos)
    assert wrong_new < 0.3 * wrong_old
    # where it changed an answer it changed it to the exact rays' (entry faces against all faces:
    # the same for origins outside the mesh)
    changed = (new != old) & facing
    assert changed.sum() > 20
    assert np.mean(new[changed] == exact[changed]) > 0.98
    # no new error: a pair the nearest pixel had right stays right
    assert np.sum((new != exact) & (old == exact) & facing) <= 2
    # pairs facing away keep the nearest pixel's answer
    np.testing.assert_array_equal(new[~facing], old[~facing])


def test_the_answer_does_not_depend_on_the_tiles(setup):
    v, f, d, img, exact, cos = setup
    n = vertex_normals(v, f)
    origins = v + LIFT * n
    got = [np.asarray(settle_ambiguous(img, v, f, origins, n, 3.0, tile=t)) for t in (1, 6, 200)]
    np.testing.assert_array_equal(got[0], got[1])
    np.testing.assert_array_equal(got[1], got[2])
    assert 0.05 < got[1].mean() < 0.7


def _blade(slope: float, half: float = 0.002):
    """A closed box 1.8 long along (1, slope, 0), 2·half thick across it, over z in [0.1, 0.15]."""
    t = np.array([1.0, slope]) / np.hypot(1.0, slope)
    across = np.array([-t[1], t[0]])
    v = np.array(
        [[*(s * t + o * across), z] for s in (-0.9, 0.9) for o in (-half, half) for z in (0.1, 0.15)],
        np.float32,
    )  # corner 4·(end) + 2·(side) + (top)
    quads = [(0, 2, 6, 4), (1, 5, 7, 3), (0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6)]
    f = np.array([tri for a, b, c, d in quads for tri in ((a, b, c), (a, c, d))], np.int32)
    if np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() < 0:
        f = f[:, ::-1].copy()  # outward
    return jnp.asarray(v), jnp.asarray(f), t


def test_a_sliver_beside_the_four_centres_is_settled():
    """A blade 0.004 thick (an eighth of a pixel at 64²) 3-5 pixels above points on its midline
    covers a pixel centre only every few pixels along it: the four centres about most points see
    nothing, the wider search finds the blade and the exact test blocks them."""
    v, f, t = _blade(0.3)
    d = jnp.asarray([[0.0, 0.0, 1.0]])
    img = lamp_images(v, f, d, 64, entry_only=True)
    assert 0 < int(np.sum(np.asarray(img.covered))) < 40  # isolated pixels along the blade
    s = np.linspace(-0.7, 0.7, 300)
    origins = jnp.asarray(np.stack([s * t[0], s * t[1], np.zeros_like(s)], 1), jnp.float32)
    normals = jnp.broadcast_to(d[0], origins.shape)
    exact = np.asarray(ray_triangle_any_hit(origins, d[0], v, f))
    assert exact.all()  # every point lies under the blade
    four = np.asarray(settle_ambiguous(img, v, f, origins, normals, 3.0, reach=0))[:, 0]
    wide = np.asarray(settle_ambiguous(img, v, f, origins, normals, 3.0))[:, 0]
    assert four.mean() < 0.6  # measured 0.42
    assert wide.mean() > 0.85  # measured 0.91
    assert np.all(wide[four])  # what the four centres settled stays settled
    # a blade further ahead than the search's depth window is left to the four centres
    far = np.asarray(settle_ambiguous(img, v, f, origins - jnp.asarray([0.0, 0.0, 1.0]), normals, 3.0))
    assert far.mean() < 0.6


def test_origins_outside_the_images_leave_nothing_to_settle(setup):
    v, f, d, img, exact, cos = setup
    n = vertex_normals(v, f)
    far_away = v + 10.0 * float(img.radius) * jnp.asarray([1.0, 0.0, 0.0])
    got = np.asarray(settle_ambiguous(img, v, f, far_away, n, 3.0))
    assert got.shape == (v.shape[0], d.shape[0]) and not got.any()


@pytest.mark.usefixtures("x64")
def test_float64(bunny):  # noqa: F811
    v, f = bunny
    v = v.astype(jnp.float64)
    d = jnp.asarray(random_dirs(np.random.default_rng(3), (8,)), jnp.float64)
    img = lamp_images(v, f, d, 64, entry_only=True)
    local = ring_faces(np.asarray(f), v.shape[0])
    exact, cos = _exact_lamp_rays(v, f, d, LIFT)
    got = vertex_lamp_visibility(img, v, f, local, LIFT, 3.0, exact_ambiguous=True)
    assert got.dtype == jnp.float64
    old = np.asarray(vertex_lamp_visibility(img, v, f, local, LIFT, 3.0))
    assert np.sum(np.abs(np.asarray(got) - exact) * cos) < np.sum(np.abs(old - exact) * cos)


def test_the_scene_settles_its_own_vertices_lamps(setup):
    """``self_visibility = "maps"``: a mesh occluder's own-vertex lamp visibility is the images'
    with the ambiguous pairs settled."""
    import dataclasses

    from test_own_maps import MAPS
    from test_self_visibility import _scene

    import jshadow.scene as scene_mod
    from jshadow.entities import MeshOccluder

    v, f, d, _, _, _ = setup
    occ = MeshOccluder(v - jnp.mean(v, 0), f, jnp.asarray([0.0, 1.0, 0.0]), jnp.float32(0.8))
    scene = _scene(dataclasses.replace(MAPS, lamp_images=64), occ)
    got = np.asarray(scene_mod.occluder_own_light_visibility(occ, 0.0, scene, d, cache=False))
    t = jnp.float32(0.0)
    verts = np.asarray(scene_mod._vertices_at(occ, t))
    lift = scene_mod._concrete_lift(scene, t)
    img = lamp_images(verts, f, d, 64, entry_only=True)
    local = ring_faces(np.asarray(f), verts.shape[0])
    margin = scene_mod.MAPS_MARGIN
    want = [
        np.asarray(vertex_lamp_visibility(img, verts, f, local, lift, margin, exact_ambiguous=e))
        for e in (True, False)
    ]
    np.testing.assert_array_equal(got, want[0])
    assert np.any(want[0] != want[1])


def test_the_scene_casts_anew_when_a_constant_of_the_casts_changes(setup, monkeypatch):
    """The own-vertex caches' keys hold the module constants the "maps" casts read (the margins,
    rings, the settling's reach and ahead): a pose cast before one of them changed is cast anew."""
    import dataclasses

    from test_own_maps import MAPS
    from test_self_visibility import _scene

    import jshadow.scene as scene_mod
    from jshadow.entities import MeshOccluder
    from jshadow.visibility import _own_exact

    v, f, d, _, _, _ = setup
    occ = MeshOccluder(v - jnp.mean(v, 0), f, jnp.asarray([0.0, 1.0, 0.0]), jnp.float32(0.8))
    scene = _scene(dataclasses.replace(MAPS, lamp_images=64), occ)
    calls = []
    real = scene_mod.vertex_lamp_visibility

    def counted(*args, **kw):
        calls.append(1)
        return real(*args, **kw)

    monkeypatch.setattr(scene_mod, "vertex_lamp_visibility", counted)
    scene_mod.clear_pose_caches()
    first = np.asarray(scene_mod.occluder_own_light_visibility(occ, 0.0, scene, d))
    np.testing.assert_array_equal(
        np.asarray(scene_mod.occluder_own_light_visibility(occ, 0.0, scene, d)), first
    )
    assert len(calls) == 1  # kept
    monkeypatch.setattr(_own_exact, "REACH", 0)
    scene_mod.occluder_own_light_visibility(occ, 0.0, scene, d)
    assert len(calls) == 2  # another reach: cast anew
    monkeypatch.setattr(scene_mod, "MAPS_RINGS", 3)
    scene_mod.occluder_own_light_visibility(occ, 0.0, scene, d)
    assert len(calls) == 3
    scene_mod.clear_pose_caches()
