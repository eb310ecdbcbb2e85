"""Vertex derivative of the edge-scan BSV in the image plane, with visibility read off its own images.

The edge-scan sampler (:mod:`jshadow.visibility._edgescan`) computes, per shell point p, the occluded
region Ω of the gnomonic image of the cone that holds the mesh. The SH coefficients are
``V_i = √(4π)·δ_i0 − O_i`` with ``O_i = ∫_Ω Y_i(ω) dω``. In gnomonic coordinates (x, y) of the local
frame (``ω = (x, y, 1)/ρ``, ``ρ = √(1 + x² + y²)``) the solid angle is ``dω = ρ⁻³ dx dy``, so
``O_i = ∫_Ω Y_i J dx dy`` with ``J = ρ⁻³``, and when the boundary of Ω moves with outward normal
speed v the coefficients change by the line integral ``dO_i = ∮ Y_i J v dl`` (Reynolds transport in
the plane; the boundary term of notes/visibility-gradients.md §2 in image coordinates).

The boundary of Ω is made of projected silhouette edges, which are straight segments in a gnomonic
image. For a silhouette edge (a, b) with local coordinates ``q = Fᵀ(x − p)`` (F the fixed frame of
the view), image end points A = q_a,xy / q_a,z and B, weight ``w = ±1`` (+1 when the edge reads a→b
in its front-facing face) and ``n₃ = (A, 1) × (B, 1)``, the edge's line is ``L(X) = m·X = 0`` with
``X = (x, y, 1)`` and ``m = w·q_a × q_b`` pointing out of Ω, so the outward speed is
``v = −δm·X / |m_xy|``. On the line ``X = α q_a + β q_b`` with ``α = (1 − t)/q_a,z``,
``β = t/q_b,z`` (``P(t) = A + t(B − A)``), hence ``δm·X = −(α δq_a + β δq_b)·m``; and
``m = w q_a,z q_b,z n₃`` with ``|n₃,xy| = |B − A|``, so with ``dl = |B − A| dt``:

    v dl = w · (α δq_a + β δq_b) · n₃ dt,     δq = Fᵀ(δx − δp),

which is linear in the vertex and viewpoint motion and vanishes smoothly for an edge that projects
to a point (n₃ = 0): no division by the edge length anywhere. Only *visible* parts of silhouette
edges bound Ω. Their visibility χ at a node is decided without casting rays, in O(1) per node:

* the pixel one pixel beyond the node along the outward normal must be free in the forward pass's
  own occlusion image (that pixel centre lies at least 0.29 px outside the edge's own line, so the
  edge never hides itself), and
* no face around the edge's end points (the ring of faces touching a or b) may cover the node: the
  contour of a finely tessellated mesh zigzags below the pixel size, and edges folded back under
  their neighbours are invisible to the image.

Layout of the computation (the tangent is linear, so JAX transposes it for reverse mode):

1. all (silhouette edge, view) pairs, packed and compacted into ``S`` static slots over all views
   (the same compaction as the edge-scan's, but not restricted to edges that cross a pixel column);
2. per slot and Gauss–Legendre node t_k the image test; the nodes that pass it (the bunny: 40 % of
   its silhouette nodes) are compacted again into ``N`` static node slots, and only those are
   tested against the faces around the edge's end points, walked as two fans (each spoke's
   orientation serves two faces);
3. per node the scalar ``s = W_k χ_k w (α_k n₃·δq_a + β_k n₃·δq_b)`` with primal weights, splatted
   bilinearly onto the (N_y + 1) × (N_x + 1) pixel-corner grid of its view;
4. ``dV = −D @ (Y J)`` with the corner values of ``Y_i J`` (one matrix product for all views).

In reverse mode step 4 becomes one product of the cotangent with the corner table (the cotangent
as a function on the image), step 3 a bilinear lookup per node, and the vertex gradient a
scatter onto the two vertices of each node: nothing of size (slots × n²) is formed. Each step is a
:func:`~jshadow.visibility._edgescan.staged` computation, so that XLA does not fuse the gathers of
one step into the next and recompute them per element (the face test was 5× slower that way).
Both slot counts are measured on concrete poses (:func:`edgescan_grad_slots`); an overflow
raises at run time, also under ``jax.jit(jax.grad(...))``.

Accuracy (tests/test_edgescan_grad.py; BENCHMARKS.md "BSV gradients"): on convex meshes every
silhouette edge is visible and only the bilinear ``Y J`` table separates the result from the exact
derivative (3.5e-4 relative at 64² against converged differences); on a coarse self-occluding torus it
converges to the ray-cast derivative with nodes and pixels (0.5–2 % at 16 nodes and 128²; 3–12 %,
cosine ≥ 0.993, at the default 2 nodes and 32²). On finely tessellated self-occluding meshes
(bunny, airplane) χ is **biased**: folded contour edges hidden by faces beyond the ring, or within a
pixel of another silhouette, count as visible, so the derivative is 10–35 % too large with a cosine
of 0.97–0.985 to the ray-cast one. Use ``bsv_gradient = "raycast"`` where the magnitude matters.
"""

from __future__ import annotations

import math
from functools import lru_cache, partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike, Float, Int

from ..sh._grids import _np_sh_basis
from ._bsv import bsv_sample_points
from ._bsv_grad import _sample_points  # sample points p = c(X) + shell·r(X)·u and frames
from ._edgescan import (
    _WORD,
    EdgeTable,
    _basis_weights,
    _cached_edge_table,
    _compact,
    _compute,
    _local_coords,
    _pack,
    _prepare,
    _project_sh,
    _resolve,
    _round_up,
    _stage_occlusion,
    _stage_views,
    always,
    edgescan_occlusion,
    staged,
)

__all__ = ["bsv_mesh_edgescan_diff", "edgescan_grad_slots"]


_GRAD_OVERFLOW = (
    "edge-scan gradient slots overflowed: pass a larger grad_slots (see edgescan_grad_slots); "
    "silhouette edges would be missing from the derivative"
)


# --------------------------------------------------------------------------------------------
# static tables
# --------------------------------------------------------------------------------------------


@lru_cache(maxsize=32)
def _np_corner_basis(directions, shell, n):
    """``Y_i(ω) J`` at the (N_y + 1)(N_x + 1) pixel corners, row-major (row = local y): (C, n²)."""
    ny, nx = directions
    tan_a = 1.0 / math.sqrt(shell * shell - 1.0)
    xe = np.linspace(-tan_a, tan_a, nx + 1)
    ye = np.linspace(-tan_a, tan_a, ny + 1)
    d = np.stack(np.broadcast_arrays(xe[None, :], ye[:, None], 1.0), axis=-1).reshape(-1, 3)
    rho = np.linalg.norm(d, axis=-1)
    return _np_sh_basis(d / rho[:, None], n) * (rho**-3.0)[:, None]


def _corner_basis(directions, shell, n, dtype):
    with jax.ensure_compile_time_eval():
        return jnp.asarray(_np_corner_basis(directions, shell, n), dtype)


_FANS: dict = {}


def _ring_fans(faces_np: np.ndarray, table: EdgeTable) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The faces around an edge's end points, other than its own two, as the rims of two open fans.

    For edge (a, b) the faces around a are ``(a, u_i, u_{i+1})`` for consecutive entries of a's rim
    ``u`` read around a from the vertex after b to the vertex before it (so the edge's own faces
    (a, b, ·) and (a, ·, b) are left out), then the same around b starting after a, in one row.
    Returns ``rim`` (E_pad, M) int32 vertex ids, ``at_b`` (E_pad, M) bool (the entry belongs to b's
    fan) and ``face`` (E_pad, M − 1) bool, True where ``rim[i], rim[i + 1]`` bound a face with the
    centre of entry i (False at the seam between the fans, on padding, which repeats the last entry,
    and between two cycles of a vertex whose neighbourhood is not a single disc). This is the set of
    faces touching a or b minus the edge's own two; each spoke centre → u_i serves two faces, so a
    point needs two orientation tests per face instead of three (the bunny's padded rows: 47
    instead of 66). Cached per topology.
    """
    key = (faces_np.shape, hash(faces_np.tobytes()))
    if key in _FANS:
        return _FANS[key]
    if len(_FANS) >= 32:
        _FANS.clear()
    nxt: dict = {}  # (centre, u) -> the vertex after u around the centre, in the faces' winding
    for i, j, k in faces_np.tolist():
        nxt[(i, j)], nxt[(j, k)], nxt[(k, i)] = k, i, j
    around: dict = {}
    for c, u in nxt:
        around.setdefault(c, []).append(u)

    def fan(c, start):
        """(rim, face) of c: from the vertex after ``start`` to the one before it, then any other
        cycles around c (closed); face[i] says whether rim[i - 1], rim[i] bound a face."""
        rim, face, seen = [], [], {start}
        u = nxt[(c, start)]
        while u != start and u not in seen:
            seen.add(u)
            face.append(len(rim) > 0)
            rim.append(u)
            u = nxt[(c, u)]
        for s in around[c]:
            if s in seen:
                continue
            u = s
            face.append(False)
            rim.append(u)
            seen.add(u)
            while (u := nxt[(c, u)]) != s:
                face.append(True)
                rim.append(u)
                seen.add(u)
            face.append(True)  # close the cycle: the face (c, last, s)
            rim.append(s)
        return rim, face

    a, b = (np.asarray(x)[: table.num_edges].tolist() for x in (table.a, table.b))
    rows = []
    for x, y in zip(a, b, strict=True):
        ra, fa = fan(x, y)
        rb, fb = fan(y, x)
        rows.append((ra + rb, fa + [False] + fb[1:] if rb else fa, len(ra)))
    m = max(2, max(len(r) for r, _, _ in rows))
    e_pad = int(table.a.shape[0])
    rim = np.zeros((e_pad, m), np.int32)
    at_b = np.zeros((e_pad, m), bool)
    face = np.zeros((e_pad, m), bool)
    for e, (r, f, na) in enumerate(rows):
        if r:
            rim[e, : len(r)], rim[e, len(r) :] = r, r[-1]
            face[e, : len(f)] = f
            at_b[e, na:] = True
    _FANS[key] = (rim, at_b, face[:, 1:])
    return _FANS[key]


@lru_cache(maxsize=16)
def _np_nodes(nodes):
    x, w = np.polynomial.legendre.leggauss(nodes)
    return 0.5 * (x + 1.0), 0.5 * w  # on [0, 1]


# --------------------------------------------------------------------------------------------
# slots
# --------------------------------------------------------------------------------------------


@partial(jax.jit, static_argnames=("grid", "shell"))
def _local(vertices, faces, *, grid, shell):
    """Local coordinates per (vertex, view): image x, y and depth q_z (V, G); facing (F, G)."""
    _, _, comps, offset = _stage_views(vertices, faces, grid=grid, shell=shell)
    qx, qy, qz, side = _local_coords(comps)
    return qx / qz, qy / qz, qz, side > offset[:, None]


@jax.jit
def _silhouette_mask(front, t1, t2):
    return front[t1] != front[t2]  # (E_pad, G); padding edges have t1 = t2: never


def edgescan_grad_slots(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    grid: tuple[int, int] = (12, 20),
    shell: float = 1.5,
    *,
    margin: float = 1.5,
    edge_table: EdgeTable | None = None,
    directions: tuple[int, int] = (32, 32),
    nodes: int = 2,
) -> tuple[int, int]:
    """Static slot counts ``(pairs, nodes)`` for :func:`bsv_mesh_edgescan_diff`'s ``grad_slots``.

    ``pairs``: the (silhouette edge, view) pairs over all T·P views; ``nodes``: the Gauss–Legendre
    nodes on them whose pixel beyond the edge is free in the occlusion image (the only ones whose
    visibility is tested further; the bunny at shell 1.5 and 32² keeps 40 % of its nodes). Both
    counted on the given (concrete) pose, times ``margin``, rounded up to a multiple of 32.
    Silhouettes of closed meshes hold a small share of the edges per view (the bunny: 12 %).
    """
    if not (isinstance(margin, int | float) and margin >= 1.0):
        raise ValueError(f"margin must be a number >= 1, got {margin!r}")
    vertices, faces_j, table = _prepare(vertices, faces, edge_table)
    grid, directions, shell = tuple(grid), tuple(directions), float(shell)
    _, _, _, front = _local(vertices, faces_j, grid=grid, shell=shell)
    count = int(jnp.sum(_silhouette_mask(front, table.t1, table.t2)))
    cap = int(table.a.shape[0]) * grid[0] * grid[1]
    pairs = min(_round_up(max(1, count), _WORD), cap)
    occ, _ = edgescan_occlusion(vertices, faces_j, grid, directions, shell, edge_table=table)
    occ = jnp.swapaxes(occ.reshape(-1, *directions), -1, -2)  # column-major, as the pass keeps it
    live = int(
        _count_live(
            vertices,
            faces_j,
            table,
            occ,
            grid=grid,
            directions=directions,
            shell=shell,
            slots=pairs,
            nodes=nodes,
        )
    )
    return (
        min(_round_up(max(1, math.ceil(count * margin)), _WORD), cap),
        min(_round_up(max(1, math.ceil(live * margin)), _WORD), cap * nodes),
    )


@partial(jax.jit, static_argnames=("grid", "directions", "shell", "slots", "nodes"))
def _count_live(vertices, faces, table, occ, **kw):
    """Nodes that pass the image test (one compiled call: eagerly, its many small steps each compile)."""
    return jnp.sum(_pair_terms(vertices, faces, table, occ, **kw)[1])


def _check_grad_slots(grad_slots, nodes):
    """``grad_slots`` as ``(pairs, nodes)`` ints (an int: pairs, with a node slot for every node)."""

    def positive(x):
        return not isinstance(x, bool) and isinstance(x, int | np.integer) and x >= 1

    if positive(grad_slots):
        return int(grad_slots), int(grad_slots) * int(nodes)
    if isinstance(grad_slots, tuple | list) and len(grad_slots) == 2 and all(positive(x) for x in grad_slots):
        return int(grad_slots[0]), int(grad_slots[1])
    raise ValueError(f"grad_slots must be a positive int or a pair of them, got {grad_slots!r}")


def _default_grad_slots(table, grid):
    """Generous count when the pose is unknown: 30 % of all (edge, view) pairs (the bunny uses 12 %)."""
    return _round_up(math.ceil(0.3 * table.num_edges * grid[0] * grid[1]), _WORD)


# --------------------------------------------------------------------------------------------
# the tangent
# --------------------------------------------------------------------------------------------


def _pair_terms(vertices, faces, table, occ, *, grid, directions, shell, slots, nodes):
    """Per (silhouette edge, view) slot: the image-space quantities, and the nodes whose pixel one
    pixel beyond the edge is free in the occlusion image ``occ`` (G, N_x, N_y).

    Returns ``pair`` (a dict of (S,) arrays: edge, view, end points' vertex ids, image coordinates
    and depths, the facing weight w, n₃, and the nodes' image coordinates (S, nodes)), ``chi``
    (S, nodes) bool (False on empty slots), the silhouette pair count (), and the (vertex, view)
    image coordinates ``px, py`` (V, G). Each step is a :func:`staged` computation.
    """
    ny, nx = directions
    g = grid[0] * grid[1]
    tan_a = 1.0 / math.sqrt(shell * shell - 1.0)
    dx, dy = 2.0 * tan_a / nx, 2.0 * tan_a / ny
    stage = partial(staged, always(vertices))
    px, py, qz, front = stage(partial(_local, grid=grid, shell=shell), vertices, faces)
    sil = stage(_silhouette_mask, front, table.t1, table.t2)
    pos, total = stage(lambda m: _compact(_pack(m.reshape(-1)), slots), sil)

    def gather(pos, px, py, qz, front, a, b, t1):
        filled = pos >= 0
        pos = jnp.where(filled, pos, (a.shape[0] - 1) * g)  # empty: view 0 of a padding edge
        edge, view = pos // g, pos % g
        va, vb = a[edge], b[edge]
        fa, fb = va * g + view, vb * g + view
        pxf, pyf, qzf = px.reshape(-1), py.reshape(-1), qz.reshape(-1)
        ax, ay, az = pxf[fa], pyf[fa], qzf[fa]
        bx, by, bz = pxf[fb], pyf[fb], qzf[fb]
        w = jnp.where(front.reshape(-1)[t1[edge] * g + view], 1.0, -1.0).astype(px.dtype)
        return dict(edge=edge, view=view, va=va, vb=vb, ax=ax, ay=ay, az=az, bx=bx, by=by, bz=bz, w=w), filled

    def image_test(p, filled, occ):
        ax, ay, bx, by, w, view = (p[k] for k in ("ax", "ay", "bx", "by", "w", "view"))
        n3 = jnp.stack([ay - by, bx - ax, ax * by - ay * bx], axis=-1)  # (A, 1) × (B, 1)
        # nodes along the image segment: image coordinates (S, nodes)
        t_k = jnp.asarray(_np_nodes(nodes)[0], ax.dtype)
        node_x = ax[:, None] + t_k * (bx - ax)[:, None]
        node_y = ay[:, None] + t_k * (by - ay)[:, None]
        # visibility: the pixel one pixel beyond the node along the outward normal w·n₃_xy is free
        # (u along x, v along y in pixel units; pixel corners at integers)
        u, v = (node_x + tan_a) / dx, (node_y + tan_a) / dy
        nu, nv = w * n3[:, 0] * dx, w * n3[:, 1] * dy  # the normal in pixel units
        length = jnp.sqrt(nu * nu + nv * nv)
        ok = length > 0.0
        inv = jnp.where(ok, 1.0 / jnp.where(ok, length, 1.0), 0.0)  # double where: zero-length edges
        jo = jnp.floor(u + (nu * inv)[:, None]).astype(jnp.int32)
        io = jnp.floor(v + (nv * inv)[:, None]).astype(jnp.int32)
        inside = (jo >= 0) & (jo < nx) & (io >= 0) & (io < ny)
        flat = view[:, None] * (nx * ny) + jnp.clip(jo, 0, nx - 1) * ny + jnp.clip(io, 0, ny - 1)
        chi = ~(occ.reshape(-1)[flat] & inside) & filled[:, None]  # occ is column-major (G, N_x, N_y)
        return dict(p, n3=n3, node_x=node_x, node_y=node_y), chi

    pair, filled = stage(gather, pos, px, py, qz, front, table.a, table.b, table.t1)
    pair, chi = stage(image_test, pair, filled, occ)
    return pair, chi, total, (px, py)


def _slot_terms(vertices, faces, table, fans, occ, *, grid, directions, shell, slots, node_slots, nodes):
    """Primal per-node terms of the boundary integral (no derivative flows here).

    The nodes that pass the image test of :func:`_pair_terms` are compacted into ``node_slots``
    entries, and only those are tested against the faces around the edge's end points. Returns
    ``va, vb`` (N,) vertex ids, ``view`` (N,), ``normal`` (N, 3) = F n₃ (world), ``corner`` (N, 4)
    flat corner indices, ``ca, cb`` (N, 4) splat weights of ``n₃·δq_a`` and ``n₃·δq_b`` (zero on empty
    entries), the silhouette pair count () and the node count ().
    """
    ny, nx = directions
    g = grid[0] * grid[1]
    tan_a = 1.0 / math.sqrt(shell * shell - 1.0)
    dx, dy = 2.0 * tan_a / nx, 2.0 * tan_a / ny
    pair, chi, total, (px, py) = _pair_terms(
        vertices, faces, table, occ, grid=grid, directions=directions, shell=shell, slots=slots, nodes=nodes
    )
    stage = partial(staged, always(vertices))
    npos, count = stage(lambda c: _compact(_pack(c.reshape(-1)), node_slots), chi)

    def gather(npos, pair):
        live = npos >= 0
        npos = jnp.where(live, npos, 0)
        si, kk = npos // nodes, npos % nodes
        node = {k: (x.reshape(-1)[npos] if k in ("node_x", "node_y") else x[si]) for k, x in pair.items()}
        t_np, w_np = _np_nodes(nodes)
        dtype = node["ax"].dtype
        return dict(node, live=live, t_k=jnp.asarray(t_np, dtype)[kk], w_k=jnp.asarray(w_np, dtype)[kk])

    node = stage(gather, npos, pair)

    # ... and no face around the edge's end points covers the node (the contour of a fine mesh
    # zigzags: edges folded back under their neighbours by less than a pixel, which the image
    # cannot see). All vertices lie in front of p, so a face covers a direction iff the node lies
    # inside its projected triangle. The faces around each end point c form a fan
    # (c, u_i, u_{i+1}) (_ring_fans): the orientation of the node against a spoke c -> u_i serves
    # two faces.
    def fan_gather(edge, view, px, py, rim, at_b, face_ok):
        ids = rim[edge] * g + view[:, None]  # (N, M)
        return px.reshape(-1)[ids], py.reshape(-1)[ids], at_b[edge], face_ok[edge]

    fans = (jnp.asarray(x) for x in fans)
    ux, uy, at_b, face_ok = stage(fan_gather, node["edge"], node["view"], px, py, *fans)

    def finish(p, ux, uy, at_b, face_ok):
        ax, ay, bx, by, node_x, node_y = (p[k] for k in ("ax", "ay", "bx", "by", "node_x", "node_y"))
        cx, cy = jnp.where(at_b, bx[:, None], ax[:, None]), jnp.where(at_b, by[:, None], ay[:, None])
        spoke = (ux - cx) * (node_y[:, None] - cy) - (uy - cy) * (node_x[:, None] - cx)  # (N, M)
        ex, ey = ux[:, 1:] - ux[:, :-1], uy[:, 1:] - uy[:, :-1]
        rim_side = ex * (node_y[:, None] - uy[:, :-1]) - ey * (node_x[:, None] - ux[:, :-1])
        s0, s1, s2 = spoke[:, :-1], rim_side, -spoke[:, 1:]
        covered = ((s0 > 0) & (s1 > 0) & (s2 > 0)) | ((s0 < 0) & (s1 < 0) & (s2 < 0))
        chi = p["live"] & ~jnp.any(covered & face_ok, axis=-1)

        # bilinear splat onto the corner grid (G, N_y + 1, N_x + 1)
        u, v = (node_x + tan_a) / dx, (node_y + tan_a) / dy
        j0 = jnp.clip(jnp.floor(u), 0, nx - 1)
        i0 = jnp.clip(jnp.floor(v), 0, ny - 1)
        fu, fv = jnp.clip(u - j0, 0.0, 1.0), jnp.clip(v - i0, 0.0, 1.0)
        j0, i0 = j0.astype(jnp.int32), i0.astype(jnp.int32)
        base = p["view"] * ((ny + 1) * (nx + 1)) + i0 * (nx + 1) + j0
        corner = jnp.stack([base, base + 1, base + nx + 1, base + nx + 2], axis=-1)  # (N, 4)
        bil = jnp.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], axis=-1)
        t_k = p["t_k"]
        k = (p["w"] * p["w_k"] * chi.astype(ax.dtype))[:, None] * bil  # (N, 4)
        ca = k * ((1.0 - t_k) / p["az"])[:, None]
        cb = k * (t_k / p["bz"])[:, None]
        _, frames = bsv_sample_points(jnp.zeros(3, ax.dtype), jnp.ones((), ax.dtype), grid, shell)
        frames = frames.reshape(-1, 3, 3)
        normal = jnp.einsum("sij,sj->si", frames[p["view"]], p["n3"])  # F n₃: n₃·Fᵀδ = (F n₃)·δ
        return p["va"], p["vb"], p["view"], normal, corner, ca, cb

    return (*stage(finish, node, ux, uy, at_b, face_ok), total, count)


def _apply(terms, corner_basis, dvertices, dpoints, *, views):
    """The linear part: dV (G, n²) from the vertex motion (V, 3) and the viewpoint motion (G, 3)."""
    va, vb, view, normal, corner, ca, cb = terms
    dp = dpoints[view]
    ta = jnp.sum(normal * (dvertices[va] - dp), axis=-1)  # n₃·δq_a (S,)
    tb = jnp.sum(normal * (dvertices[vb] - dp), axis=-1)
    s = ca * ta[:, None] + cb * tb[:, None]  # (N, 4)
    c = corner_basis.shape[0]
    d = jnp.zeros(views * c, s.dtype).at[corner.reshape(-1)].add(s.reshape(-1))
    return -(d.reshape(views, c) @ corner_basis)  # V = √(4π)e₀ − O


# --------------------------------------------------------------------------------------------
# public
# --------------------------------------------------------------------------------------------


def bsv_mesh_edgescan_diff(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    n: int = 4,
    grid: tuple[int, int] = (12, 20),
    directions: tuple[int, int] = (32, 32),
    shell: float = 1.5,
    *,
    edge_table: EdgeTable | None = None,
    slots: tuple[int, int, int, int] | None = None,
    grad_slots: int | tuple[int, int] | None = None,
    nodes: int = 2,
) -> Float[Array, "T P n2"]:
    """Edge-scan BSV coefficients (T, P, n²) with the silhouette derivative (module docstring).

    The primal is exactly :func:`jshadow.visibility.bsv_mesh_edgescan` ``(...).coeffs``. Its
    ``jax.jvp`` is the image-plane boundary term, including the motion of the sample points
    ``p = c(X) + shell·r(X)·u``; ``jax.grad``/``jax.vjp`` are its transpose.

    Args:
        vertices: (V, 3) float, world units. faces: (F, 3) int, concrete, closed, consistently
            wound, edge-manifold (as for the edge-scan).
        n, grid, directions, shell, edge_table, slots: as in :func:`bsv_mesh_edgescan`.
        grad_slots: static sizes ``(pairs, nodes)`` of the derivative: (silhouette edge, view)
            slots and the nodes on them that pass the image test, from
            :func:`edgescan_grad_slots` on the rest pose; an int gives the pairs only (every node
            then keeps a slot: never overflows, slower); None: measured on ``vertices`` when they
            are concrete, else 30 % of all (edge, view) pairs. An overflow raises at run time.
        nodes: Gauss–Legendre nodes per projected edge (2: exact for the bilinear part on edges of
            constant visibility; most projected edges are shorter than a pixel).

    Limitations: see the module docstring (χ from the image, bilinear Y·J, one-sided derivative
    at visual events). The ``center`` and ``radius`` of the BSV are not returned here; take them
    from :func:`jshadow.geometry.bounding_sphere`, which is differentiable.
    """
    if not (isinstance(n, int | np.integer) and n >= 1):
        raise ValueError(f"n (number of SH bands) must be a positive int, got {n!r}")
    if not (isinstance(nodes, int | np.integer) and not isinstance(nodes, bool) and nodes >= 1):
        raise ValueError(f"nodes (Gauss–Legendre nodes per edge) must be a positive int, got {nodes!r}")
    faces_np = np.asarray(faces, np.int32)  # concrete topology (raises for traced faces)
    if edge_table is None:
        edge_table = _cached_edge_table(faces_np, jnp.shape(vertices)[0])
    vertices, _, table, grid, directions, shell, slots = _resolve(
        vertices, faces_np, grid, directions, shell, edge_table, slots
    )
    if grad_slots is None:
        if isinstance(vertices, jax.core.Tracer):
            grad_slots = _default_grad_slots(table, grid)
        else:
            grad_slots = edgescan_grad_slots(
                vertices,
                faces_np,
                grid,
                shell,
                margin=1.25,
                edge_table=table,
                directions=directions,
                nodes=nodes,
            )
    pair_slots, node_slots = _check_grad_slots(grad_slots, nodes)
    cap = int(table.a.shape[0]) * grid[0] * grid[1]
    pair_slots = min(_round_up(pair_slots, _WORD), cap)
    node_slots = min(_round_up(node_slots, _WORD), pair_slots * int(nodes))
    n, nodes = int(n), int(nodes)
    views = grid[0] * grid[1]
    basis_w = _basis_weights(directions, shell, n, vertices.dtype)
    fans = _ring_fans(faces_np, table)

    def forward(x):
        """Coefficients (G, n²) and occlusion images (G, N_x, N_y) of one edge-scan pass."""
        diff, _, _, _ = _compute(x, faces_np, table, grid, directions, shell, slots)
        occ = _stage_occlusion(diff)
        return _project_sh(occ, basis_w, n), occ

    @jax.custom_jvp
    def bsv(x):
        return forward(x)[0]

    @bsv.defjvp
    def bsv_jvp(primals, tangents):
        (x,), (dx,) = primals, tangents
        x0 = lax.stop_gradient(x)
        out, occ = forward(x0)
        *terms, total, count = _slot_terms(
            x0,
            faces_np,
            table,
            fans,
            occ,
            grid=grid,
            directions=directions,
            shell=shell,
            slots=pair_slots,
            node_slots=node_slots,
            nodes=nodes,
        )
        overflow = (total > pair_slots) | (count > node_slots)
        out = eqx.error_if(out, overflow, _GRAD_OVERFLOW)
        # the tangent carries the check too: under jax.jit(jax.grad(...)) the primal is dead code
        # and its check would be dropped with it, leaving a silently incomplete gradient
        ok = eqx.error_if(jnp.ones((), out.dtype), overflow, _GRAD_OVERFLOW)
        _, dpoints = jax.jvp(lambda v: _sample_points(v, grid, shell)[0], (x0,), (dx,))
        corner_basis = _corner_basis(directions, shell, n, out.dtype)
        dout = _apply(terms, corner_basis, dx, dpoints, views=views)
        return out, ok * dout.astype(out.dtype)

    return bsv(vertices).reshape(*grid, n * n)
