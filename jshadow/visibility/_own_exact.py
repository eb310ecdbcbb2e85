"""Exact answers for the (vertex, lamp) pairs a mesh's entry-face images cannot settle.

:func:`jshadow.visibility.vertex_lamp_visibility` reads whether a vertex's ray toward a lamp is
blocked from the nearest pixel of the lamp's image. That is right wherever the pixels about the
vertex agree; next to a silhouette in the image (the edge of an ear, a thin part less than a pixel
to the side of the ray) the nearest pixel centre can say either. Here a pair is *ambiguous* when
its vertex faces the lamp and either the four pixel centres around its projection disagree (the
bilinear footprint of :func:`jshadow.visibility.lamp_visibility`) or, while those four do not all
say blocked, a pixel centre up to ``reach`` pixels beyond them holds an entry ahead of the vertex
but within ``ahead`` pixels past the margin: a sliver of the mesh close ahead (an ear's rim seen
edge-on) that covers the ray's point but no pixel centre next to it, only isolated ones further
along. Only those pairs (4.8 % of the animated bunny's 1901 × 64, 2.3 % by the four centres alone)
are tested exactly: the ray from the lifted vertex
along d enters the mesh iff an entry face's projection along d covers the vertex's projection at a
depth ahead of it, a point-in-triangle test in the image plane against the entry faces whose
projected bounds overlap the pair's tile (``tile`` pixels; 42 faces on average for the bunny at
128² and 6-pixel tiles, of its 3798).

The faces are binned on the host (the pairs are found there: their number changes with the pose),
only into the tiles some pair falls in, and the test runs over one flat list of (pair, face)
entries padded to a few sizes per octave, so that a deforming mesh compiles few shapes.

Measured on the animated bunny under the studio map (64 lamps, 128² images, its last frame; exact
rays from the lifted vertices as the measure): with the map split at 4 × its mean and the four
centres alone, the lamp-weighted error per vertex 3.25 → 0.34 % RMS (largest 68.5 → 10.1 %), the
render 1.03 → 0.94 % relative RMSE (vertices 1.40 → 1.24 %, what exact rays for all pairs give),
for 20 ms more per frame at the shipped 160² plane (174.0 against 154.3 ms, the paper's 130.2 ms:
``python benchmarks/bench_own_maps.py``). With the split at 2 × its mean (the default) the four
centres left 0.245 % RMS (largest 8.6 %: ten wrong pairs, slivers all but two); the slivers
(``reach`` 2, ``ahead`` 6) take it to 0.008 % (largest 0.35 %; 0.36 → 0.17 %, largest 10.4 → 5.7 %
at its tenth frame), the vertices' largest render error 9.0 → 6.5 % of their mean, the settling
16.3 → 20.4 ms alone and the shipped frame 170.1 → 177.4 ms (``bench_own_maps.py``'s "four" and
"default"). Not used for the
transfer's sphere grid: 288 directions over the spot cow's 2930 vertices (3.5 % of the pairs
ambiguous) took its frame from 216 to 382 ms for 1.03 → 0.95 %.

Limitations: entry faces only, as the images (a vertex lifted inside the mesh, in a tight crease,
is not shadowed by the faces it would leave through); pairs whose vertex faces away from the lamp
(``n·d ≤ 0``, no diffuse light either way) keep the nearest pixel's answer; concrete input; no
derivative.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ._lamps import LampImages, _front_at, _orientation, _padded_count, image_coords

__all__ = ["settle_ambiguous"]


# pixels per side of the bins of faces: the same answers at any size; the animated bunny's 64 lamps
# settled in 13.9 ms at 6 against 16.6, 14.5 and 18.8 ms at 4, 8 and 12 (one run, 0.5 ms for the
# nearest pixels alone)
TILE = 6
# pixels beyond the 2 x 2 centres searched for a sliver, and how far past the margin its entry may
# lie (the animated bunny's last frame: reach 0, 2, 3 settled 2743, 5298, 6774 pairs in 16.3, 20.7,
# 22.3 ms for 0.245, 0.008, 0.000 % lamp-weighted RMS error; ahead 3 and 6 alike there, 6 better at
# its tenth frame: 0.29 against 0.17 %)
REACH = 2
AHEAD = 6.0


@partial(jax.jit, static_argnames=("tile", "reach"))
def _ambiguous(images: LampImages, vertices, faces, origins, normals, margin, tile: int, reach: int, ahead):
    """The nearest pixel's answer and the pairs to settle, the pairs' tiles, and the entry faces
    binned into tiles that hold a pair (see :func:`settle_ambiguous`)."""
    k, res = images.front.shape[0], images.front.shape[-1]
    u, w, z, pixel = image_coords(images, origins)  # (V, K) each
    thr = z + margin * pixel
    ju, iw = jnp.floor(u), jnp.floor(w)
    j0, i0 = ju.astype(jnp.int32), iw.astype(jnp.int32)

    def far_at(i, j):  # an entry more than the margin ahead in pixel (i, j), False outside
        return _front_at(images, i, j) > thr

    f00, f01, f10, f11 = far_at(i0, j0), far_at(i0, j0 + 1), far_at(i0 + 1, j0), far_at(i0 + 1, j0 + 1)
    right, down = u - ju >= 0.5, w - iw >= 0.5  # the nearest of the four centres
    far = jnp.where(down, jnp.where(right, f11, f10), jnp.where(right, f01, f00))
    anyf, allf = f00 | f01 | f10 | f11, f00 & f01 & f10 & f11
    sliver = jnp.zeros_like(allf)  # an entry close ahead at a centre up to `reach` beyond the 2 x 2
    near = z + (margin + ahead) * pixel
    for a in range(-reach, reach + 2):
        for b in range(-reach, reach + 2):
            if not (0 <= a <= 1 and 0 <= b <= 1):
                front = _front_at(images, i0 + a, j0 + b)
                sliver = sliver | ((front > thr) & (front <= near))
    amb = ((anyf != allf) | (sliver & ~allf)) & (normals @ images.directions.T.astype(normals.dtype) > 0)

    nt = -(-res // tile)

    def tile_of(x):  # monotone in x: a point inside a face's bounds has a tile within its tiles'
        return jnp.clip(jnp.floor((x + 0.5) / tile), 0, nt - 1).astype(jnp.int32)

    kk = jnp.arange(k, dtype=jnp.int32)[None, :]
    qbin = (kk * nt + tile_of(w)) * nt + tile_of(u)  # (V, K)
    held = jnp.zeros(k * nt * nt, bool).at[qbin.reshape(-1)].max(amb.reshape(-1))
    number = jnp.where(held, jnp.cumsum(held) - 1, -1)  # the tiles that hold a pair, numbered
    vu, vw, vz, _ = image_coords(images, vertices)  # (V, K)
    x, y = vu[faces], vw[faces]  # (F, 3, K)
    a0, a1 = tile_of(x.min(1)), tile_of(x.max(1))
    b0, b1 = tile_of(y.min(1)), tile_of(y.max(1))
    tri = vertices[faces]
    normal = jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    enters = (normal @ images.directions.T.astype(vertices.dtype)) * _orientation(vertices, faces) < 0
    small = (a1 - a0 <= 1) & (b1 - b0 <= 1)  # within 2 × 2 tiles: the face's tiles are 4 corners'
    ta = a0[..., None] + jnp.asarray([0, 1, 0, 1], jnp.int32)
    tb = b0[..., None] + jnp.asarray([0, 0, 1, 1], jnp.int32)
    corner = (ta <= a1[..., None]) & (tb <= b1[..., None]) & (enters & small)[..., None]
    at = (kk[..., None] * nt + jnp.minimum(tb, nt - 1)) * nt + jnp.minimum(ta, nt - 1)
    tiles = jnp.where(corner, number[at], -1)  # (F, K, 4): the numbered tiles of each face's corners
    proj = jnp.stack([vu, vw, vz], -1).reshape(-1, 3)  # (V·K, 3): vertex v along lamp k at v·K + k
    large = enters & ~small  # (F, K): faces over more than 2 × 2 tiles, binned on the host
    bounds = jnp.stack([a0, a1, b0, b1], -1)
    return far, amb, jnp.stack([u, w, z], -1), number[qbin], number, tiles, large, bounds, proj


@partial(jax.jit, static_argnames=("n_lamps",))
def _settle(far, amb, q, proj, faces, face, vertex, lamp, *, n_lamps):
    """``far`` with the ambiguous pairs (``amb``) answered by their entries: entry e tests face
    ``face[e]`` against the point ``q[vertex[e], lamp[e]]`` (u, w, z) in the lamp's image, a hit
    where the face covers it (inclusive edges, as the images) ahead of the point; entries with a
    vertex out of range are padding."""
    p = proj[faces[face] * n_lamps + lamp[:, None]]  # (E, 3, 3): the face's corners (u, w, z)
    qq = q[jnp.minimum(vertex, q.shape[0] - 1), lamp]  # (E, 3)
    ax, bx, cx = p[:, 0, 0], p[:, 1, 0], p[:, 2, 0]
    ay, by, cy = p[:, 0, 1], p[:, 1, 1], p[:, 2, 1]
    qx, qy = qq[:, 0], qq[:, 1]
    area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)

    def edge(x0, y0, x1, y1):  # twice the signed area of (p0, p1, q)
        return (x1 - x0) * (qy - y0) - (y1 - y0) * (qx - x0)

    wa, wb, wc = edge(bx, by, cx, cy), edge(cx, cy, ax, ay), edge(ax, ay, bx, by)
    s = jnp.sign(area)
    inside = (s * wa >= 0) & (s * wb >= 0) & (s * wc >= 0) & (s != 0)
    depth = (wa * p[:, 0, 2] + wb * p[:, 1, 2] + wc * p[:, 2, 2]) / jnp.where(area != 0, area, 1.0)
    hit = inside & (depth > qq[:, 2])
    return (far & ~amb).at[vertex, lamp].max(hit, mode="drop")


def _padded(x: np.ndarray, n: int, fill) -> np.ndarray:
    out = np.full((n, *x.shape[1:]), fill, x.dtype)
    out[: x.shape[0]] = x
    return out


def settle_ambiguous(
    images: LampImages,
    vertices: Float[Array, "V 3"],
    faces: Int[Array, "F 3"],
    origins: Float[Array, "V 3"],
    normals: Float[Array, "V 3"],
    margin: float,
    tile: int = TILE,
    reach: int | None = None,
    ahead: float | None = None,
) -> Bool[Array, "V K"]:
    """(V, K) whether each vertex's ray toward each lamp of its entry-face ``images`` is blocked
    beyond the near part: the nearest pixel's entry more than ``margin`` pixels ahead of the
    ``origins`` (the vertices lifted along their ``normals``), except where the vertex faces the
    lamp and the four pixel centres around the origin's projection disagree, or a sliver shows
    within ``reach`` pixels beyond them (an entry ahead, no more than ``ahead`` pixels past the
    margin, while the four do not all say blocked; ``reach`` 0 looks at the four alone). There
    the ray is tested exactly against the entry faces binned into its ``tile``-pixel tile: blocked
    where it enters the mesh anywhere ahead of the origin (as the rays of
    :func:`jshadow.visibility.ray_fan_any_hit` with ``t_min`` the lift find: an entry closer than
    the lift is followed by an exit beyond it, in a closed mesh). ``reach`` and ``ahead`` default
    to the module's :data:`REACH` and :data:`AHEAD` as they are at the call. See the module
    docstring."""
    reach = REACH if reach is None else reach
    ahead = AHEAD if ahead is None else ahead
    k = images.front.shape[0]
    far, amb, q, qtile, number, tiles, large, bounds, proj = _ambiguous(
        images,
        vertices,
        faces,
        origins,
        normals,
        jnp.asarray(margin, vertices.dtype),
        int(tile),
        int(reach),
        jnp.asarray(ahead, vertices.dtype),
    )
    iv, ik = np.nonzero(np.asarray(amb))
    if iv.size == 0:
        return far
    qtile = np.asarray(qtile)[iv, ik]
    n_tiles = int(qtile.max()) + 1
    tiles = np.asarray(tiles).reshape(faces.shape[0], -1)  # (F, K·4)
    eface, slot = np.nonzero(tiles >= 0)
    etile = tiles[eface, slot]
    lf, lk = np.nonzero(np.asarray(large))
    if lf.size:  # faces over more than 2 × 2 tiles: each of their tiles that holds a pair
        nt = -(-images.front.shape[-1] // int(tile))
        bd = np.asarray(bounds)[lf, lk].astype(np.int64)  # (L, 4): a0, a1, b0, b1
        nx, ny = bd[:, 1] - bd[:, 0] + 1, bd[:, 3] - bd[:, 2] + 1
        e = np.repeat(np.arange(lf.shape[0]), nx * ny)
        off = np.arange(e.shape[0]) - np.repeat(np.cumsum(nx * ny) - nx * ny, nx * ny)
        more = np.asarray(number)[(lk[e] * nt + bd[e, 2] + off // nx[e]) * nt + bd[e, 0] + off % nx[e]]
        eface = np.concatenate([eface, lf[e][more >= 0]])
        etile = np.concatenate([etile, more[more >= 0]])
    order = np.argsort(etile.astype(np.uint16) if n_tiles <= 65536 else etile, kind="stable")
    eface = eface[order]
    start = np.concatenate([[0], np.cumsum(np.bincount(etile, minlength=n_tiles))])
    # one entry per (pair, face of its tile), padded to a few sizes per octave
    count = start[qtile + 1] - start[qtile]
    pair = np.repeat(np.arange(iv.shape[0]), count)
    first = np.repeat(np.cumsum(count) - count, count)
    n = _padded_count(max(pair.shape[0], 1))
    face = _padded(eface[start[qtile][pair] + np.arange(pair.shape[0]) - first].astype(np.int32), n, 0)
    return _settle(
        far,
        amb,
        q,
        proj,
        faces,
        face,
        _padded(iv[pair].astype(np.int32), n, vertices.shape[0]),  # the padding falls outside: dropped
        _padded(ik[pair].astype(np.int32), n, 0),
        n_lamps=k,
    )
