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
2. per slot and Gauss–Legendre node t_k: the scalar ``s = Σ W_k χ_k w (α_k n₃·δq_a + β_k n₃·δq_b)``
   weights are primal; s is splatted bilinearly onto the (N_y + 1) × (N_x + 1) pixel-corner grid of
   its view;
3. ``dV = −D @ (Y J)`` with the corner values of ``Y_i J`` (one matrix product for all views).

In reverse mode step 3 becomes one product of the cotangent with the corner table (the cotangent
as a function on the image), step 2 a bilinear lookup per node, and the vertex gradient a
scatter onto the two vertices of each slot: nothing of size (slots × n²) is formed.

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


_RINGS: dict = {}


def _ring_faces(faces_np: np.ndarray, table: EdgeTable) -> np.ndarray:
    """Per edge (a, b): the vertex ids of every face that touches a or b, except the edge's own two.

    (E_pad, K, 3) int32, K the largest such count of the mesh; unused entries repeat a vertex
    (a degenerate triangle that contains no point). Cached per topology.
    """
    key = (faces_np.shape, hash(faces_np.tobytes()))
    if key not in _RINGS:
        if len(_RINGS) >= 32:
            _RINGS.clear()
        a, b, t1, t2 = (np.asarray(x)[: table.num_edges] for x in (table.a, table.b, table.t1, table.t2))
        nv = max(int(faces_np.max()) + 1, table.num_vertices)
        order = np.argsort(faces_np.reshape(-1), kind="stable")
        start = np.searchsorted(faces_np.reshape(-1)[order], np.arange(nv + 1))
        inc = [order[start[v] : start[v + 1]] // 3 for v in range(nv)]  # faces around each vertex
        rings = []
        for e in range(table.num_edges):
            r = np.union1d(inc[a[e]], inc[b[e]])
            rings.append(r[(r != t1[e]) & (r != t2[e])])
        k = max(1, max(len(r) for r in rings))
        out = np.zeros((int(table.a.shape[0]), k, 3), np.int32)  # padding: vertex 0 thrice
        for e, r in enumerate(rings):
            out[e, : len(r)] = faces_np[r]
            out[e, len(r) :] = a[e]
        _RINGS[key] = out
    return _RINGS[key]


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
) -> int:
    """Static slot count for :func:`bsv_mesh_edgescan_diff`: (silhouette edge, view) pairs × margin.

    Counted on the given (concrete) pose over all T·P views, times ``margin``, rounded up to a
    multiple of 32. Silhouettes of closed meshes hold a small share of the edges per view (the
    bunny at shell 1.5: 12 % on average).
    """
    if not (isinstance(margin, int | float) and margin >= 1.0):
        raise ValueError(f"margin must be a number >= 1, got {margin!r}")
    vertices, faces, table = _prepare(vertices, faces, edge_table)
    _, _, _, front = _local(vertices, faces, grid=tuple(grid), shell=float(shell))
    count = int(jnp.sum(_silhouette_mask(front, table.t1, table.t2)))
    return min(_round_up(max(1, math.ceil(count * margin)), _WORD), int(table.a.shape[0]) * grid[0] * grid[1])


def _default_grad_slots(table, grid):
    """Generous count when the pose is unknown: 30 % of all (edge, view) pairs (the bunny uses 12 %)."""
    return _round_up(math.ceil(0.3 * table.num_edges * grid[0] * grid[1]), _WORD)


# --------------------------------------------------------------------------------------------
# the tangent
# --------------------------------------------------------------------------------------------


def _slot_terms(vertices, faces, table, rings, occ, *, grid, directions, shell, slots, nodes):
    """Primal per-slot and per-node terms of the boundary integral (no derivative flows here).

    Returns ``va, vb`` (S,) vertex ids, ``view`` (S,), ``normal`` (S, 3) = F n₃ (world),
    ``corner`` (S, nodes, 4) flat corner indices, ``ca, cb`` (S, nodes, 4) splat weights of
    ``n₃·δq_a`` and ``n₃·δq_b``, and the silhouette pair count ().
    """
    ny, nx = directions
    g = grid[0] * grid[1]
    dtype = vertices.dtype
    tan_a = 1.0 / math.sqrt(shell * shell - 1.0)
    dx, dy = 2.0 * tan_a / nx, 2.0 * tan_a / ny
    px, py, qz, front = _local(vertices, faces, grid=grid, shell=shell)
    sil = _silhouette_mask(front, table.t1, table.t2)
    pos, total = _compact(_pack(sil.reshape(-1)), slots)
    pos = jnp.where(pos >= 0, pos, (table.a.shape[0] - 1) * g)  # empty: view 0 of a padding edge
    edge, view = pos // g, pos % g
    va, vb = table.a[edge], table.b[edge]
    fa, fb = va * g + view, vb * g + view
    pxf, pyf, qzf = px.reshape(-1), py.reshape(-1), qz.reshape(-1)
    ax, ay, az = pxf[fa], pyf[fa], qzf[fa]
    bx, by, bz = pxf[fb], pyf[fb], qzf[fb]
    w = jnp.where(front.reshape(-1)[table.t1[edge] * g + view], 1.0, -1.0).astype(dtype)
    n3 = jnp.stack([ay - by, bx - ax, ax * by - ay * bx], axis=-1)  # (A, 1) × (B, 1)

    # nodes along the image segment: image coordinates (S, nodes), and the same in pixel units
    # (u along x, v along y; pixel corners at integers)
    t_k, w_k = (jnp.asarray(x, dtype) for x in _np_nodes(nodes))
    node_x = ax[:, None] + t_k * (bx - ax)[:, None]
    node_y = ay[:, None] + t_k * (by - ay)[:, None]
    u, v = (node_x + tan_a) / dx, (node_y + tan_a) / dy

    # visibility: the pixel one pixel beyond the node along the outward normal w·n₃_xy is free
    nu, nv = w * n3[:, 0] * dx, w * n3[:, 1] * dy  # the normal in pixel units
    length = jnp.sqrt(nu * nu + nv * nv)
    ok = length > 0.0
    inv = jnp.where(ok, 1.0 / jnp.where(ok, length, 1.0), 0.0)  # double where: zero-length edges
    jo = jnp.floor(u + (nu * inv)[:, None]).astype(jnp.int32)
    io = jnp.floor(v + (nv * inv)[:, None]).astype(jnp.int32)
    inside = (jo >= 0) & (jo < nx) & (io >= 0) & (io < ny)
    flat = view[:, None] * (nx * ny) + jnp.clip(jo, 0, nx - 1) * ny + jnp.clip(io, 0, ny - 1)
    chi = ~(occ.reshape(-1)[flat] & inside)  # occ is column-major (G, N_x, N_y)
    # ... and no face around the edge's end points covers the node (the contour of a fine mesh
    # zigzags: edges folded back under their neighbours by less than a pixel, which the image
    # cannot see). All vertices lie in front of p, so a face covers a direction iff the node lies
    # inside its projected triangle.
    ring = jnp.asarray(rings)[edge] * g + view[:, None, None]  # (S, K, 3) flat (vertex, view) ids
    rx, ry = pxf[ring], pyf[ring]

    def side(i, j):  # (S, nodes, K): orientation of the node against the ring face's edge i -> j
        ex, ey = (rx[:, :, j] - rx[:, :, i])[:, None], (ry[:, :, j] - ry[:, :, i])[:, None]
        return ex * (node_y[..., None] - ry[:, None, :, i]) - ey * (node_x[..., None] - rx[:, None, :, i])

    s0, s1, s2 = side(0, 1), side(1, 2), side(2, 0)
    covered = ((s0 > 0) & (s1 > 0) & (s2 > 0)) | ((s0 < 0) & (s1 < 0) & (s2 < 0))
    chi = chi & ~jnp.any(covered, axis=-1)

    # bilinear splat onto the corner grid (G, N_y + 1, N_x + 1)
    j0 = jnp.clip(jnp.floor(u), 0, nx - 1)
    i0 = jnp.clip(jnp.floor(v), 0, ny - 1)
    fu, fv = jnp.clip(u - j0, 0.0, 1.0), jnp.clip(v - i0, 0.0, 1.0)
    j0, i0 = j0.astype(jnp.int32), i0.astype(jnp.int32)
    base = view[:, None] * ((ny + 1) * (nx + 1)) + i0 * (nx + 1) + j0
    corner = jnp.stack([base, base + 1, base + nx + 1, base + nx + 2], axis=-1)  # (S, nodes, 4)
    bil = jnp.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], axis=-1)
    k = (w[:, None] * w_k * chi.astype(dtype))[..., None] * bil  # (S, nodes, 4)
    ca = k * ((1.0 - t_k)[:, None] / az[:, None, None])
    cb = k * (t_k[:, None] / bz[:, None, None])

    _, frames = bsv_sample_points(jnp.zeros(3, dtype), jnp.ones((), dtype), grid, shell)
    frames = frames.reshape(-1, 3, 3)
    normal = jnp.einsum("sij,sj->si", frames[view], n3)  # F n₃: n₃·Fᵀδ = (F n₃)·δ
    return va, vb, view, normal, corner, ca, cb, total


def _apply(terms, corner_basis, dvertices, dpoints, *, views):
    """The linear part: dV (G, n²) from the vertex motion (V, 3) and the viewpoint motion (G, 3)."""
    va, vb, view, normal, corner, ca, cb = terms
    dp = dpoints[view]
    ta = jnp.sum(normal * (dvertices[va] - dp), axis=-1)  # n₃·δq_a (S,)
    tb = jnp.sum(normal * (dvertices[vb] - dp), axis=-1)
    s = ca * ta[:, None, None] + cb * tb[:, None, None]  # (S, nodes, 4)
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
    grad_slots: int | None = None,
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
        grad_slots: static number of (silhouette edge, view) slots of the derivative, from
            :func:`edgescan_grad_slots` on the rest pose; None: measured on ``vertices`` when they
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
            grad_slots = edgescan_grad_slots(vertices, faces_np, grid, shell, margin=1.25, edge_table=table)
    if isinstance(grad_slots, bool) or not isinstance(grad_slots, int | np.integer) or grad_slots < 1:
        raise ValueError(f"grad_slots must be a positive int, got {grad_slots!r}")
    grad_slots = min(_round_up(int(grad_slots), _WORD), int(table.a.shape[0]) * grid[0] * grid[1])
    n, nodes = int(n), int(nodes)
    views = grid[0] * grid[1]
    basis_w = _basis_weights(directions, shell, n, vertices.dtype)
    rings = _ring_faces(faces_np, table)

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
        *terms, total = _slot_terms(
            x0,
            faces_np,
            table,
            rings,
            occ,
            grid=grid,
            directions=directions,
            shell=shell,
            slots=grad_slots,
            nodes=nodes,
        )
        out = eqx.error_if(out, total > grad_slots, _GRAD_OVERFLOW)
        _, dpoints = jax.jvp(lambda v: _sample_points(v, grid, shell)[0], (x0,), (dx,))
        corner_basis = _corner_basis(directions, shell, n, out.dtype)
        dout = _apply(terms, corner_basis, dx, dpoints, views=views)
        return out, dout.astype(out.dtype)

    return bsv(vertices).reshape(*grid, n * n)
