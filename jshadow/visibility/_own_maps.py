"""A mesh's visibility of itself at its own vertices from depth images and local rays.

:func:`jshadow.visibility.vertex_visibility_sh` casts every vertex's rays against every face
(V × K × F tests, about a second for the bunny's 1901 vertices), affordable once per shape but not
per frame of a deforming mesh. Here the far and the near part of the same question are answered
separately:

* far: an orthographic image of the mesh along each direction d holds, per pixel, the front-most
  depth at which the line along d *enters* the mesh (the faces with ``n_f·d < 0``;
  :func:`jshadow.visibility.lamp_images` with ``entry_only``). A ray from a point on a closed
  surface toward d is blocked iff it enters the mesh ahead, so the vertex (lifted ε along its
  normal) is shadowed when its pixel's front-most entry lies more than ``margin`` pixels ahead of
  it. This is a shadow map of the entry faces (the "second-depth" choice of Wang & Molnar 1994,
  which keeps a lit surface from shadowing itself);
* near: what lies within the margin, or closer than a pixel sideways, is lost to the pixel grid —
  contact shadows in creases, where pixel-only lookups missed a quarter of the bunny's
  self-shadowed lamp energy (1.2–1.6 % of all of it wrongly lit, 64²–128² pixels, twisted bunny
  under the studio map's 128 lamps). Those occluders are nearly always topologically near too, so
  each vertex also casts its rays exactly against the faces within ``rings`` rings of it
  (:func:`ring_faces`; 61 faces at most for the bunny with 2 rings).

Together they left 0.24 % of that lamp energy wrongly classified (2 rings, 128², margin 2 pixels;
exact rays from the lifted vertices as the measure; 1 ring 0.81 %, 3 rings 0.20 %). The margin is
a distance past which the images answer: 3 pixels of the lamps' 128² (the scene's default,
:data:`jshadow.scene.MAPS_MARGIN`) took the animated bunny's vertices from 1.73 to 1.40 % relative
RMSE against 2 pixels, where a margin past what the rings hold undoes it (6 pixels: 3.7 %; one
ring at 4 pixels: 7.9 %); 0.5 of the transfer's 64² (:data:`jshadow.scene.MAPS_TRANSFER_MARGIN`)
took the bending spot cow's under a sky from 4.67 to 3.13 % against 1.5 (the animated bunny's
unchanged, the bunny's under a sky 1.82 → 1.77 %). Both were chosen on those scenes; a margin
from each vertex's own rings would be the principled choice (tried as each vertex's rings' reach
along the direction: worse, the bending spot 3.13 → 3.82 %, since what the images then miss is
mostly occluders within a pixel sideways, not self-hits).

Where the pixels about a vertex disagree (its ray passes within a pixel of a silhouette) the images
cannot settle the far part; with ``exact_ambiguous`` those pairs are tested exactly against the
entry faces near their pixel (:mod:`._own_exact`), what the scene does for the environment's lamps
(the animated bunny's vertices 1.40 → 1.24 % relative RMSE with the map split at 4 × its mean,
what exact rays for every pair give; 0.88 % at the default 2).

The transfer's sphere grid and pixels limit it more than the margins: on the bending spot cow
under a sky (its 2930 vertices; exact rays toward the grid's directions as the measure) an 8 × 16
grid leaves 2.38 % relative RMSE with exact visibility and 3.13 % from 64² images, 12 × 24 gives
1.21 % exact, 2.41 % at 64² and 1.41 % at 128² (images of 64² pixels mistake directions within a
pixel of a silhouette: 1.9 % of each vertex's shadowed cosine against 0.8 % at 128²).
:func:`jshadow.config.auto_light_path` takes 12 × 24 at pixels about a third of the mesh's
median edge where the environment reaches the vertices through the transfer alone
(``method.self_maps_grid``, ``method.self_maps_resolution``).

Cost per pose: the K images (K·F·stamp² pixel tests, one windowed scatter per face)
and V·K·C local ray tests, against V·K·F for rays (the bunny: 64 lamps at 128², their ambiguous
pairs settled, and the transfer's 128 directions at 64² in 133 ms per frame at the shipped 160²
plane, 112 ms without settling, ``python benchmarks/bench_own_maps.py``; against 1.4 s for the
rays. The spot cow's transfer at 12 × 24 and 128²: 214 ms, 187 of it the images, which narrower
windows in powers of two took to 126–130 ms).

Limitations: closed, consistently oriented meshes (the entry faces must cover the silhouette); a contact
between parts of the mesh that are far apart on it and closer than the margin is resolved only to
the pixel; no derivative with respect to the vertices (binary visibility); concrete vertices (the
images group faces by size, :func:`jshadow.visibility.lamp_images`).
"""

from __future__ import annotations

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ..geometry import vertex_normals
from ..sh import clamped_cosine, sh_basis, sphere_grid
from ._lamps import LampImages, _front_at, image_coords, lamp_images
from ._own_exact import settle_ambiguous

__all__ = ["ring_faces", "near_any_hit", "vertex_lamp_visibility", "vertex_transfer_maps"]


def ring_faces(faces: Int[ArrayLike, "F 3"], n_vertices: int, rings: int = 2) -> np.ndarray:
    """(V, C) int32: the faces within ``rings`` rings of each vertex (ring 1: the faces around it;
    ring r + 1: every face touching a vertex of ring r), in increasing order, padded with −1 to the
    largest count C. Concrete input (a topology is fixed per mesh)."""
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[-1] != 3:
        raise ValueError(f"faces must be (F, 3), got {f.shape}")
    if int(rings) < 1:
        raise ValueError(f"rings must be >= 1, got {rings}")
    around: list[list[int]] = [[] for _ in range(int(n_vertices))]
    for i, tri in enumerate(f.tolist()):
        for a in tri:
            around[a].append(i)
    cur = [set(x) for x in around]
    for _ in range(int(rings) - 1):
        cur = [set().union(*(around[a] for a in set(f[sorted(s)].reshape(-1).tolist()))) for s in cur]
    width = max(1, max(len(s) for s in cur))
    out = np.full((len(cur), width), -1, np.int32)
    for i, s in enumerate(cur):
        out[i, : len(s)] = sorted(s)
    return out


@partial(jax.jit, static_argnames=("chunk",))
def near_any_hit(
    vertices: Float[Array, "V 3"],
    faces: Int[Array, "F 3"],
    local: Int[Array, "N C"],
    origins: Float[Array, "N 3"],
    directions: Float[Array, "D 3"],
    t_min: Float[ArrayLike, ""],
    chunk: int = 16,
) -> Bool[Array, "N D"]:
    """(N, D) whether the ray ``origins[i] + t·directions[k]`` (t > ``t_min``) hits one of the faces
    ``local[i]`` (−1: none). Factorised per (origin, face) as the fans of
    :func:`jshadow.visibility.ray_fan_any_hit` are: the three edge volumes
    ``d·((p − o) × (q − o))`` share a sign inside (inclusive, so a ray through a shared edge hits
    both faces and does not leak), and the hit distance ``(a − o)·n / (d·n)`` exceeds ``t_min``;
    four dot products per (ray, face), directions taken ``chunk`` at a time. N·D·C tests."""
    dt = vertices.dtype
    valid = local >= 0
    tri = vertices[faces[jnp.maximum(local, 0)]] - origins[:, None, None, :]  # (N, C, 3, 3), o at 0
    a, b, c = tri[:, :, 0], tri[:, :, 1], tri[:, :, 2]
    n = jnp.cross(b - a, c - a)
    rows = jnp.stack([jnp.cross(a, b), jnp.cross(b, c), jnp.cross(c, a), n], -2)  # (N, C, 4, 3)
    dist = jnp.sum(a * n, -1)  # (a − o)·n
    t_min = jnp.asarray(t_min, dt)
    d = directions.astype(dt)
    pad = (-d.shape[0]) % chunk
    d = jnp.concatenate([d, jnp.zeros((pad, 3), dt)]).reshape(-1, chunk, 3)

    def one(dc):  # (chunk, 3): the dot products as fused multiply-adds (a K = 3 matmul is slower)
        x = rows[..., 0, None] * dc[:, 0] + rows[..., 1, None] * dc[:, 1] + rows[..., 2, None] * dc[:, 2]
        e0, e1, e2, dn = x[:, :, 0], x[:, :, 1], x[:, :, 2], x[:, :, 3]  # (N, C, chunk) each
        same = ((e0 >= 0) & (e1 >= 0) & (e2 >= 0)) | ((e0 <= 0) & (e1 <= 0) & (e2 <= 0))
        ahead = (dist[:, :, None] - t_min * dn) * jnp.sign(dn) > 0  # t > t_min, dn != 0
        return jnp.any(same & ahead & valid[:, :, None], axis=1)  # (N, chunk)

    hits = jax.lax.map(one, d)  # (D / chunk, N, chunk)
    return jnp.moveaxis(hits, 0, 1).reshape(origins.shape[0], -1)[:, : directions.shape[0]]


@eqx.filter_jit
def _far_hits(images: LampImages, origins, margin):
    """(N, K) whether each origin's pixel holds an entry more than ``margin`` pixels ahead of it."""
    u, w, z, pixel = image_coords(images, origins)
    j = jnp.floor(u + 0.5).astype(jnp.int32)  # the nearest pixel centre
    i = jnp.floor(w + 0.5).astype(jnp.int32)
    return _front_at(images, i, j) > z + margin * pixel


def vertex_lamp_visibility(
    images: LampImages,
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    local: Int[ArrayLike, "V C"],
    lift: float | Float[ArrayLike, ""],
    margin: float = 2.0,
    exact_ambiguous: bool = False,
) -> Float[Array, "V K"]:
    """(V, K) visibility, 0 or 1, of a closed mesh's own vertices toward the K directions of its
    entry-face ``images`` (:func:`jshadow.visibility.lamp_images` with ``entry_only``, of these
    vertices): 0 where the vertex, lifted ``lift`` along its normal, lies more than ``margin``
    pixels behind its pixel's front-most entry, or where its ray (hits closer than ``lift``
    ignored) meets one of its ``local`` faces (:func:`ring_faces`). See the module docstring.

    With ``exact_ambiguous`` the pairs whose four pixel centres about the lifted vertex disagree
    (and whose vertex faces the lamp) are tested exactly against the entry faces near their pixel
    instead (:func:`jshadow.visibility.settle_ambiguous`: the animated bunny's lamps 1.40 → 1.24 %
    relative RMSE at its vertices with the map split at 4 × its mean, 13.9 ms alone, 20 ms more
    per frame in ``benchmarks/bench_own_maps.py``)."""
    if not images.entry_only:
        raise ValueError(
            "vertex_lamp_visibility needs images of the entry faces (lamp_images(..., entry_only=True))"
        )
    v = jax.lax.stop_gradient(jnp.asarray(vertices))
    f = jnp.asarray(faces)
    lift = jnp.asarray(lift, v.dtype)
    normals = vertex_normals(v, f)
    origins = v + lift * normals
    if exact_ambiguous:
        far = settle_ambiguous(images, v, f, origins, normals, margin)
    else:
        far = _far_hits(images, origins, margin)
    rows, owner = _split_rows(np.asarray(local))
    near = near_any_hit(v, f, jnp.asarray(rows), origins[owner], images.directions, lift)
    near = jax.ops.segment_max(near, jnp.asarray(owner), num_segments=v.shape[0], indices_are_sorted=True)
    return 1.0 - (far | near).astype(v.dtype)


def _split_rows(local: np.ndarray, width: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Each vertex's faces (a row of ``local``) cut into rows of ``width`` (−1 padded) and the
    vertex each row belongs to: the rings' counts vary (the bunny's two rings: 28 faces on average,
    61 at most), and testing the padding costs as much as a face."""
    count = (local >= 0).sum(1)
    pieces = np.maximum(-(-count // width), 1)
    owner = np.repeat(np.arange(local.shape[0], dtype=np.int32), pieces)
    first = np.concatenate([[0], np.cumsum(pieces)[:-1]])
    piece = np.arange(owner.shape[0]) - first[owner]
    cols = piece[:, None] * width + np.arange(width)[None, :]
    wide = np.concatenate([local, np.full((local.shape[0], width), -1, local.dtype)], 1)
    rows = np.take_along_axis(wide[owner], np.minimum(cols, wide.shape[1] - 1), axis=1)
    return rows.astype(np.int32), owner


def vertex_transfer_maps(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    n: int,
    local: Int[ArrayLike, "V C"],
    lift: float | Float[ArrayLike, ""],
    grid: tuple[int, int] = (8, 16),
    resolution: int = 64,
    margin: float = 2.0,
) -> Float[Array, "V n2"]:
    """(V, n²) SH of each own vertex's shadowed diffuse transfer ``V(ω)·max(0, n·ω)`` (the
    quantity :func:`jshadow.visibility.vertex_visibility_sh` casts with ``transfer=True``), as
    the clamped cosine's exact SH less the occluded part, summed over a Gauss–Legendre × uniform
    sphere ``grid`` (:func:`jshadow.sh.sphere_grid`) whose directions' visibility comes from
    entry-face images of ``resolution`` pixels and ``local`` rays (:func:`vertex_lamp_visibility`).
    A vertex that sees no occluder gets the clamped cosine exactly."""
    v = jax.lax.stop_gradient(jnp.asarray(vertices))
    f = np.asarray(faces)
    dirs, w = sphere_grid(*grid, dtype=v.dtype)
    images = lamp_images(v, f, dirs, resolution, entry_only=True)
    vis = vertex_lamp_visibility(images, v, f, local, lift, margin)
    return _transfer(v, jnp.asarray(f), vis, dirs, w, n)


@eqx.filter_jit
def _transfer(v, f, vis, dirs, w, n):
    normals = vertex_normals(v, f)
    cos = jnp.maximum(normals @ dirs.T, 0.0)
    return clamped_cosine(normals, n) - ((1.0 - vis) * cos * w) @ sh_basis(dirs, n)
