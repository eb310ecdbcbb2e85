"""Silhouette edges of a triangle mesh seen from a point, sampled for the visibility boundary term.

The derivative of the SH projection of binary visibility, ``S_i = ∫ V Y_i dω``, with respect to the
vertices is a line integral over the *visible* parts of the silhouette edges (Reynolds transport
on the sphere; the edge-sampling view of the boundary term in the deformable-shadow-fields paper's
gradient discussion, derived in ``notes/visibility-gradients.md`` §2). This module does the
geometric half of that work for one viewpoint p, with static shapes:

1. :func:`silhouette_edges_table` (once per topology): undirected edges with the face in which
   each edge reads i→j (``f0``) and the one in which it reads j→i (``f1``, −1 on a boundary).
2. :func:`silhouette_samples` (per viewpoint): facing of every face, the silhouette mask
   ``front[f0] ≠ front[f1]`` (boundary edges always), compaction to K slots with
   ``jnp.nonzero(size=K)``, orientation a→b as in the front-facing face, Gauss–Legendre nodes in
   the angle ψ at p, and the visibility χ of every node.

Sign rule: with (a, b) oriented as in the front-facing face, ``m = (a − p) × (b − p)`` points out of
the occluded region Ω. The occluded-region coefficients ``O_i = ∫_Ω Y_i dω`` then change by
``dO_i = Σ_edges ∫ χ Y_i(ω) m̂·(δx − δp)/r dψ`` with ``x(s) = a + s(b − a)`` and
``δx = (1 − s)δa + sδb``.

Visibility of a node: the ray from p along ω, to infinity, ignoring the edge's own two faces.
An edge point bounds Ω only if the *whole* line through it is free, so geometry behind the edge
counts as well as geometry in front of it (notes §4 pitfall 1). Rays of one viewpoint share their
origin, so per face only the three edge-plane normals ``(v_k − p) × (v_{k+1} − p)`` are needed and a
direction hits iff its three dot products with them are ≥ 0 (9 multiply-adds per ray and face, fused
by XLA with the sign tests and the face-id mask). On a closed mesh a ray from an outside viewpoint can
meet the surface only by entering through a front-facing face, so only front faces are tested.

Limitations: S is only piecewise smooth; when p crosses the plane of a face next to a visible
silhouette edge the derivative jumps, and the plain sign test returns the one-sided derivative of
the current facing configuration. Fixed nodes per edge integrate partly visible edges (visibility
changing along the edge) only to first order: about 4 % of ‖dS/dX‖ at 8 nodes on the bunny, falling
like 1/n (notes §5). Degenerate (zero-area) faces have no facing and must be removed beforehand.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._numerics import eps, safe_atan2, safe_div, safe_norm

_FACE_CHUNK = 8  # faces per lax.scan step of the visibility test

__all__ = ["EdgeTable", "silhouette_edges_table", "SilhouetteSamples", "silhouette_samples"]


class EdgeTable(eqx.Module):
    """Undirected edges of a triangle mesh and their two faces (fixed per topology).

    Attributes:
        edges: (E, 2) int32 vertex ids (i, j), i < j.
        faces: (E, 2) int32 face ids (f0, f1): the edge reads i→j in f0 and j→i in f1. On a boundary
            edge one of them is −1; then ``f0`` is always the existing face and the edge is stored
            in the direction that face reads it.
        closed: (static) no boundary edges. Then a ray from an outside viewpoint can only meet the
            mesh by entering through a front-facing face, and the visibility test skips back faces.
    """

    edges: Int[Array, "E 2"]
    faces: Int[Array, "E 2"]
    closed: bool = eqx.field(static=True, default=False)

    @property
    def num_edges(self) -> int:
        return int(self.edges.shape[0])


def silhouette_edges_table(faces: Int[ArrayLike, "F 3"]) -> EdgeTable:
    """Build the :class:`EdgeTable` of a consistently wound triangle mesh (numpy, once per topology).

    Raises ValueError if ``faces`` is not an (F, 3) integer array of concrete values, if a face
    repeats a vertex, or if a directed half-edge i→j occurs in two faces (inconsistent winding or
    a non-manifold edge). Boundary edges (one face only) are allowed.
    """
    if isinstance(faces, jax.core.Tracer):
        raise ValueError("silhouette_edges_table needs concrete faces (the topology is static), got a tracer")
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces must be an integer array of shape (F, 3), got {f.dtype} {f.shape}")
    if f.shape[0] == 0:
        raise ValueError("faces must contain at least one triangle")
    if np.any(f < 0):
        raise ValueError("faces contain negative vertex ids")
    if np.any((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])):
        raise ValueError("faces contain a triangle with a repeated vertex (degenerate); remove it first")
    n_f = f.shape[0]
    src = f.reshape(-1)
    dst = np.roll(f, -1, axis=1).reshape(-1)
    fid = np.repeat(np.arange(n_f), 3)
    key = np.stack([src, dst], axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    if np.any(counts > 1):
        bad = key[np.argmax(counts[inverse.reshape(-1)] > 1)]
        raise ValueError(
            f"half-edge {int(bad[0])}->{int(bad[1])} occurs in more than one face: inconsistent winding or "
            "a non-manifold edge (expected every directed edge at most once)"
        )
    lo, hi = np.minimum(src, dst), np.maximum(src, dst)
    und = np.stack([lo, hi], axis=1)
    uniq, inv = np.unique(und, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    n_e = uniq.shape[0]
    fwd = src < dst  # the half-edge reads lo -> hi
    f_fwd = np.full(n_e, -1, np.int64)
    f_bwd = np.full(n_e, -1, np.int64)
    f_fwd[inv[fwd]] = fid[fwd]
    f_bwd[inv[~fwd]] = fid[~fwd]
    edges = uniq.copy()
    # boundary edge read only hi -> lo: store it reversed so that f0 is its face
    only_bwd = f_fwd < 0
    edges[only_bwd] = edges[only_bwd][:, ::-1]
    f0 = np.where(only_bwd, f_bwd, f_fwd)
    f1 = np.where(only_bwd, -1, f_bwd)
    return EdgeTable(
        edges=jnp.asarray(edges, jnp.int32),
        faces=jnp.asarray(np.stack([f0, f1], axis=1), jnp.int32),
        closed=bool(np.all(f1 >= 0)),
    )


class SilhouetteSamples(eqx.Module):
    """Per-viewpoint silhouette quadrature, K slots of n nodes (all under ``stop_gradient``).

    Attributes (K slots; slots past ``count`` or with an end-on edge carry zero weights):
        a, b: (K,) int32 vertex ids, oriented as in the edge's front-facing face.
        m: (K, 3) ``(a − p) × (b − p)``, the outward normal (out of Ω) of the edge's plane at p.
        s: (K, n) edge parameter of each node, ``x = a + s (b − a)``.
        omega: (K, n, 3) world unit direction from p to each node.
        q: (K, n) weight ``w_ψ χ / (r |m|)``: the node's Gauss–Legendre weight in ψ times its
            visibility χ ∈ {0, 1}, divided by its distance r and by |m|.
        count: () int32 number of silhouette edges (``count > K`` means slots overflowed).
    """

    a: Int[Array, " K"]
    b: Int[Array, " K"]
    m: Float[Array, "K 3"]
    s: Float[Array, "K n"]
    omega: Float[Array, "K n 3"]
    q: Float[Array, "K n"]
    count: Int[Array, ""]


def _face_cones(rel: Float[Array, "F 3 3"]) -> Float[Array, "F 3 3"]:
    """Edge-plane normals (F, edge, xyz) of each face's cone at the origin, signed so that a direction
    is inside iff all three dot products are ≥ 0 (and one is > 0). Faces whose plane contains the
    origin, and zero-area faces, get zero normals and are never hit."""
    nrm = jnp.cross(rel, jnp.roll(rel, -1, axis=1))  # edge k: corner k -> k+1
    vol = jnp.sum(nrm[:, 0] * rel[:, 2], axis=-1)  # det[a, b, c] relative to the origin
    return nrm * jnp.sign(vol).astype(rel.dtype)[:, None, None]


def _any_hit_masked(
    dirs: Float[Array, "R 3"],
    cones: Float[Array, "F 3 3"],
    fids: Int[Array, " F"],
    n_active: Int[Array, ""],
    skip0: Int[Array, " R"],
    skip1: Int[Array, " R"],
) -> Bool[Array, " R"]:
    """Whether each ray from the cones' common origin along ``dirs`` enters any of the first
    ``n_active`` faces other than those with ids ``skip0``/``skip1`` (``fids`` are the faces' ids).

    Written as explicit multiply-adds over chunks of faces, each chunk one vectorised pass over the
    rays, so XLA fuses the dot products, the sign tests and the OR (no rays × faces array is stored);
    the loop stops after the chunk holding face ``n_active − 1`` (primal only, not differentiable).
    """
    n_f = cones.shape[0]
    n_chunks = -(-n_f // _FACE_CHUNK)
    pad = n_chunks * _FACE_CHUNK - n_f  # padding faces have zero normals: never hit
    cones = jnp.concatenate([cones, jnp.zeros((pad, 3, 3), cones.dtype)]).reshape(n_chunks, _FACE_CHUNK, 3, 3)
    fids = jnp.concatenate([fids, jnp.full((pad,), -2, jnp.int32)]).reshape(n_chunks, _FACE_CHUNK)
    ox, oy, oz = dirs[:, 0], dirs[:, 1], dirs[:, 2]

    def body(i, hit):
        c_chunk, f_chunk = cones[i], fids[i]
        for c in range(_FACE_CHUNK):
            s = [ox * c_chunk[c, k, 0] + oy * c_chunk[c, k, 1] + oz * c_chunk[c, k, 2] for k in range(3)]
            lo = jnp.minimum(jnp.minimum(s[0], s[1]), s[2])
            hi = jnp.maximum(jnp.maximum(s[0], s[1]), s[2])
            hit = hit | ((lo >= 0) & (hi > 0) & (skip0 != f_chunk[c]) & (skip1 != f_chunk[c]))
        return hit

    n_used = (n_active + _FACE_CHUNK - 1) // _FACE_CHUNK
    return lax.fori_loop(0, n_used, body, jnp.zeros(dirs.shape[0], bool))


def silhouette_samples(
    vertices: Float[Array, "V 3"],
    faces: Int[Array, "F 3"],
    table: EdgeTable,
    point: Float[Array, "3"],
    slots: int,
    nodes: int,
) -> SilhouetteSamples:
    """Silhouette edges of the mesh seen from ``point`` and their quadrature nodes (one viewpoint).

    Args:
        vertices: (V, 3) positions; faces: (F, 3) outward-wound triangles; table: their
            :class:`EdgeTable`.
        point: (3,) viewpoint p, outside the mesh.
        slots: K, static number of silhouette slots; edges beyond K are dropped (see ``count``).
        nodes: n, static number of Gauss–Legendre nodes per edge in the angle ψ at p.

    Returns:
        :class:`SilhouetteSamples`; compute it under ``stop_gradient`` (it is piecewise constant or
        not meant to be differentiated). vmap over viewpoints (or ``lax.map`` to bound memory:
        the visibility test holds a (K·n, 3F) array per viewpoint).

    Edges seen end-on (p on the edge's line, |m| ≈ 0) and edges with an end at p get zero weight; so
    do faces containing p, which face neither way (plain sign test, one-sided derivative).
    """
    dtype = vertices.dtype
    tol = eps(dtype)
    rel = vertices[faces] - point  # (F, 3 corners, 3)
    nrm = jnp.cross(rel[:, 1] - rel[:, 0], rel[:, 2] - rel[:, 0])
    front = jnp.sum(nrm * rel[:, 0], axis=-1) < 0  # n_f · (p − a) > 0
    f0, f1 = table.faces[:, 0], table.faces[:, 1]
    fr0 = front[f0]
    fr1 = jnp.where(f1 >= 0, front[jnp.maximum(f1, 0)], ~fr0)  # boundary edge: always silhouette
    sil = fr0 != fr1
    count = jnp.sum(sil, dtype=jnp.int32)
    (idx,) = jnp.nonzero(sil, size=slots, fill_value=0)
    used = jnp.arange(slots, dtype=jnp.int32) < count
    i, j = table.edges[idx, 0], table.edges[idx, 1]
    fwd = fr0[idx]
    a_id = jnp.where(fwd, i, j)
    b_id = jnp.where(fwd, j, i)
    av = vertices[a_id] - point  # (K, 3)
    bv = vertices[b_id] - point
    scale = jnp.max(jnp.abs(rel))
    r_a = safe_norm(av)
    r_b = safe_norm(bv)
    a_hat = av / jnp.where(r_a > 0, r_a, 1.0)[:, None]
    b_x = jnp.sum(bv * a_hat, axis=-1)
    b_perp = bv - b_x[:, None] * a_hat
    b_y = safe_norm(b_perp)
    ok = used & (r_a > tol * scale) & (r_b > tol * scale) & (b_y > tol * r_b)  # end-on / end at p: skip
    t_hat = b_perp / jnp.where(ok, b_y, 1.0)[:, None]
    psi_e = jnp.where(ok, safe_atan2(b_y, b_x), 0.0)  # angle subtended at p, in [0, π)

    xi, wi = np.polynomial.legendre.leggauss(nodes)
    xi, wi = jnp.asarray(xi, dtype), jnp.asarray(wi, dtype)
    psi = 0.5 * psi_e[:, None] * (1.0 + xi)  # (K, n)
    w_psi = 0.5 * psi_e[:, None] * wi
    cos_p, sin_p = jnp.cos(psi), jnp.sin(psi)
    omega = cos_p[..., None] * a_hat[:, None, :] + sin_p[..., None] * t_hat[:, None, :]
    # x(ψ) on the line a + s (b − a): D = b_y cos ψ − (b_x − r_a) sin ψ > 0 on [0, ψ_e]
    den = b_y[:, None] * cos_p - (b_x - r_a)[:, None] * sin_p
    s = safe_div(r_a[:, None] * sin_p, den)
    r = safe_div(r_a[:, None] * b_y[:, None], den)
    m = jnp.cross(av, bv)
    m_len = r_a * b_y  # |m| = r_a · b_y

    # masked whole-line visibility: ray from p along ω to infinity, ignoring the edge's two faces
    skip0 = jnp.broadcast_to(f0[idx][:, None], (slots, nodes)).reshape(-1)
    skip1 = jnp.broadcast_to(f1[idx][:, None], (slots, nodes)).reshape(-1)
    cones = _face_cones(rel)
    n_faces = faces.shape[0]
    if table.closed:  # only front faces can be entered from outside: test them first, stop there
        order = jnp.argsort(~front, stable=True).astype(jnp.int32)
        cones, fids, n_active = cones[order], order, jnp.sum(front, dtype=jnp.int32)
    else:
        fids, n_active = jnp.arange(n_faces, dtype=jnp.int32), jnp.asarray(n_faces, jnp.int32)
    hit = _any_hit_masked(omega.reshape(-1, 3), cones, fids, n_active, skip0, skip1).reshape(slots, nodes)
    chi = (~hit & ok[:, None]).astype(dtype)
    q = chi * safe_div(w_psi, r * m_len[:, None])
    return SilhouetteSamples(a=a_id, b=b_id, m=m, s=s, omega=omega, q=q, count=count)
