"""Fans of rays tested against only the faces they can reach: by each origin's tangent plane and by
azimuth sector about its normal (exact: the same hits as the whole-mesh fan, for a fraction of the
work).

Two facts make a (ray, face) test skippable, each exact for a ray ``o + t·d``, t > 0:

* **Height.** With ``d·n > 0`` the ray lies above the plane through o normal to n, so it cannot
  meet a face whose three corners lie below that plane (a face is the convex hull of its corners).
* **Azimuth.** Project along n onto that plane: the ray becomes a half-line from o at the
  azimuth φ(d) of d about n, and the face becomes the triangle of its projected corners, so a hit
  needs φ(d) within the angle that triangle subtends at o. That angle is the arc spanned by the
  corners' azimuths when it is under π, and the whole circle when the projected triangle holds o
  (a face straight above the origin). This holds for any d, above or below the plane.

:func:`hemisphere_fan_any_hit` sorts each origin's fan by azimuth sector about the normal, cuts it
into groups, and tests each group against the faces that reach above the plane and into the
group's sectors: lists built per (origin, group) (chunks of neighbouring faces whose bounding ball
lies below the plane dropped first, then each remaining face measured on the device, the lists
expanded on the host), then one compiled kernel loops over every list. The azimuths (measured by
a pseudo-angle, :func:`_diamond`), the sectors and the heights are given margins
(``_ARC_MARGIN``; a corner or direction within ``_VERTICAL`` of the normal's axis covers every
sector) far wider than the rounding of the fan kernel's own tests
(:func:`jshadow.visibility.ray_fan_any_hit`), whose per-face arithmetic is evaluated unchanged,
so the hits are those of the whole-mesh fan bit for bit (tests: the bunny's fans, lamps and random
fans, random triangle soups with corner and axis cases).

Cost (`/tmp` probes unless named). The kernel takes about 45 ns per (origin, group, face) listed
with 72 rays a group (the spot cow's 3.5 M in about 160 ms): gathering the face and setting up its
edge planes, then about 0.4 ns per (ray, face) test, so a few wide groups beat many narrow ones
(16 sectors: the bunny's cast 135 → 184 ms). Making the lists takes about a third of the whole,
45 of the bunny's ~140 ms. Eight sectors gave the bunny's 12 × 48 cast 0.15 s, against 0.45 s for
the height alone and 1.04 s for every face (``benchmarks/bench_own_rays.py``; BENCHMARKS.md
"Own-vertex rays by azimuth sector", "Deforming meshes' own vertices by rays; chunked face
lists").
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._raycast import DEFAULT_FAN_FACE_CHUNK, _check_mesh, _fan_fold, _fan_table, _onb

__all__ = ["hemisphere_fan_any_hit"]

# azimuth sectors of a fan about its origin's normal, and at most as many groups of its directions
# (one bit each in a byte: at most 8)
HEMISPHERE_SECTORS = 8
# (origin, group) rows per run of the kernel: the rows are sorted by the length of their lists,
# and each run loops over as many steps of faces as its longest list needs
HEMISPHERE_RUN_ROWS = 512
# a longer list is cut into pieces of twice the mean length, and at least this long
HEMISPHERE_PIECE_MIN = 32
# (origin, face) pairs one block of the lists measures at once: bounds their memory (a few tens of
# bytes a pair) whatever the mesh size
HEMISPHERE_BLOCK_PAIRS = 1 << 20
# neighbouring faces (in the Z-order) culled together by their bounding ball before each face is
# measured: one bit each in a uint16, so 16 (fixed: _face_lists unpacks two bytes a chunk). The
# bunny keeps 34 % of its (vertex, chunk) pairs, against 19 % of its (vertex, face) pairs above
# the planes; measuring the faces took 14 against 37 ms (`/tmp` probe)
HEMISPHERE_CHUNK_FACES = 16
# pseudo-angle (a quarter turn is 1; see _diamond) added to each face's arc; a corner or direction
# whose horizontal part is under _VERTICAL of its length has an ill-conditioned azimuth and covers
# every sector
_ARC_MARGIN = 1e-3
_VERTICAL = 1e-2
# heights within this fraction of the coordinate scale count as above the plane
_HEIGHT_MARGIN = 1e-5


def _frame(normals):
    """Unit normals and a basis (e1, e2) of their planes; a zero normal gives a zero frame."""
    length = jnp.sqrt(jnp.sum(normals * normals, -1, keepdims=True))
    ok = length > 0
    unit = jnp.where(ok, normals / jnp.where(ok, length, 1.0), jnp.asarray([0.0, 0.0, 1.0], normals.dtype))
    e1, e2 = _onb(unit)
    return tuple(jnp.where(ok, x, 0.0) for x in (unit, e1, e2))


def _diamond(x, y):
    """Pseudo-angle of (x, y) in [0, 4] (4 only by rounding, the same direction as 0): increasing
    with atan2(y, x) mod 2π, a quarter turn per unit, never faster than the angle in radians, and
    D(−x, −y) = D(x, y) + 2 (mod 4), so a half turn is 2; (0, 0) gives 0. No transcendental
    functions."""
    s = jnp.abs(x) + jnp.abs(y)
    t = jnp.where(s > 0, y / jnp.where(s > 0, s, 1.0), 0.0)
    return jnp.where(x >= 0, jnp.where(y >= 0, t, 4.0 + t), 2.0 - t)


@partial(jax.jit, static_argnames=("sectors",))
def _direction_keys(d, normals, sectors):
    """(n, K) uint8 key of each direction: its azimuth sector about the normal (0 … S−1), S for a
    direction near the normal's axis (or any direction of a zero normal), S + 1 for a zero
    direction; and (n,) whether every nonzero direction lies strictly above the plane."""
    nrm, e1, e2 = _frame(normals)

    def dot(e):  # (n, K), elementwise (fused)
        return d[..., 0] * e[:, None, 0] + d[..., 1] * e[:, None, 1] + d[..., 2] * e[:, None, 2]

    x, y, z = dot(e1), dot(e2), dot(nrm)
    length2 = d[..., 0] ** 2 + d[..., 1] ** 2 + d[..., 2] ** 2
    vertical = x * x + y * y <= (_VERTICAL**2) * length2
    sector = jnp.clip(jnp.floor(_diamond(x, y) * (sectors / 4)), 0, sectors - 1).astype(jnp.uint8)
    zero = length2 == 0
    key = jnp.where(zero, jnp.uint8(sectors + 1), jnp.where(vertical, jnp.uint8(sectors), sector))
    return key, jnp.all((z > 0) | zero, -1)


def _group_masks(keys_sorted, sectors):
    """(n, G) uint8 sector masks of the groups of sorted keys (n, G, K'): the sectors from the
    group's first key to its last nonzero direction's; every sector if it holds a direction near
    the axis; none if it holds only zero directions."""
    k = keys_sorted.astype(np.int64)
    full = np.any(k == sectors, -1)
    empty = np.all(k == sectors + 1, -1)
    lo = k[..., 0]
    hi = np.max(np.where(k < sectors, k, -1), -1)
    span = np.clip(hi - lo + 1, 0, sectors)
    mask = ((np.int64(1) << span) - 1) << np.clip(lo, 0, sectors - 1)
    every = (1 << sectors) - 1
    return np.where(empty, 0, np.where(full, every, mask)).astype(np.uint8)


@jax.jit
def _chunk_keep(o, normals, keep_all, centers, radii, scale):
    """(n, NC) bool: chunk c may hold a face reaching above origin i's plane (its bounding ball
    does, by twice the height margin), or origin i ``keep_all``."""
    nrm, _, _ = _frame(normals)
    h = nrm @ centers.T - jnp.sum(o * nrm, -1)[:, None]
    return (h + radii[None, :] > -2.0 * _HEIGHT_MARGIN * scale) | keep_all[:, None]


@partial(jax.jit, static_argnames=("sectors",))
def _chunk_sectors(o, normals, keep_all, vi, ci, corners, valid, scale, *, sectors):
    """(P, L) uint8 sector masks of the L faces of chunk ``ci[p]`` at origin ``vi[p]``: the
    sectors the face's arc of azimuths crosses, widened by margins, or every sector where the arc
    is a half turn or more (the projected face holds the origin) or a corner lies near the normal's
    axis; none where every corner lies below the plane (unless the origin ``keep_all``) or the
    lane holds no face. ``corners`` (NC + 1, 9, L): corner k's component i at row 3k + i."""
    nrm, e1, e2 = _frame(normals)
    oc = o[vi]  # (P, 3)
    fr = jnp.concatenate([e1, e2, nrm], -1)[vi]  # (P, 9)
    cc = corners[ci]  # (P, 9, L)
    xs, ys, hs = [], [], []
    for k in range(3):
        rel = [cc[:, 3 * k + i, :] - oc[:, i, None] for i in range(3)]
        for out, b in ((xs, 0), (ys, 3), (hs, 6)):
            out.append(rel[0] * fr[:, b, None] + rel[1] * fr[:, b + 1, None] + rel[2] * fr[:, b + 2, None])
    vert = [
        x * x + y * y <= (_VERTICAL**2) * (x * x + y * y + h * h) for x, y, h in zip(xs, ys, hs, strict=True)
    ]
    above = (
        (hs[0] > -_HEIGHT_MARGIN * scale)
        | (hs[1] > -_HEIGHT_MARGIN * scale)
        | (hs[2] > -_HEIGHT_MARGIN * scale)
    )
    a0, a1, a2 = (jnp.where(v, 0.0, _diamond(x, y)) for v, x, y in zip(vert, xs, ys, strict=True))

    def wrap(t):  # to [−2, 2)
        return t - 4.0 * jnp.floor((t + 2.0) / 4.0)

    d1, d2 = wrap(a1 - a0), wrap(a2 - a0)
    lo = jnp.minimum(0.0, jnp.minimum(d1, d2))
    hi = jnp.maximum(0.0, jnp.maximum(d1, d2))
    wide = (hi - lo >= 2.0 - 4 * _ARC_MARGIN) | vert[0] | vert[1] | vert[2]
    s_lo = jnp.floor((a0 + lo - _ARC_MARGIN) * (sectors / 4)).astype(jnp.int32)
    s_hi = jnp.floor((a0 + hi + _ARC_MARGIN) * (sectors / 4)).astype(jnp.int32)
    span = s_hi - s_lo + 1
    every = (1 << sectors) - 1
    run = (jnp.int32(1) << jnp.clip(span, 0, sectors - 1)) - 1
    r = jnp.mod(s_lo, sectors)
    rot = ((run << r) | (run >> (sectors - r))) & every
    mask = jnp.where(wide | (span >= sectors), every, rot)
    mask = jnp.where((above | keep_all[vi][:, None]) & valid[ci], mask, 0)
    return mask.astype(jnp.uint8)


@partial(jax.jit, static_argnames=("n",))
def _group_lanes(mask, group_masks, vi, *, n):
    """(P, G) uint16: bit l set where face l of pair p's chunk reaches ray group g (its sectors
    meet the group's), and (n, G) int32 counts of them per origin. A jit of its own: fused with
    :func:`_chunk_sectors`, XLA recomputes the sector masks for every consumer."""
    g = group_masks[vi].astype(jnp.int32)  # (P, G)
    m = mask.T.astype(jnp.int32)  # (L, P)
    reach = ((m[None] & g.T[:, None, :]) != 0).astype(jnp.int32)  # (G, L, P)
    lanes = jnp.sum(jnp.left_shift(reach, jnp.arange(m.shape[0], dtype=jnp.int32)[None, :, None]), 1)
    counts = jax.ops.segment_sum(jnp.sum(reach, 1).T, vi, num_segments=n)  # padding: an empty chunk
    return lanes.T.astype(jnp.uint16), counts


@partial(jax.jit, static_argnames=("face_chunk", "groups"))
def _grouped_kernel(
    o, d, perm, inv, row, vertices, faces, flat, start, count, steps, t_min, *, face_chunk, groups
):
    """(n, K) hits of the fans ``d`` (n, K, 3) from ``o`` (n, 3), grouped: ``perm`` (n, G·K')
    orders each fan by sector (K for padding), ``inv`` (n, K) undoes it; run u's row r
    (``row[u, r]`` = origin · G + group, −1 for padding) is tested against the faces
    ``flat[start[u, r] : start + count[u, r]]`` (ids into ``faces``), C = ``face_chunk`` a step,
    ``steps[u]`` steps (traced: one compilation serves every list)."""
    n, k = d.shape[:2]
    c, g = face_chunk, groups
    kg = perm.shape[1] // g
    d_pad = jnp.concatenate([d, jnp.zeros((n, 1, 3), d.dtype)], 1)
    d_g = jnp.take_along_axis(d_pad, perm[..., None], axis=1).reshape(n * g, kg, 3)
    ok = row >= 0
    rc = jnp.maximum(row, 0)
    o_r = o[rc // g]  # (runs, R, 3)
    d_r = jnp.where(ok[..., None, None], d_g[rc], 0.0)  # (runs, R, K', 3)
    table = _fan_table(vertices, faces, t_min)  # (F, rows)
    # the edge orientations and validity (columns 9 … 12, each 0 or 1) packed in one column
    flags = table[:, 9] + 2 * table[:, 10] + 4 * table[:, 11] + 8 * table[:, 12]
    table = jnp.concatenate([table[:, :9], flags[:, None], table[:, 13:]], 1)
    table = jnp.concatenate([table, jnp.zeros((1, table.shape[1]), table.dtype)])  # row F: no face
    none = table.shape[0] - 1
    last = flat.shape[0] - 1
    j = jnp.arange(c)

    def run(args):
        o_u, d_u, st, cn, n_steps = args
        fold = _fan_fold(o_u, d_u, t_min, c)

        def body(s, hit):
            i = s * c + j[None, :]  # (1, C)
            ids = jnp.where(i < cn[:, None], flat[jnp.minimum(st[:, None] + i, last)], none)  # (R, C)
            t = table[ids]  # (R, C, packed rows)
            bits = t[..., 9].astype(jnp.int32)
            unpacked = [(bits >> b) & 1 for b in range(4)]
            return fold(
                hit, [t[..., r] for r in range(9)] + unpacked + [t[..., r] for r in range(10, t.shape[-1])]
            )[0]

        hit = lax.fori_loop(0, n_steps, body, jnp.zeros(d_u.shape[:-1], bool))
        return hit & jnp.any(d_u != 0, axis=-1)

    hit = lax.map(run, (o_r, d_r, start, count, steps))  # (runs, R, K')
    grouped = (
        jnp.zeros((n * g, kg), jnp.uint8)
        .at[jnp.where(ok, row, n * g)]
        .max(hit.astype(jnp.uint8), mode="drop")
    )
    return jnp.take_along_axis(grouped.reshape(n, g * kg), inv, axis=1) > 0


def _morton_order(points):
    """Order of points (F, 3) along a Z-order curve (10 bits an axis): neighbours in the order lie
    close in space."""
    lo, ext = points.min(0), np.ptp(points, 0).max()
    q = ((points - lo) / (ext if ext > 0 else 1.0) * 1023).astype(np.int64).clip(0, 1023)
    code = np.zeros(points.shape[0], np.int64)
    for b in range(10):
        for a in range(3):
            code |= ((q[:, a] >> b) & 1) << (3 * b + a)
    return np.argsort(code, kind="stable")


def _bucket(n: int) -> int:
    """n rounded up to 2^k or 1.5 · 2^k (few compiled shapes, under 1.5× the length)."""
    p = 1 << max(0, (n - 1).bit_length() - 1)
    return p if n <= p else (p * 3 // 2 if n <= p * 3 // 2 else 2 * p)


def _sector_groups(d, nrm, sectors):
    """The fans' directions sorted by sector on the host and cut into G groups of K': the order
    ``perm`` (n, G·K', K for padding) and its inverse ``inv`` (n, K), the groups' sector masks
    (n, G) and whether each fan lies strictly above its plane (n,). Fans whose keys all agree
    (each vertex's hemisphere grid in its own frame) are sorted once."""
    n, k = d.shape[:2]
    keys, strict = (np.asarray(x) for x in _direction_keys(d, nrm, sectors))
    shared = bool(np.all(keys == keys[:1]))
    rows = keys[:1] if shared else keys
    perm = np.argsort(rows, axis=1, kind="stable").astype(np.int32)  # radix sort of bytes
    kg = -(-k // sectors)
    g = -(-k // kg)
    pad = g * kg - k
    m = rows.shape[0]
    keys_s = np.take_along_axis(rows, perm, 1)
    keys_s = np.concatenate([keys_s, np.full((m, pad), sectors + 1, keys.dtype)], 1).reshape(m, g, kg)
    inv = np.empty_like(perm)
    np.put_along_axis(inv, perm, np.arange(k, dtype=np.int32)[None], 1)
    perm = np.concatenate([perm, np.full((m, pad), k, np.int32)], 1)
    out = perm, inv, _group_masks(keys_s, sectors)
    if shared:
        out = tuple(np.broadcast_to(x, (n, *x.shape[1:])) for x in out)
    return (*out, strict)


def _chunks(tri):
    """The faces' corners ``tri`` (F, 3, 3), in their Z-order, in chunks of L =
    :data:`HEMISPHERE_CHUNK_FACES`: corners (NC + 1, 9, L), valid lanes (NC + 1, L) (the last chunk
    empty, for padding) and each chunk's bounding ball (NC, 3) and (NC,)."""
    lanes = HEMISPHERE_CHUNK_FACES
    f = tri.shape[0]
    nc = -(-f // lanes)
    tri = np.concatenate([tri, np.zeros((nc * lanes - f + lanes, 3, 3), tri.dtype)])
    corners = np.ascontiguousarray(tri.reshape(nc + 1, lanes, 9).transpose(0, 2, 1))
    valid = (np.arange((nc + 1) * lanes) < f).reshape(nc + 1, lanes)
    pts = tri[: nc * lanes].reshape(nc, lanes * 3, 3).astype(np.float64)
    ok = np.repeat(valid[:nc], 3, axis=1)[..., None]
    centers = 0.5 * (np.where(ok, pts, np.inf).min(1) + np.where(ok, pts, -np.inf).max(1))
    radii = np.where(ok[..., 0], np.linalg.norm(pts - centers[:, None], axis=-1), 0.0).max(1)
    # a relative margin over the rounding of the balls and of the heights measured against them
    radii = radii * (1.0 + 1e-5) + 1e-6 * np.abs(pts).max(initial=0.0)
    return corners, valid, centers.astype(tri.dtype), radii.astype(tri.dtype)


def _face_lists(o, nrm, keep_all, vertices, tri, group_masks, sectors):
    """Every (origin, group) row's list of faces in one buffer (its length bucketed), with each
    row's start and count (n·G,).

    Made in two passes on the device and one on the host: chunks of
    :data:`HEMISPHERE_CHUNK_FACES` neighbouring faces whose bounding ball lies below an origin's
    plane are dropped for it (:func:`_chunk_keep`, a block of origins at a time); every kept
    (origin, chunk) pair gets its faces' sector masks (:func:`_chunk_sectors`) and, per group, a
    16-bit mask of the faces that reach it (:func:`_group_lanes`), in blocks of at most
    :data:`HEMISPHERE_BLOCK_PAIRS` (origin, face) pairs, all dispatched before the host expands
    any; the host turns each group's masks into face ids, each origin's in the faces' order."""
    n, g = group_masks.shape
    lanes = HEMISPHERE_CHUNK_FACES
    corners, valid, centers, radii = _chunks(tri)
    nc = centers.shape[0]
    scale = jnp.max(jnp.abs(vertices)) + jnp.max(jnp.abs(o))
    ka = jnp.asarray(keep_all)
    per = max(1, HEMISPHERE_BLOCK_PAIRS // max(nc, 1))
    keep = [
        _chunk_keep(o[b0 : b0 + per], nrm[b0 : b0 + per], ka[b0 : b0 + per], centers, radii, scale)
        for b0 in range(0, n, per)
    ]
    vi, ci = np.nonzero(np.concatenate([np.asarray(k) for k in keep]))  # origin-major
    vi, ci = vi.astype(np.int32), ci.astype(np.int32)
    block = max(1, HEMISPHERE_BLOCK_PAIRS // lanes)
    cj, vj, gj = jnp.asarray(corners), jnp.asarray(valid), jnp.asarray(group_masks)
    out = []
    for b0 in range(0, vi.shape[0], block):
        m = min(block, vi.shape[0] - b0)
        size = _bucket(m)  # few compiled shapes; the padding points at the empty chunk
        vb = np.zeros(size, np.int32)
        cb = np.full(size, nc, np.int32)
        vb[:m], cb[:m] = vi[b0 : b0 + m], ci[b0 : b0 + m]
        vb = jnp.asarray(vb)
        sec = _chunk_sectors(o, nrm, ka, vb, jnp.asarray(cb), cj, vj, scale, sectors=sectors)
        out.append((m, *_group_lanes(sec, gj, vb, n=n)))
    counts = np.zeros((n, g), np.int64)
    parts = []
    for m, lane_masks, cnt in out:
        counts += np.asarray(cnt)
        parts.append(np.asarray(lane_masks)[:m])
    masks = np.concatenate(parts) if parts else np.zeros((0, g), np.uint16)
    base = ci.astype(np.int32) * lanes  # the first face of each pair's chunk
    flat = np.zeros(_bucket(max(int(counts.sum()), 1)), np.int32)
    start = np.zeros((n, g), np.int64)
    offset = 0
    for j in range(g):
        mj = masks[:, j]
        nzp = np.flatnonzero(mj)
        bits = np.unpackbits(mj[nzp].view(np.uint8).reshape(-1, 2), axis=1, bitorder="little")  # (·, 16)
        e = np.flatnonzero(bits)  # pair-major, then face
        ids = base[nzp[e >> 4]] | (e & 15).astype(np.int32)
        cnt = counts[:, j]
        start[:, j] = offset + np.cumsum(cnt) - cnt
        flat[offset : offset + ids.shape[0]] = ids
        offset += ids.shape[0]
    return flat, start.reshape(-1), counts.reshape(-1)


def _runs(start, count, face_chunk):
    """The rows with faces, each list longer than twice the mean cut into pieces (their hits are
    OR-ed), sorted by length and cut into runs of :data:`HEMISPHERE_RUN_ROWS` (runs, R): row ids
    (−1 for padding, at the short end), starts, counts and each run's steps of ``face_chunk``; the
    number of runs is bucketed."""
    listed = np.flatnonzero(count)
    mean = int(count[listed].mean()) if listed.size else 0
    cap = max(HEMISPHERE_PIECE_MIN, face_chunk * -(-2 * mean // face_chunk))
    pieces = -(-count[listed] // cap)
    row = np.repeat(listed, pieces)
    piece = np.arange(row.shape[0]) - np.repeat(np.cumsum(pieces) - pieces, pieces)
    st = start[row] + piece * cap
    cnt = np.minimum(cap, count[row] - piece * cap)
    order = np.argsort(cnt, kind="stable")
    r = HEMISPHERE_RUN_ROWS
    runs = _bucket(max(1, -(-row.shape[0] // r)))
    pad = runs * r - row.shape[0]

    def shaped(x, fill):
        return np.concatenate([np.full(pad, fill, np.int64), x[order]]).reshape(runs, r).astype(np.int32)

    row, st, cnt = shaped(row, -1), shaped(st, 0), shaped(cnt, 0)
    return row, st, cnt, (-(-cnt.max(1) // face_chunk)).astype(np.int32)


def hemisphere_fan_any_hit(
    origins: Float[ArrayLike, "N 3"],
    dirs: Float[ArrayLike, "N K 3"],
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    normals: Float[ArrayLike, "N 3"],
    *,
    t_min: float | Float[ArrayLike, ""] | None = None,
) -> Bool[Array, "N K"]:
    """:func:`jshadow.visibility.ray_fan_any_hit` with each origin's fan tested against only the
    faces its rays can reach: the same (N, K) hits, bit for bit, for a fraction of the work.

    Each origin has a plane normal ``normals[i]``. A face whose corners all lie below the plane
    (beyond a rounding margin) cannot meet a ray with ``d·n > 0``, and a face meets only the rays
    whose azimuth about n lies in the arc the face subtends at the origin (module docstring). The
    fan is cut into at most :data:`HEMISPHERE_SECTORS` groups of neighbouring azimuths, each tested
    against the faces that reach above the plane and into its sectors. An origin whose fan holds a
    nonzero direction with ``d·n ≤ 0`` keeps the faces below its plane (the azimuth still culls);
    zero directions never hit and need no faces, so a fan may have the directions below its plane
    zeroed (the own vertices' lamp rays, ``jshadow.scene._lamp_rays``).

    The own-vertex casts are such fans: each vertex's hemisphere of directions about its normal,
    from the vertex lifted along it (:func:`jshadow.visibility.vertex_visibility_sh`). The bunny's
    12 × 48 transfer cast took 0.15 s against 1.04 s with every face, and its 256 lamp rays 0.14
    against 0.58 s (``benchmarks/bench_own_rays.py``; BENCHMARKS.md "Own-vertex rays by azimuth
    sector").

    How: the directions are sorted by sector about their origin's normal (on the host) and cut into
    groups; each (origin, group) gets its list of faces (the faces in a Z-order, which keeps a
    list's faces near in memory; :func:`_face_lists`: chunks of
    :data:`HEMISPHERE_CHUNK_FACES` faces whose bounding ball lies below the plane are dropped
    before any face is measured); one compiled kernel tests each row against its list,
    :data:`jshadow.visibility._raycast.DEFAULT_FAN_FACE_CHUNK` faces a step, in runs of
    :data:`HEMISPHERE_RUN_ROWS` rows sorted by length with a traced trip count. The lists' buffer
    and the number of runs are bucketed, so a mesh's poses share a few compilations.

    Memory: the faces are measured in blocks of at most :data:`HEMISPHERE_BLOCK_PAIRS`
    (origin, face) pairs, whatever the mesh size. The lists hold one
    4-byte entry per (origin, group, face) kept: about 820 per bunny vertex for its hemisphere
    fans, but up to G·F per origin for fans that reach below their planes from inside a mesh (every
    face kept in every group), where :func:`jshadow.visibility.ray_fan_any_hit`, bounded for any
    mesh, is the better call.

    Limitations: concrete inputs only (the lists' lengths are data), no derivative (boolean).

    Args:
        origins: (N, 3); dirs: (N, K, 3); normals: (N, 3), each origin's plane normal (need not be
            unit; a zero normal culls nothing); t_min: as for
            :func:`jshadow.visibility.ray_fan_any_hit`.
    """
    vertices, faces = _check_mesh(vertices, faces)
    o, d, nrm = jnp.asarray(origins), jnp.asarray(dirs), jnp.asarray(normals)
    if any(isinstance(x, jax.core.Tracer) for x in (o, d, nrm, vertices, faces, t_min)):
        raise ValueError("hemisphere_fan_any_hit needs concrete inputs: use ray_fan_any_hit under a trace")
    if (
        o.ndim != 2
        or o.shape[-1] != 3
        or d.ndim != 3
        or d.shape[::2] != (o.shape[0], 3)
        or nrm.shape != o.shape
    ):
        raise ValueError(
            f"origins and normals must be (N, 3) and dirs (N, K, 3), got {o.shape}, {nrm.shape} and {d.shape}"
        )
    dtype = jnp.result_type(o, d, vertices)
    o, d, nrm, vertices = o.astype(dtype), d.astype(dtype), nrm.astype(dtype), vertices.astype(dtype)
    n, k = d.shape[:2]
    if n == 0 or k == 0 or faces.shape[0] == 0:
        return jnp.zeros((n, k), bool)
    if t_min is not None:
        t_min = jnp.asarray(t_min, dtype)
        if t_min.shape != ():
            raise ValueError(f"t_min must be a scalar, got shape {t_min.shape}")
    s, c = HEMISPHERE_SECTORS, DEFAULT_FAN_FACE_CHUNK
    if not 1 <= s <= 8:
        raise ValueError(f"HEMISPHERE_SECTORS must be 1 to 8 (a bit each in a byte), got {s}")
    perm, inv, group_masks, strict = _sector_groups(d, nrm, s)
    f_np = np.asarray(faces)
    tri = np.asarray(vertices)[f_np]  # (F, 3, 3), on the host
    order = _morton_order(tri.mean(1))
    faces_z = jnp.asarray(f_np[order])
    flat, start, count = _face_lists(o, nrm, ~strict, vertices, tri[order], group_masks, s)
    row, st, cnt, steps = (jnp.asarray(x) for x in _runs(start, count, c))
    return _grouped_kernel(
        o,
        d,
        jnp.asarray(perm),
        jnp.asarray(inv),
        row,
        vertices,
        faces_z,
        jnp.asarray(flat),
        st,
        cnt,
        steps,
        t_min,
        face_chunk=c,
        groups=group_masks.shape[1],
    )
