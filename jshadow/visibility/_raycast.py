"""Any-hit ray queries against triangle meshes and spheres (brute force, memory bounded).

These are the exact visibility tests behind the base sphere visibility (BSV, deformable-shadow-fields
paper Sec. 4.1; Zhou et al. 2005 "Precomputed shadow fields" Sec. 4) and the Monte Carlo reference
renderer. No acceleration structure is built: every ray is tested against every triangle, but
never as a rays × triangles array. Triangles are visited in chunks of ``face_chunk`` by
``lax.scan`` (the per-chunk tests are OR-folded explicitly, which XLA:CPU runs much faster than a
``jnp.any`` over a chunk axis) and rays in chunks of ``ray_chunk`` by ``lax.map``; peak memory is
O(ray_chunk · face_chunk) plus the inputs and outputs, whatever the mesh size.

Watertightness
--------------
:func:`ray_triangle_any_hit` follows the idea of Woop, Benthin and Wald (2013, "Watertight
ray/triangle intersection"): each vertex is first projected onto the plane orthogonal to the ray
(coordinates relative to the origin in a per-ray orthonormal basis), and the inside test uses 2D
edge functions of these projected vertices. Two triangles that share a vertex see bit-identical
projected coordinates, and every edge function is evaluated once in a canonical orientation (from
the lower to the higher vertex index) and negated for the triangle that traverses the edge the
other way, so the two triangles of a shared edge get exactly opposite values. Edge values of zero
count as inside for both. A ray through a shared edge or vertex of a closed mesh therefore hits at
least one of the adjacent triangles: no leaks, independent of FMA contraction by the compiler
(XLA:CPU does contract ``a·b − c·d``, so ``a·b − b·a`` is not always 0; zero-area faces are
therefore flagged up front and never hit).
(The original algorithm re-evaluates exactly-zero edge functions in double precision; here a zero
simply counts as inside, which can only add hits on the shared boundary, never lose them.)

:func:`ray_fan_any_hit` is the factorised variant for fans of rays that share an origin (the BSV
brute force, notes/bsv-speed.md §(a)): per (origin, triangle) it precomputes the three edge-plane
normals ``m_k = (a_k − o) × (a_{k+1} − o)`` (canonical orientation again), and a direction d hits iff
``d · m_k ≥ 0`` for all k once the normals are oriented by the sign of the tetrahedron volume.
That is 9 multiply-adds per (ray, triangle) and needs no distance test (the hit is always at t > 0).

Degenerate (zero-area) triangles never hit. Rays with a zero direction never hit.
"""

from __future__ import annotations

import math
from functools import partial

import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._numerics import eps, safe_sqrt

__all__ = ["ray_triangle_any_hit", "ray_fan_any_hit", "ray_sphere_any_hit"]

# Chunk sizes measured on the 2-core CPU (jax 0.10.2, bunny_small, loaded machine, min of 5):
# general rays, 32768 rays: (ray_chunk, face_chunk) = (8192, 4) 44 ms, (8192, 8) 48 ms,
# (2048, 4) 58 ms, (32768, 4) 46 ms, (8192, 2) 49 ms; BSV fan, 240 × 32² rays: face_chunk 2 / 4 / 8 /
# 16 at origin_chunk 256: 68 / 67 / 67 / 76 ms, origin_chunk 60 / 120 / 256: 76 / 69 / 67 ms.
DEFAULT_RAY_CHUNK = 8192
DEFAULT_FACE_CHUNK = 4
DEFAULT_FAN_FACE_CHUNK = 4
DEFAULT_FAN_ORIGIN_CHUNK = 256


def _check_mesh(vertices, faces):
    vertices = jnp.asarray(vertices)
    faces = jnp.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[-1] != 3:
        raise ValueError(f"vertices must have shape (V, 3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[-1] != 3:
        raise ValueError(f"faces must have shape (F, 3), got {faces.shape}")
    if not jnp.issubdtype(faces.dtype, jnp.integer):
        raise ValueError(f"faces must be an integer array, got dtype {faces.dtype}")
    if not jnp.issubdtype(vertices.dtype, jnp.floating):
        raise ValueError(f"vertices must be a float array, got dtype {vertices.dtype}")
    return vertices, faces.astype(jnp.int32)


def _check_chunk(name, value):
    if not (isinstance(value, int) and value >= 1):
        raise ValueError(f"{name} must be a positive int, got {value!r}")


def _onb(d):
    """Branchless orthonormal basis (e1, e2) orthogonal to the unit vector d (Duff et al. 2017)."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    s = jnp.where(z >= 0, 1.0, -1.0).astype(d.dtype)
    a = -1.0 / (s + z)
    b = x * y * a
    e1 = jnp.stack([1.0 + s * x * x * a, s * b, -s * x], axis=-1)
    e2 = jnp.stack([b, s + y * y * a, -y], axis=-1)
    return e1, e2


def _pad_faces(vertices, faces, chunk):
    """Faces padded to a multiple of ``chunk``, their ids (−2 for padding) and a validity flag.

    Padding and zero-area faces (repeated indices or collinear corners) are invalid and never hit:
    their edge functions are rounding noise (the compiler may contract ``a·b − c·d`` into an FMA,
    so even ``a·b − b·a`` need not be 0).
    """
    f = faces.shape[0]
    f_pad = max(chunk, -(-f // chunk) * chunk)
    faces_p = jnp.zeros((f_pad, 3), jnp.int32).at[:f].set(faces)
    ids = jnp.full((f_pad,), -2, jnp.int32).at[:f].set(jnp.arange(f, dtype=jnp.int32))
    tri = vertices[faces_p]
    area2 = jnp.sum(jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]) ** 2, axis=-1)
    distinct = (
        (faces_p[:, 0] != faces_p[:, 1]) & (faces_p[:, 1] != faces_p[:, 2]) & (faces_p[:, 2] != faces_p[:, 0])
    )
    valid = (ids >= 0) & distinct & (area2 > 0)
    return faces_p, ids, valid


def _edge_sorted(vid):
    """For the edges (k, k+1) of (..., 3) vertex ids: whether the edge runs high → low index."""
    return vid > jnp.roll(vid, -1, axis=-1)


# --------------------------------------------------------------------------------------------
# General rays
# --------------------------------------------------------------------------------------------


@partial(jax.jit, static_argnames=("ray_chunk", "face_chunk", "has_mask"))
def _any_hit_kernel(o, d, tmin, tmax, mask, vertices, faces, *, ray_chunk, face_chunk, has_mask):
    n = o.shape[0]
    dtype = o.dtype
    faces_p, ids, valid = _pad_faces(vertices, faces, face_chunk)
    # rotate each face (orientation kept) so that corner 0 holds its lowest vertex index: then edge
    # 0 -> 1 is already canonical, edge 2 -> 0 is always reversed, and only edge 1 -> 2 needs a test
    first = jnp.argmin(faces_p, axis=1)
    faces_p = jnp.take_along_axis(faces_p, (first[:, None] + jnp.arange(3)) % 3, axis=1)
    n_chunks = faces_p.shape[0] // face_chunk
    tri = vertices[faces_p].reshape(n_chunks, face_chunk, 3, 3)  # (chunks, C, corner, xyz)
    swap = (faces_p[:, 1] > faces_p[:, 2]).reshape(n_chunks, face_chunk)  # edge 1 -> 2 runs high -> low
    fid = ids.reshape(n_chunks, face_chunk)
    valid = valid.reshape(n_chunks, face_chunk)

    dn2 = jnp.sum(d * d, axis=-1)
    ok = dn2 > 0
    dlen = jnp.sqrt(jnp.where(ok, dn2, 1.0))
    dn = jnp.where(ok[:, None], d, jnp.asarray([0.0, 0.0, 1.0], dtype)) / dlen[:, None]
    e1, e2 = _onb(dn)
    lo = tmin * dlen  # distance bounds along the unit direction
    hi = tmax * dlen

    r = min(ray_chunk, n)
    n_pad = -(-n // r) * r

    def pad(x, fill):
        return jnp.concatenate([x, jnp.full((n_pad - n, *x.shape[1:]), fill, x.dtype)], axis=0).reshape(
            n_pad // r, r, *x.shape[1:]
        )

    rays = (pad(o, 0.0), pad(e1, 0.0), pad(e2, 0.0), pad(dn, 0.0), pad(lo, 0.0), pad(hi, 0.0))
    rays = (*rays, pad(ok, False), pad(mask, -1))

    def per_chunk(args):
        o_c, e1_c, e2_c, dn_c, lo_c, hi_c, ok_c, mask_c = args
        # structure of arrays: (r,) per component, so that no size-3 reductions reach the fusions
        oc = [o_c[:, i] for i in range(3)]
        basis = [[b[:, i] for i in range(3)] for b in (e1_c, e2_c, dn_c)]

        def proj(p, b):
            return p[0] * b[0] + p[1] * b[1] + p[2] * b[2]

        def body(hit, xs):
            tri_s, swap_s, fid_s, valid_s = xs
            for c in range(face_chunk):
                # projected corners: (x, y) in the plane orthogonal to the ray, z along it
                px, py, pz = [], [], []
                for k in range(3):
                    p = [tri_s[c, k, i] - oc[i] for i in range(3)]  # (r,) each
                    px.append(proj(p, basis[0]))
                    py.append(proj(p, basis[1]))
                    pz.append(proj(p, basis[2]))
                # 2D edge functions, each evaluated in canonical orientation (low -> high index)
                s = swap_s[c]
                ax, ay = jnp.where(s, px[2], px[1]), jnp.where(s, py[2], py[1])
                bx, by = jnp.where(s, px[1], px[2]), jnp.where(s, py[1], py[2])
                e12 = ax * by - ay * bx
                edge = [
                    px[0] * py[1] - py[0] * px[1],  # corner 0 -> 1
                    jnp.where(s, -e12, e12),  # corner 1 -> 2
                    -(px[0] * py[2] - py[0] * px[2]),  # corner 2 -> 0
                ]
                det = edge[0] + edge[1] + edge[2]
                # edge k is opposite corner k+2: barycentric weight of that corner
                tz = edge[0] * pz[2] + edge[1] * pz[0] + edge[2] * pz[1]
                sgn = jnp.where(det < 0, -1.0, 1.0).astype(dtype)
                adet = jnp.abs(det)
                inside = ((edge[0] >= 0) & (edge[1] >= 0) & (edge[2] >= 0)) | (
                    (edge[0] <= 0) & (edge[1] <= 0) & (edge[2] <= 0)
                )
                h = inside & valid_s[c] & (adet > 0) & (tz * sgn > lo_c * adet) & (tz * sgn < hi_c * adet)
                for j in range(mask_c.shape[-1] if has_mask else 0):
                    h = h & (mask_c[:, j] != fid_s[c])
                hit = hit | h
            return hit, None

        hit0 = jnp.zeros(o_c.shape[0], bool)
        hit, _ = lax.scan(body, hit0, (tri, swap, fid, valid))
        return hit & ok_c

    out = lax.map(per_chunk, rays)
    return out.reshape(n_pad)[:n]


def ray_triangle_any_hit(
    origins: Float[ArrayLike, "... 3"],
    dirs: Float[ArrayLike, "... 3"],
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    t_min: float | Float[ArrayLike, "..."] = 0.0,
    t_max: float | Float[ArrayLike, "..."] = math.inf,
    mask_faces: Int[ArrayLike, "... K"] | None = None,
    *,
    ray_chunk: int = DEFAULT_RAY_CHUNK,
    face_chunk: int = DEFAULT_FACE_CHUNK,
) -> Bool[Array, "..."]:
    """Whether each ray ``o + t·d`` hits any triangle with ``t_min < t < t_max``.

    Args:
        origins, dirs: (..., 3), broadcast against each other; ``dirs`` need not be unit (t is in
            units of |d|); a zero direction never hits.
        vertices: (V, 3) float; faces: (F, 3) int vertex indices.
        t_min, t_max: scalars or arrays broadcastable to the batch shape ``...``.
        mask_faces: optional (..., K) int face ids that each ray ignores (negative entries are
            unused), e.g. the two faces of a silhouette edge a ray starts on.
        ray_chunk, face_chunk: chunk sizes (static): rays per ``lax.map`` step, triangles per
            ``lax.scan`` step. Peak temporary memory is O(ray_chunk · face_chunk).

    Returns:
        bool (...).

    Watertight for closed meshes (see the module docstring): a ray through a shared edge or vertex
    is not lost between the adjacent triangles. Hits lying exactly on a triangle's boundary count.
    An origin lying on a triangle has ``t ≈ 0`` there up to rounding; pass ``t_min > 0`` (a few
    ``eps(dtype)`` times the scene scale) or ``mask_faces`` to exclude the origin's own face.
    Not differentiable (the output is boolean).
    """
    vertices, faces = _check_mesh(vertices, faces)
    _check_chunk("ray_chunk", ray_chunk)
    _check_chunk("face_chunk", face_chunk)
    origins = jnp.asarray(origins)
    dirs = jnp.asarray(dirs)
    if origins.shape[-1:] != (3,) or dirs.shape[-1:] != (3,):
        raise ValueError(f"origins and dirs must end in an axis of 3, got {origins.shape} and {dirs.shape}")
    dtype = jnp.result_type(origins, dirs, vertices)
    batch = jnp.broadcast_shapes(origins.shape[:-1], dirs.shape[:-1])
    n = math.prod(batch)
    o = jnp.broadcast_to(origins, (*batch, 3)).astype(dtype).reshape(n, 3)
    d = jnp.broadcast_to(dirs, (*batch, 3)).astype(dtype).reshape(n, 3)
    tmin = jnp.broadcast_to(jnp.asarray(t_min, dtype), batch).reshape(n)
    tmax = jnp.broadcast_to(jnp.asarray(t_max, dtype), batch).reshape(n)
    if mask_faces is None:
        mask = jnp.full((n, 1), -1, jnp.int32)
    else:
        mask_faces = jnp.asarray(mask_faces)
        if mask_faces.ndim < 1 or not jnp.issubdtype(mask_faces.dtype, jnp.integer):
            raise ValueError(
                "mask_faces must be an int array (..., K) of face ids, "
                f"got {mask_faces.dtype} {mask_faces.shape}"
            )
        mask = jnp.broadcast_to(mask_faces, (*batch, mask_faces.shape[-1])).astype(jnp.int32)
        mask = mask.reshape(n, mask_faces.shape[-1])
    if n == 0 or faces.shape[0] == 0:
        return jnp.zeros(batch, bool)
    hit = _any_hit_kernel(
        o,
        d,
        tmin,
        tmax,
        mask,
        vertices.astype(dtype),
        faces,
        ray_chunk=ray_chunk,
        face_chunk=face_chunk,
        has_mask=mask_faces is not None,
    )
    return hit.reshape(batch)


# --------------------------------------------------------------------------------------------
# Fans of rays with a shared origin
# --------------------------------------------------------------------------------------------


def _fan_table(vertices, faces, t_min):
    """(F, rows): per face, what every fan test reads (corners, canonical edge orientations,
    validity, |normal|, coordinate scale, and the normal where ``t_min`` is given)."""
    dtype = vertices.dtype
    faces_p, _, valid = _pad_faces(vertices, faces, 1)
    tri = vertices[faces_p]  # (F, corner, xyz)
    nrm = jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    per_face = [
        tri.reshape(-1, 9),  # 0..8: corner k, component i at 3k + i
        _edge_sorted(faces_p).astype(dtype),  # 9..11: edge k runs high -> low vertex index
        valid.astype(dtype)[:, None],  # 12
        jnp.sqrt(jnp.sum(nrm * nrm, axis=-1))[:, None],  # 13: |(b − a) × (c − a)|
        jnp.max(jnp.abs(tri), axis=(-2, -1))[:, None],  # 14: coordinate scale of the corners
    ]
    if t_min is not None:
        per_face.append(nrm)  # 15..17: (b − a) × (c − a), for the hit distance
    return jnp.concatenate(per_face, axis=-1)  # (F, rows)


def _fan_fold(o_c, d_c, t_min, face_chunk):
    """The scan over face chunks of one chunk of fans: (g, K) hits of origins ``o_c`` (g, 3) along
    ``d_c`` (g, K, 3), folding chunks ``fd`` (rows, 1 or g, C) of face rows (:func:`_fan_table`:
    shared by every origin, or one list per origin)."""
    dtype = o_c.dtype
    tol = eps(dtype)
    dx, dy, dz = d_c[..., 0], d_c[..., 1], d_c[..., 2]
    oc = [o_c[:, i, None] for i in range(3)]
    o_scale = jnp.max(jnp.abs(o_c), axis=-1)[:, None]

    def body(hit, fd):
        rel = [[fd[3 * k + i] - oc[i] for i in range(3)] for k in range(3)]  # (g, C)
        m = []  # m[k]: normal of the plane through o and edge k (corner k -> k+1), opposite corner k+2
        for k in range(3):
            a, b = rel[k], rel[(k + 1) % 3]
            s = fd[9 + k] > 0
            lo = [jnp.where(s, b[i], a[i]) for i in range(3)]
            hi = [jnp.where(s, a[i], b[i]) for i in range(3)]
            # canonical orientation (low -> high vertex index), then the triangle's own sign
            cr = [
                lo[1] * hi[2] - lo[2] * hi[1],
                lo[2] * hi[0] - lo[0] * hi[2],
                lo[0] * hi[1] - lo[1] * hi[0],
            ]
            m.append([jnp.where(s, -x, x) for x in cr])
        vol = m[0][0] * rel[2][0] + m[0][1] * rel[2][1] + m[0][2] * rel[2][2]  # (a−o)·((b−o)×(c−o))
        # origin within rounding of the triangle's plane (distance |vol|/|N| at the scale of the
        # coordinates): the triangle is seen edge-on and never hits; so do invalid faces
        flat = jnp.abs(vol) <= tol * fd[13] * (fd[14] + o_scale)
        usable = (fd[12] > 0) & ~flat  # (g, C)
        sgn = jnp.where(vol < 0, -1.0, 1.0).astype(dtype)
        m = [[x * sgn for x in mk] for mk in m]
        if t_min is not None:
            far = jnp.abs(vol)  # the hit is beyond t_min iff t_min·|d·N| < |vol|
        for c in range(face_chunk):
            s_k = [
                dx * m[k][0][:, c, None] + dy * m[k][1][:, c, None] + dz * m[k][2][:, c, None]
                for k in range(3)
            ]
            # d lies in the cone of the triangle seen from o (for a usable triangle the m_k span
            # space, so all s_k = 0 only for d = 0; zero directions are masked below)
            h = (s_k[0] >= 0) & (s_k[1] >= 0) & (s_k[2] >= 0) & usable[:, c, None]
            if t_min is not None:
                # t = (a − o)·N / (d·N), of one sign with vol for a hit in the cone
                dn = dx * fd[15][:, c, None] + dy * fd[16][:, c, None] + dz * fd[17][:, c, None]
                h = h & (t_min * jnp.abs(dn) < far[:, c, None])
            hit = hit | h
        return hit, None

    return body


def _chunked_origins(o, d, g):
    n_pad = -(-o.shape[0] // g) * g
    o_p = jnp.concatenate([o, jnp.zeros((n_pad - o.shape[0], 3), o.dtype)]).reshape(n_pad // g, g, 3)
    d_p = jnp.concatenate([d, jnp.zeros((n_pad - o.shape[0], *d.shape[1:]), d.dtype)])
    return o_p, d_p.reshape(n_pad // g, g, *d.shape[1:])


@partial(jax.jit, static_argnames=("face_chunk", "origin_chunk"))
def _fan_kernel(o, d, vertices, faces, t_min=None, *, face_chunk, origin_chunk):
    n = o.shape[0]
    table = _fan_table(vertices, faces, t_min)
    pad = (-table.shape[0]) % face_chunk  # zero rows: invalid faces
    table = jnp.concatenate([table, jnp.zeros((pad, table.shape[1]), table.dtype)])
    # structure of arrays, (chunks, rows, 1, C): no size-3 reductions or gathers in the hot fusions
    fdat = table.reshape(-1, face_chunk, table.shape[1]).transpose(0, 2, 1)[:, :, None, :]
    o_p, d_p = _chunked_origins(o, d, min(origin_chunk, n))

    def per_chunk(args):
        o_c, d_c = args  # (g, 3), (g, K, 3)
        hit, _ = lax.scan(_fan_fold(o_c, d_c, t_min, face_chunk), jnp.zeros(d_c.shape[:-1], bool), fdat)
        return hit & jnp.any(d_c != 0, axis=-1)

    out = lax.map(per_chunk, (o_p, d_p))
    return out.reshape(-1, *d.shape[1:-1])[:n]


def ray_fan_any_hit(
    origins: Float[ArrayLike, "... 3"],
    dirs: Float[ArrayLike, "... K 3"],
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    *,
    t_min: float | Float[ArrayLike, ""] | None = None,
    face_chunk: int = DEFAULT_FAN_FACE_CHUNK,
    origin_chunk: int = DEFAULT_FAN_ORIGIN_CHUNK,
) -> Bool[Array, "... K"]:
    """Any-hit for fans of K rays sharing an origin: ``hit[..., k]`` for the ray ``o + t·d_k``,
    t > 0, or t > ``t_min`` where given.

    Same result as :func:`ray_triangle_any_hit` with ``t_min = 0, t_max = ∞`` (up to rays that
    graze a vertex within rounding), factorised per (origin, triangle) as in notes/bsv-speed.md
    §(a): 9 multiply-adds per (ray, triangle). A triangle whose plane passes within rounding of
    the origin (distance ≤ ``eps(dtype)`` times the coordinate scale) is seen edge-on and never
    hits, so an origin on the surface ignores its own faces. Shared edges are evaluated in one
    canonical orientation, so rays through an edge of a closed mesh do not leak.

    Limitation: the edge tests are triple products ``d · ((a − o) × (b − o))``, each rounded on its
    own, so a ray passing within rounding (~1e-7 rad in float32) of a *vertex* can slip between
    the triangles around it. Fans of fixed grid directions (the BSV) essentially never do; use
    :func:`ray_triangle_any_hit` (watertight at vertices too) for rays aimed at vertices.

    Args:
        origins: (..., 3); dirs: (..., K, 3), any length (a zero direction never hits).
        t_min: None, or a scalar ≥ 0 (may be traced): hits at ``t ≤ t_min`` (in units of |d|) are
            then ignored, and each (ray, triangle) pair also tests the hit distance (three more
            multiply-adds), as for a receiver lifted off a surface
            (:func:`jshadow.entities.surface_offset`).
        face_chunk: triangles per ``lax.scan`` step; origin_chunk: origins per ``lax.map`` step.
    """
    vertices, faces = _check_mesh(vertices, faces)
    _check_chunk("face_chunk", face_chunk)
    _check_chunk("origin_chunk", origin_chunk)
    origins = jnp.asarray(origins)
    dirs = jnp.asarray(dirs)
    if origins.shape[-1:] != (3,) or dirs.ndim < 2 or dirs.shape[-1] != 3:
        raise ValueError(
            f"origins must be (..., 3) and dirs (..., K, 3), got {origins.shape} and {dirs.shape}"
        )
    dtype = jnp.result_type(origins, dirs, vertices)
    batch = jnp.broadcast_shapes(origins.shape[:-1], dirs.shape[:-2])
    k = dirs.shape[-2]
    n = math.prod(batch)
    if n == 0 or k == 0 or faces.shape[0] == 0:
        return jnp.zeros((*batch, k), bool)
    o = jnp.broadcast_to(origins, (*batch, 3)).astype(dtype).reshape(n, 3)
    d = jnp.broadcast_to(dirs, (*batch, k, 3)).astype(dtype).reshape(n, k, 3)
    if t_min is not None:
        t_min = jnp.asarray(t_min, dtype)
        if t_min.shape != ():
            raise ValueError(f"t_min must be a scalar, got shape {t_min.shape}")
    hit = _fan_kernel(
        o, d, vertices.astype(dtype), faces, t_min, face_chunk=face_chunk, origin_chunk=origin_chunk
    )
    return hit.reshape(*batch, k)


# --------------------------------------------------------------------------------------------
# Spheres
# --------------------------------------------------------------------------------------------


def ray_sphere_any_hit(
    origins: Float[ArrayLike, "... 3"],
    dirs: Float[ArrayLike, "... 3"],
    center: Float[ArrayLike, "3"],
    radius: float | Float[ArrayLike, ""],
    t_min: float | Float[ArrayLike, "..."] = 0.0,
    t_max: float | Float[ArrayLike, "..."] = math.inf,
) -> Bool[Array, "..."]:
    """Whether the ray ``o + t·d`` meets the sphere's surface at some ``t_min < t < t_max``.

    The surface, not the ball: an origin inside the sphere hits (at the exit point, t > 0) unless
    ``t_max`` ends the segment before it. A tangent ray (one touching point) counts as a hit.
    ``dirs`` need not be unit (t in units of |d|); a zero direction never hits. Batches over the
    broadcast leading axes of origins, dirs, t_min and t_max. Not differentiable (boolean output).
    """
    o = jnp.asarray(origins)
    d = jnp.asarray(dirs)
    c = jnp.asarray(center)
    if o.shape[-1:] != (3,) or d.shape[-1:] != (3,) or c.shape != (3,):
        raise ValueError(
            f"origins, dirs must be (..., 3) and center (3,), got {o.shape}, {d.shape}, {c.shape}"
        )
    dtype = jnp.result_type(o, d, c)
    o, d, c = o.astype(dtype), d.astype(dtype), c.astype(dtype)
    r = jnp.asarray(radius, dtype)
    if r.shape != ():
        raise ValueError(f"radius must be a scalar, got shape {r.shape}")
    oc = o - c
    a = jnp.sum(d * d, axis=-1)
    b = jnp.sum(oc * d, axis=-1)  # half the linear coefficient
    cc = jnp.sum(oc * oc, axis=-1) - r * r
    disc = b * b - a * cc
    ok = (a > 0) & (disc >= 0)
    sq = safe_sqrt(disc)
    # numerically stable roots: q = −(b + sign(b)·√disc); t = q/a and cc/q
    q = -(b + jnp.where(b >= 0, sq, -sq))
    a_s = jnp.where(a > 0, a, 1.0)
    q_s = jnp.where(q != 0, q, 1.0)
    t1 = q / a_s
    t2 = jnp.where(q != 0, cc / q_s, t1)  # q = 0 only if b = 0 and disc = 0: double root at 0
    t_lo, t_hi = jnp.minimum(t1, t2), jnp.maximum(t1, t2)
    tmin = jnp.asarray(t_min, dtype)
    tmax = jnp.asarray(t_max, dtype)

    def inside(t):
        return (t > tmin) & (t < tmax)

    return ok & (inside(t_lo) | inside(t_hi))
