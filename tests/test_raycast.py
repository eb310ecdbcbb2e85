"""Any-hit ray queries: against Embree, closed forms, watertightness on shared edges and vertices."""

from pathlib import Path

import jax
import numpy as np
import pytest
import trimesh
from conftest import BATCH_SHAPES, random_dirs
from hypothesis import given, settings
from hypothesis import strategies as st
from trimesh.ray.ray_pyembree import RayMeshIntersector

import jshadow.visibility._hemisphere as hemisphere
from jshadow.visibility import (
    hemisphere_fan_any_hit,
    ray_fan_any_hit,
    ray_sphere_any_hit,
    ray_triangle_any_hit,
)
from jshadow.visibility._own import _hemisphere_fans

_ROOT = Path(__file__).resolve().parents[1]


def _asset(name):
    p = _ROOT / "assets" / name
    return p if p.exists() else Path("/work/shared/assets") / name


@pytest.fixture(scope="module")
def bunny():
    m = trimesh.load(_asset("bunny_small.obj"), process=False)
    return m, np.asarray(m.vertices), np.asarray(m.faces, np.int32)


def _embree_any(mesh, o, d):
    ri = RayMeshIntersector(mesh)
    return ri.intersects_any(
        o.reshape(-1, 3).astype(np.float64), d.reshape(-1, 3).astype(np.float64)
    ).reshape(o.shape[:-1])


def _bunny_rays(rng, verts, n):
    c = 0.5 * (verts.min(0) + verts.max(0))
    scale = np.ptp(verts, axis=0).max()
    o = c + rng.normal(size=(n, 3)) * 0.4 * scale
    d = random_dirs(rng, (n,))
    return o, d


def test_random_rays_match_embree(bunny, rng):
    mesh, v, f = bunny
    o, d = _bunny_rays(rng, v, 3000)
    ref = _embree_any(mesh, o, d)
    assert 0.1 < ref.mean() < 0.9
    got = np.asarray(
        ray_triangle_any_hit(o.astype(np.float32), d.astype(np.float32), v.astype(np.float32), f)
    )
    np.testing.assert_array_equal(got, ref)


def test_fan_matches_embree(bunny, rng):
    mesh, v, f = bunny
    o, _ = _bunny_rays(rng, v, 12)
    d = random_dirs(rng, (12, 256))
    ref = _embree_any(mesh, np.broadcast_to(o[:, None], d.shape), d)
    assert 0.05 < ref.mean() < 0.95
    got = np.asarray(ray_fan_any_hit(o.astype(np.float32), d.astype(np.float32), v.astype(np.float32), f))
    np.testing.assert_array_equal(got, ref)


def test_t_range(bunny, rng):
    mesh, v, f = bunny
    o, d = _bunny_rays(rng, v, 400)
    ri = RayMeshIntersector(mesh)
    loc, idx, _ = ri.intersects_location(o, d, multiple_hits=False)
    first = np.full(len(o), np.inf)
    first[idx] = np.linalg.norm(loc - o[idx], axis=-1)  # d is unit
    hit = np.isfinite(first)
    assert hit.sum() > 50
    o_h, d_h, t_h = o[hit], d[hit], first[hit]
    with jax.enable_x64(True):
        before = np.asarray(ray_triangle_any_hit(o_h, d_h, v, f, t_max=0.99 * t_h))
        after = np.asarray(ray_triangle_any_hit(o_h, d_h, v, f, t_max=1.01 * t_h))
        # scaling d by 2 halves t
        scaled = np.asarray(ray_triangle_any_hit(o_h, 2.0 * d_h, v, f, t_max=0.51 * t_h))
    assert not before.any()
    assert after.all()
    assert scaled.all()


def test_fan_t_min_matches_the_watertight_test(bunny, rng):
    """A fan with ``t_min`` ignores the hits at t ≤ t_min as :func:`ray_triangle_any_hit` does (the
    same rays, scalar t_min, concrete or traced), and None is the plain t > 0 test."""
    _, v, f = bunny
    o, _ = _bunny_rays(rng, v, 24)
    d = random_dirs(rng, (24, 64))
    v32, o32, d32 = v.astype(np.float32), o.astype(np.float32), d.astype(np.float32)
    ob = np.broadcast_to(o32[:, None], d32.shape)
    plain = np.asarray(ray_fan_any_hit(o32, d32, v32, f))
    np.testing.assert_array_equal(plain, np.asarray(ray_triangle_any_hit(ob, d32, v32, f)))
    scale = float(np.ptp(v, axis=0).max())
    counts = []
    for t_min in (0.05 * scale, 0.3 * scale, 0.8 * scale):
        want = np.asarray(ray_triangle_any_hit(ob, d32, v32, f, t_min=t_min))
        np.testing.assert_array_equal(np.asarray(ray_fan_any_hit(o32, d32, v32, f, t_min=t_min)), want)
        traced = jax.jit(lambda tm: ray_fan_any_hit(o32, d32, v32, f, t_min=tm))(np.float32(t_min))
        np.testing.assert_array_equal(np.asarray(traced), want)
        counts.append(int(want.sum()))
    assert plain.sum() > counts[0] > counts[-1] > 0  # the range cuts hits off, and not all of them
    with pytest.raises(ValueError, match="scalar"):
        ray_fan_any_hit(o32, d32, v32, f, t_min=np.ones(2, np.float32))


def _closed_meshes():
    ico = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    return [ico, box]


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("mesh_i", [0, 1])
def test_watertight_vertices_and_edges(dtype, mesh_i):
    mesh = _closed_meshes()[mesh_i]
    assert mesh.is_watertight
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces, np.int32)
    e = mesh.edges_unique
    frac = np.array([0.25, 0.5, 1.0 / 3.0])
    targets = np.concatenate(
        [v, (v[e[:, 0], None] * (1 - frac[:, None]) + v[e[:, 1], None] * frac[:, None]).reshape(-1, 3)]
    )
    with jax.enable_x64(dtype == np.float64):
        vv = v.astype(dtype)
        # from the centre (inside) outwards, and from outside inwards, exactly through the targets
        o_in = np.zeros_like(targets)
        o_out = 3.0 * targets
        for o in (o_in, o_out):
            d = (targets - o).astype(dtype)
            hit = np.asarray(ray_triangle_any_hit(o.astype(dtype), d, vv, f))
            assert hit.all(), f"{(~hit).sum()} leaking rays"
            if np.all(o == 0):
                # the fan kernel is watertight on shared edges (see its docstring for vertices)
                fan = np.asarray(ray_fan_any_hit(o[:1].astype(dtype), d[None, len(v) :], vv, f))
                assert fan.all(), f"{(~fan).sum()} leaking fan rays"
        # axis-aligned rays on a lattice that contains the vertices and the face diagonals
        g = np.linspace(-0.875, 0.875, 15) if mesh_i == 1 else np.linspace(-0.5, 0.5, 11)
        x, y = np.meshgrid(g, g)
        o = np.stack([x, y, np.full_like(x, 5.0)], -1).reshape(-1, 3).astype(dtype)
        d = np.broadcast_to(np.array([0.0, 0.0, -1.0], dtype), o.shape)
        assert np.asarray(ray_triangle_any_hit(o, d, vv, f)).all()


def test_box_lattice_hits_vertices_exactly():
    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    v, f = np.asarray(box.vertices, np.float32), np.asarray(box.faces, np.int32)
    # rays from inside aimed exactly at the 8 corners and the 12 edge midpoints, along lattice lines
    o = np.zeros((3, 3), np.float32)
    d = np.array([[1, 1, 1], [1, 0, 1], [-1, 1, 0]], np.float32)
    assert np.asarray(ray_triangle_any_hit(o, d, v, f)).all()
    assert np.asarray(ray_fan_any_hit(o[0], d, v, f)).all()


def test_origin_on_surface():
    ico = trimesh.creation.icosphere(subdivisions=1, radius=1.0)
    v, f = np.asarray(ico.vertices), np.asarray(ico.faces, np.int32)
    cent = v[f].mean(1)
    nrm = np.asarray(ico.face_normals)
    ids = np.arange(len(f), dtype=np.int32)[:, None]
    with jax.enable_x64(True):
        # leaving the convex surface outwards: the own face is the only candidate, at t ≈ 0
        assert not np.asarray(ray_triangle_any_hit(cent, nrm, v, f, t_min=1e-9)).any()
        assert not np.asarray(ray_triangle_any_hit(cent, nrm, v, f, mask_faces=ids)).any()
        assert not np.asarray(ray_fan_any_hit(cent, nrm[:, None], v, f)).any()
        # inwards: the opposite side is hit, whatever the own face does
        assert np.asarray(ray_triangle_any_hit(cent, -nrm, v, f, t_min=1e-9)).all()
        assert np.asarray(ray_triangle_any_hit(cent, -nrm, v, f, mask_faces=ids)).all()
        assert np.asarray(ray_fan_any_hit(cent, -nrm[:, None], v, f)).all()
        # masking every face removes every hit; a -1 entry masks nothing
        all_ids = np.broadcast_to(np.arange(len(f), dtype=np.int32), (len(f), len(f)))
        assert not np.asarray(ray_triangle_any_hit(cent, -nrm, v, f, mask_faces=all_ids)).any()
        none = np.full((len(f), 2), -1, np.int32)
        assert np.asarray(ray_triangle_any_hit(cent, -nrm, v, f, mask_faces=none)).all()


def test_chunking_and_dtypes_agree(bunny, rng):
    mesh, v, f = bunny
    o, d = _bunny_rays(rng, v, 500)
    args32 = (o.astype(np.float32), d.astype(np.float32), v.astype(np.float32), f)
    base = np.asarray(ray_triangle_any_hit(*args32))
    for rc, fc in [(7, 1), (64, 3), (500, 16)]:
        np.testing.assert_array_equal(
            np.asarray(ray_triangle_any_hit(*args32, ray_chunk=rc, face_chunk=fc)), base
        )
    with jax.enable_x64(True):
        h64 = np.asarray(ray_triangle_any_hit(o, d, v, f))
    np.testing.assert_array_equal(h64, base)
    o_f, d_f = o[:20].astype(np.float32), np.broadcast_to(d[None, :50], (20, 50, 3)).astype(np.float32)
    fan = np.asarray(ray_fan_any_hit(o_f, d_f, v.astype(np.float32), f))
    for fc, oc in [(1, 3), (7, 20)]:
        np.testing.assert_array_equal(
            np.asarray(ray_fan_any_hit(o_f, d_f, v.astype(np.float32), f, face_chunk=fc, origin_chunk=oc)),
            fan,
        )
    np.testing.assert_array_equal(
        np.asarray(
            ray_triangle_any_hit(np.broadcast_to(o_f[:, None], d_f.shape), d_f, v.astype(np.float32), f)
        ),
        fan,
    )


@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_batch_shapes(bunny, rng, shape):
    mesh, v, f = bunny
    n = int(np.prod(shape))
    o, d = _bunny_rays(rng, v, n)
    o, d = o.reshape(*shape, 3).astype(np.float32), d.reshape(*shape, 3).astype(np.float32)
    hit = ray_triangle_any_hit(o, d, v.astype(np.float32), f)
    assert hit.shape == shape and hit.dtype == bool
    np.testing.assert_array_equal(
        np.asarray(hit).reshape(-1), _embree_any(mesh, o.reshape(-1, 3), d.reshape(-1, 3))
    )
    c = np.zeros(3, np.float32)
    hs = ray_sphere_any_hit(o, d, c, 0.5)
    assert hs.shape == shape
    fan = ray_fan_any_hit(o, np.broadcast_to(d[..., None, :], (*shape, 2, 3)), v.astype(np.float32), f)
    assert fan.shape == (*shape, 2)
    np.testing.assert_array_equal(np.asarray(fan)[..., 0], np.asarray(hit))


def test_sphere_closed_form(rng, x64):
    c = np.array([0.3, -0.2, 0.5])
    r = 0.7
    o = c + rng.normal(size=(4000, 3)) * 1.0
    d = random_dirs(rng, (4000,)) * rng.uniform(0.5, 2.0, size=(4000, 1))
    # independent reference: closest approach of the line, then the entry/exit parameters
    dd = np.sum(d * d, -1)
    tc = np.sum((c - o) * d, -1) / dd
    dist2 = np.sum((o + tc[:, None] * d - c) ** 2, -1)
    half = np.sqrt(np.maximum(r * r - dist2, 0.0) / dd)
    meets = dist2 <= r * r
    ref = meets & ((tc + half > 0) | (tc - half > 0))
    got = np.asarray(ray_sphere_any_hit(o, d, c, r))
    np.testing.assert_array_equal(got, ref)
    inside = np.sum((o - c) ** 2, -1) < r * r
    assert inside.sum() > 100 and got[inside].all()
    # t_max before the first surface crossing: miss
    first = np.where(tc - half > 0, tc - half, tc + half)
    got_short = np.asarray(ray_sphere_any_hit(o, d, c, r, t_max=np.where(meets, 0.999 * first, 1.0)))
    assert not got_short[ref].any()


def test_sphere_tangent_and_degenerate(x64):
    c = np.zeros(3)
    o = np.array([[-2.0, 1.0, 0.0], [-2.0, 1.0 + 1e-9, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.5, 0, 0]])
    d = np.array([[1.0, 0, 0], [1.0, 0, 0], [1.0, 0, 0], [0.0, 0.0, 1.0], [0.0, 0.0, 0.0]])
    got = np.asarray(ray_sphere_any_hit(o, d, c, 1.0))
    # tangent hits; just outside misses; pointing away misses; on the surface going out misses
    # (its only root is t = 0, excluded by t_min = 0); a zero direction never hits
    np.testing.assert_array_equal(got, [True, False, False, False, False])
    assert bool(ray_sphere_any_hit(o[3], -d[3], c, 1.0))  # on the surface going in: exit at t = 2


def test_zero_direction_and_validation(bunny):
    _, v, f = bunny
    v32 = v.astype(np.float32)
    assert not bool(ray_triangle_any_hit(np.zeros(3, np.float32), np.zeros(3, np.float32), v32, f))
    with pytest.raises(ValueError, match="vertices"):
        ray_triangle_any_hit(np.zeros(3), np.ones(3), v32[:, :2], f)
    with pytest.raises(ValueError, match="faces"):
        ray_triangle_any_hit(np.zeros(3, np.float32), np.ones(3, np.float32), v32, f.astype(np.float32))
    with pytest.raises(ValueError, match="face_chunk"):
        ray_triangle_any_hit(np.zeros(3, np.float32), np.ones(3, np.float32), v32, f, face_chunk=0)
    with pytest.raises(ValueError, match="dirs"):
        ray_fan_any_hit(np.zeros(3, np.float32), np.ones(3, np.float32), v32, f)
    with pytest.raises(ValueError, match="radius"):
        ray_sphere_any_hit(np.zeros(3), np.ones(3), np.zeros(3), np.ones(2))


def test_hemisphere_fans_cull_by_height_and_sector_and_agree_bit_for_bit(bunny, rng, monkeypatch):
    """:func:`hemisphere_fan_any_hit` on the own-vertex fans of a mesh (each vertex lifted along
    its normal, directions over the normal's hemisphere, as ``self_visibility = "rays"`` casts
    them) gives :func:`ray_fan_any_hit`'s hits exactly, with ``t_min`` and without, with the lists
    made in one block or in many, the fans' directions sorted once for all (a grid
    whose every cell keeps to one sector) or fan by fan, while listing under a fifth of the whole mesh's
    (ray, face) pairs; fans with lamps below their plane zeroed, and random fans reaching below
    their plane about random normals (the azimuth alone culls) agree too; a convex mesh, every face
    below every vertex's plane, lists nothing and has no hits; traced inputs and bad shapes are
    refused."""
    _, v, f = bunny
    v32 = v.astype(np.float32)
    scale = float(np.ptp(v, axis=0).max())
    lift = np.float32(1e-3 * scale)
    listed = {}
    real_kernel = hemisphere._grouped_kernel

    def counting(*args, face_chunk, groups):
        listed["rays"] = int(np.asarray(args[9]).sum()) * (args[2].shape[1] // groups)
        return real_kernel(*args, face_chunk=face_chunk, groups=groups)

    monkeypatch.setattr(hemisphere, "_grouped_kernel", counting)
    # (4, 24): every fan's directions in the same sectors (sorted once); (6, 12): cells centred on
    # the sectors' edges, sorted fan by fan
    for grid, offset, shared in (((4, 24), None, True), ((6, 12), lift, False), ((6, 12), None, False)):
        o, nrm, d, _ = _hemisphere_fans(v32, f, grid, offset)
        keys = np.asarray(hemisphere._direction_keys(d, nrm, hemisphere.HEMISPHERE_SECTORS)[0])
        assert np.all(keys == keys[:1]) == shared
        want = np.asarray(ray_fan_any_hit(o, d, v32, f, t_min=offset))
        got = np.asarray(hemisphere_fan_any_hit(o, d, v32, f, nrm, t_min=offset))
        assert 0.02 < want.mean() < 0.9
        np.testing.assert_array_equal(got, want)
        assert 0 < listed["rays"] < 0.2 * d.shape[0] * d.shape[1] * f.shape[0]
    # lists made a block at a time give the same: chunks kept for 16 origins at a time, faces
    # measured for 64 (origin, chunk) pairs at a time, the last block shorter (blocks of one pair
    # gave the same too, in 4 s more)
    monkeypatch.setattr(hemisphere, "HEMISPHERE_BLOCK_PAIRS", 16 * 64)
    blocks = []
    real_sectors = hemisphere._chunk_sectors
    monkeypatch.setattr(
        hemisphere, "_chunk_sectors", lambda *a, **k: blocks.append(a[3].shape[0]) or real_sectors(*a, **k)
    )
    np.testing.assert_array_equal(np.asarray(hemisphere_fan_any_hit(o, d, v32, f, nrm)), want)
    assert len(blocks) > 2 and blocks[0] == 64 and blocks[-1] <= 64
    monkeypatch.setattr(hemisphere, "_chunk_sectors", real_sectors)
    monkeypatch.setattr(hemisphere, "HEMISPHERE_BLOCK_PAIRS", 1 << 20)
    # lamps (not a multiple of the sectors) with those below each vertex's plane zeroed
    lamps = random_dirs(rng, (45,), np.float32)
    up = np.asarray(nrm) @ lamps.T > 0
    fans = np.where(up[..., None], lamps[None], 0).astype(np.float32)
    np.testing.assert_array_equal(
        np.asarray(hemisphere_fan_any_hit(o, fans, v32, f, nrm, t_min=lift)),
        np.asarray(ray_fan_any_hit(o, fans, v32, f, t_min=lift)),
    )
    # random fans about random normals, from points near the surface
    idx = rng.choice(v.shape[0], 37, replace=False)
    o_r = (v32[idx] + 0.02 * scale * rng.normal(size=(37, 3))).astype(np.float32)
    d_rand = random_dirs(rng, (37, 32), np.float32)
    n_rand = random_dirs(rng, (37,), np.float32)
    want_r = np.asarray(ray_fan_any_hit(o_r, d_rand, v32, f, t_min=lift))
    assert 0.1 < want_r.mean() < 0.95
    np.testing.assert_array_equal(
        np.asarray(hemisphere_fan_any_hit(o_r, d_rand, v32, f, n_rand, t_min=lift)), want_r
    )
    ico = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    vi, fi = np.asarray(ico.vertices, np.float32), np.asarray(ico.faces, np.int32)
    oi, ni, di, _ = _hemisphere_fans(vi, fi, (6, 12), np.float32(1e-3))
    assert not np.asarray(hemisphere_fan_any_hit(oi, di, vi, fi, ni, t_min=np.float32(1e-3))).any()
    assert listed["rays"] == 0
    with pytest.raises(ValueError, match="concrete"):
        jax.jit(lambda x: hemisphere_fan_any_hit(x, d, v32, f, nrm))(o)
    with pytest.raises(ValueError, match="origins and normals"):
        hemisphere_fan_any_hit(o, d[:, 0], v32, f, nrm)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), special=st.sampled_from(["none", "zero", "axis", "corner", "flat"]))
def test_hemisphere_fans_match_the_whole_mesh_fan_on_random_soups(seed, special):
    """Random triangle soups, origins, normals and fans (half of them above their planes), with
    hard cases: zero directions and a zero normal, directions on and next to the normal's axis, an
    origin on a corner, an origin in a face's plane with that plane for its own: the hits of
    :func:`ray_fan_any_hit`, bit for bit (fixed shapes: few compilations serve every example)."""
    r = np.random.default_rng(seed)
    v = r.normal(size=(64, 3)).astype(np.float32)
    f = r.integers(0, 64, size=(64, 3)).astype(np.int32)
    o = (0.5 * r.normal(size=(20, 3))).astype(np.float32)
    nrm = random_dirs(r, (20,), np.float32)
    d = random_dirs(r, (20, 24), np.float32)
    below = np.einsum("nkj,nj->nk", d[:10], nrm[:10]) < 0
    d[:10] = np.where(below[..., None], -d[:10], d[:10])
    if special == "zero":
        d[:, ::3] = 0
        nrm[3] = 0
    elif special == "axis":
        d[:, 0] = nrm
        d[:, 1] = nrm + 1e-4 * r.normal(size=(20, 3)).astype(np.float32)
    elif special == "corner":
        o[:8] = v[f[:8, 0]]
    elif special == "flat":
        nrm[:8] = np.cross(v[f[:8, 1]] - v[f[:8, 0]], v[f[:8, 2]] - v[f[:8, 0]])
        o[:8] = v[f[:8, 0]] + 0.3 * (v[f[:8, 1]] - v[f[:8, 0]])
    want = np.asarray(ray_fan_any_hit(o, d, v, f))
    assert want.any()
    np.testing.assert_array_equal(np.asarray(hemisphere_fan_any_hit(o, d, v, f, nrm)), want)
