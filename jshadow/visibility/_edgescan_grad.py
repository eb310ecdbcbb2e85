"""Vertex derivative of the edge-scan BSV in the image plane, with exact silhouette visibility.

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
edges bound Ω. Their visibility χ at a node is decided exactly, without casting rays: the layer
count of the forward pass is the winding number of the projected silhouette, which changes by ±1
exactly where a silhouette edge is crossed, so the count just beside a node q follows from the
count at the centre C of q's pixel plus the signed crossings of the segment C → q by the other
silhouette edges of that pixel; q lies on the boundary of Ω iff the count on one side of its edge
is 0 (:func:`_winding_chi`). An earlier version read χ off the sampled occlusion image (the pixel
beyond the node) plus a test against the faces around the edge: contours of finely tessellated
meshes zigzag below the pixel size, and that made the bunny's derivative a third too large.

Layout of the computation (the tangent is linear, so JAX transposes it for reverse mode):

1. all (silhouette edge, view) pairs, packed and compacted into ``S`` static slots over all views,
   grouped by view (the same compaction as the edge-scan's, but not restricted to edges that
   cross a pixel column);
2. the pixel lists: each pair enters every pixel of its projected bounding box (``Q`` static
   entries, the bunny: 2.1 per pair at 32²), sorted by (view, pixel) as one packed int32 key;
3. per Gauss–Legendre node t_k its pixel's list, read in tiers (16 entries for every node; the
   next 32 and then the rest, up to the static ``window``, for the nodes of longer lists,
   compacted), the crossing test and χ (on XLA:CPU in blocks, of which those holding only the
   padding of the static sizes are skipped); the visible nodes (the bunny: 20 % of its silhouette
   nodes) are compacted into ``N`` static node slots;
4. per node the scalar ``s = W_k χ_k w (α_k n₃·δq_a + β_k n₃·δq_b)`` with primal weights, splatted
   bilinearly onto the (N_y + 1) × (N_x + 1) pixel-corner grid of its view;
5. ``dV = −D @ (Y J)`` with the corner values of ``Y_i J`` (one matrix product for all views).

In reverse mode step 5 becomes one product of the cotangent with the corner table (the cotangent
as a function on the image), step 4 a bilinear lookup per node, and the vertex gradient a
scatter onto the two vertices of each node: nothing of size (slots × n²) is formed. Each step is a
:func:`~jshadow.visibility._edgescan.staged` computation, so that XLA does not fuse the gathers of
one step into the next and recompute them per element. All static sizes are measured on concrete
poses (:func:`edgescan_grad_slots`); an overflow raises at run time, also under
``jax.jit(jax.grad(...))``.

Accuracy (tests/test_edgescan_grad.py; BENCHMARKS.md "BSV gradients"): χ equals the winding number
of all silhouette edges of the view at every node (up to float rounding: 1 node of 273010 for the
bunny); what remains is quadrature: 2 Gauss–Legendre nodes per projected edge and the bilinear
``Y J`` table. On convex meshes: 3.5e-4 relative at 64² against converged differences; on
bunny_small (self-occluding, 1000 faces) against the ray-cast derivative at 32 nodes: cosine
0.9987–0.9989 and norm ratio 0.95–1.00 at 32² and 2 nodes, 1.1–1.8 % apart at 128² and 8 nodes.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import lru_cache, partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike, Float, Int

from .._sorting import argsort_keys, sort_keys
from ..sh._grids import _np_sh_basis
from ._bsv import bsv_sample_points
from ._bsv_grad import _sample_points  # sample points p = c(X) + shell·r(X)·u and frames
from ._edgescan import (
    _WORD,
    EdgeTable,
    _basis_weights,
    _cached_edge_table,
    _check_slots,
    _compact,
    _compute,
    _cumsum,
    _local_coords,
    _pack,
    _prepare,
    _project_sh,
    _resolve,
    _round_up,
    _stage_counts,
    _stage_views,
    always,
    staged,
)

__all__ = ["bsv_and_coverage_edgescan_diff", "bsv_mesh_edgescan_diff", "edgescan_grad_slots"]


_GRAD_OVERFLOW = (
    "edge-scan gradient slots overflowed: pass a larger grad_slots (see edgescan_grad_slots); "
    "silhouette edges would be missing from the derivative. Through jshadow.render / render_at, "
    "whose sizes are measured on concrete poses of the same faces: differentiate once at a concrete "
    "pose as deformed as the traced ones (its sizes are measured and the largest kept)"
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


@lru_cache(maxsize=16)
def _np_nodes(nodes):
    x, w = np.polynomial.legendre.leggauss(nodes)
    return 0.5 * (x + 1.0), 0.5 * w  # on [0, 1]


def _cell(x, tan_a, n):
    """Pixel index along one image axis of the image coordinate ``x`` (clipped to the image)."""
    return jnp.clip(jnp.floor((x + tan_a) * (n / (2.0 * tan_a))), 0, n - 1).astype(jnp.int32)


@lru_cache(maxsize=16)
def _np_centres(n, tan_a):
    """Image coordinates of the ``n`` pixel centres along one axis (one table, so that every
    computation that compares with a pixel centre sees the same numbers)."""
    return -tan_a + (np.arange(n) + 0.5) * (2.0 * tan_a / n)


def _centre(i, tan_a, n, dtype):
    """Image coordinate of the centre of pixel ``i`` (int) along an axis of ``n`` pixels."""
    with jax.ensure_compile_time_eval():
        table = jnp.asarray(_np_centres(n, tan_a), dtype)
    return table[i]


def _orient(ax, ay, bx, by, x, y):
    """``(B − A) × (X − A)``: positive when X lies to the left of the line A → B."""
    return (bx - ax) * (y - ay) - (by - ay) * (x - ax)


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
    # view-major (G, E_pad): the compacted pairs come out grouped by view; padding edges have
    # t1 = t2 and are never silhouettes
    return (front[t1] != front[t2]).T


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
    slots: tuple[int, int, int, int] | None = None,
) -> tuple[int, int, int, int, int, int]:
    """Static sizes ``(pairs, nodes, pieces, window, long, longer)`` for
    :func:`bsv_mesh_edgescan_diff`'s ``grad_slots``.

    ``pairs``: the (silhouette edge, view) pairs over all T·P views; ``nodes``: the Gauss–Legendre
    nodes on them that are visible (the only ones the linear part carries; the bunny at shell 1.5
    and 32²: 20 % of its nodes); ``pieces``: the (pair, pixel) entries of the pixel lists (every
    pixel of each projected edge's bounding box); ``window``: the longest pixel list; ``long`` and
    ``longer``: the nodes whose pixel list is longer than 16 and 48 entries. Counted on the given
    (concrete) pose, times ``margin``, rounded up to a multiple of 32 (the window: of 8).
    Silhouettes of closed meshes hold a small share of the edges per view (the bunny: 12 %).
    ``slots``: the edge-scan slots of the forward pass that gives the layer counts (as in
    :func:`bsv_mesh_edgescan`; None: measured on the first pose of this topology). Measuring several
    poses with the same ``slots`` (the largest over them) compiles that pass once.
    """
    if not (isinstance(margin, int | float) and margin >= 1.0):
        raise ValueError(f"margin must be a number >= 1, got {margin!r}")
    vertices, faces_j, table = _prepare(vertices, faces, edge_table)
    grid, directions, shell = tuple(grid), tuple(directions), float(shell)
    _, _, _, front = _local(vertices, faces_j, grid=grid, shell=shell)
    count = int(jnp.sum(_silhouette_mask(front, table.t1, table.t2)))
    cap = int(table.a.shape[0]) * grid[0] * grid[1]
    # the counting passes run with sizes rounded up to powers of two, so that the poses of one
    # mesh share their compilations (any size at least the count gives the same counts)
    pairs = min(_pow2(count), _round_up(cap, _WORD))
    kw = dict(grid=grid, directions=directions, shell=shell, slots=pairs, nodes=nodes)
    n_pieces, longest = (int(x) for x in _count_pieces(vertices, faces_j, table, **kw))
    counts = _counts_of(vertices, faces_j, table, grid, directions, shell, slots)
    live, n_long, n_longer = (
        int(x)
        for x in _count_live(
            vertices,
            faces_j,
            table,
            counts,
            **kw,
            piece_slots=_pow2(n_pieces),
            window=max(256, _pow2(longest)),  # (256: poses of one mesh share the compilation)
            long_slots=(pairs * nodes, pairs * nodes),
        )
    )

    def grow(x, m):
        return _round_up(max(1, math.ceil(x * margin)), m)

    return (
        min(grow(count, _WORD), cap),
        min(grow(live, _WORD), cap * nodes),
        grow(n_pieces, _WORD),
        grow(longest, 8),
        min(grow(n_long, _WORD), cap * nodes),
        min(grow(n_longer, _WORD), cap * nodes),
    )


def _pow2(x):
    """The smallest power of two >= max(x, 32)."""
    return 1 << max(5, (int(x) - 1).bit_length())


def _counts_of(vertices, faces, table, grid, directions, shell, slots=None):
    """Layer counts (G, N_x, N_y) of one edge-scan pass (concrete pose)."""
    vertices, _, table, grid, directions, shell, slots = _resolve(
        vertices, faces, grid, directions, shell, table, slots
    )
    diff, _, _, _ = _compute(vertices, faces, table, grid, directions, shell, slots)
    return _stage_counts(diff)


@partial(jax.jit, static_argnames=("grid", "directions", "shell", "slots", "nodes"))
def _count_pieces(vertices, faces, table, **kw):
    """(pair, pixel) entries and the longest pixel list, without forming either list."""
    pair, filled, _, _ = _pairs(vertices, faces, table, **kw)
    ny, nx = kw["directions"]
    views = kw["grid"][0] * kw["grid"][1]
    c0, c1, r0, r1 = _boxes(pair, filled, kw["directions"], kw["shell"])
    n_pieces = jnp.sum(jnp.where(filled, (c1 - c0 + 1) * (r1 - r0 + 1), 0))
    # occupancy per pixel: 2-D difference array of the boxes, prefix-summed along both axes
    one = filled.astype(jnp.int32)
    occ = jnp.zeros((views, ny + 1, nx + 1), jnp.int32)
    for r, c, s in ((r0, c0, 1), (r0, c1 + 1, -1), (r1 + 1, c0, -1), (r1 + 1, c1 + 1, 1)):
        occ = occ.at[pair["view"], r, c].add(s * one)
    occ = jnp.cumsum(jnp.cumsum(occ, axis=1), axis=2)
    return n_pieces, jnp.max(occ)


@partial(
    jax.jit,
    static_argnames=("grid", "directions", "shell", "slots", "nodes", "piece_slots", "window", "long_slots"),
)
def _count_live(vertices, faces, table, counts, **kw):
    """Visible nodes and nodes with long pixel lists (one compiled call: eagerly, its many small
    steps each compile)."""
    _, chi, _, _, (_, n_long) = _visible_nodes(vertices, faces, table, counts, **kw)
    return jnp.sum(chi), *n_long


def _check_grad_slots(grad_slots, nodes, directions, views):
    """``grad_slots`` as ``(pairs, nodes, pieces, window, long, longer)`` ints.

    An int gives the pairs only, with a node slot for every node, a window of 256 and
    ``4·pairs + 2·views·N_y·N_x`` pixel entries: the entries of a pair are the pixels of its
    bounding box, ``(|Δcol| + 1)(|Δrow| + 1)``; short edges of fine meshes take 1–4, and the long
    edges of a coarse silhouette cover about as many pixels as the image has, once or twice.
    """

    def positive(x):
        return not isinstance(x, bool) and isinstance(x, int | np.integer) and x >= 1

    if positive(grad_slots):
        every = int(grad_slots) * int(nodes)
        pieces = 4 * int(grad_slots) + 2 * int(views) * int(directions[0]) * int(directions[1])
        return int(grad_slots), every, pieces, 256, every, every
    if isinstance(grad_slots, tuple | list) and len(grad_slots) == 6 and all(positive(x) for x in grad_slots):
        return tuple(int(x) for x in grad_slots)
    raise ValueError(
        "grad_slots must be a positive int or six of them (pairs, nodes, pieces, window, long, longer), "
        f"got {grad_slots!r}"
    )


def _rounded_grad_slots(grad_slots, cap, nodes, directions, views):
    """``grad_slots`` checked, rounded up to whole words and capped (``cap``: every (edge, view)
    pair): ``(pairs, nodes, pieces, window, (long, longer))`` as the derivative uses them."""
    pairs, live, pieces, window, *longs = _check_grad_slots(grad_slots, nodes, directions, views)
    pairs = min(_round_up(pairs, _WORD), cap)
    every = pairs * nodes
    longs = tuple(min(_round_up(x, _WORD), every) for x in longs)
    return pairs, min(_round_up(live, _WORD), every), _round_up(pieces, _WORD), window, longs


def _measured(measure):
    """``measure()`` evaluated eagerly (outside any trace), also inside a derivative rule being traced;
    it must close over concrete values only."""
    with jax.core.eval_context():
        return measure()


def _default_grad_slots(table, grid):
    """Generous count when the pose is unknown: 30 % of all (edge, view) pairs (the bunny uses 12 %)."""
    return _round_up(math.ceil(0.3 * table.num_edges * grid[0] * grid[1]), _WORD)


# --------------------------------------------------------------------------------------------
# node visibility: the winding number of the silhouette, exactly
# --------------------------------------------------------------------------------------------


def _pairs(vertices, faces, table, *, grid, directions, shell, slots, nodes):
    """Per (silhouette edge, view) slot, grouped by view: the image-space quantities.

    Returns ``pair`` (a dict of (S,) arrays: edge, view, end points' vertex ids, image coordinates
    and depths, the facing weight w, n₃, and the nodes' image coordinates (S, nodes)), ``filled``
    (S,) bool, the silhouette pair count () and the (vertex, view) image coordinates ``px, py``
    (V, G). Each step is a :func:`staged` computation.
    """
    g = grid[0] * grid[1]
    e_pad = table.a.shape[0]
    stage = partial(staged, always(vertices))
    px, py, qz, front = stage(partial(_local, grid=grid, shell=shell), vertices, faces)
    sil = stage(_silhouette_mask, front, table.t1, table.t2)
    pos, total = stage(lambda m: _compact(_pack(m.reshape(-1)), slots), sil)

    def gather(pos, px, py, qz, front, a, b, t1):
        filled = pos >= 0
        pos = jnp.where(filled, pos, (g - 1) * e_pad + e_pad - 1)  # empty: a padding edge
        view, edge = pos // e_pad, pos % e_pad
        va, vb = a[edge], b[edge]
        fa, fb = va * g + view, vb * g + view
        pxf, pyf, qzf = px.reshape(-1), py.reshape(-1), qz.reshape(-1)
        ax, ay, az = pxf[fa], pyf[fa], qzf[fa]
        bx, by, bz = pxf[fb], pyf[fb], qzf[fb]
        w = jnp.where(front.reshape(-1)[t1[edge] * g + view], 1.0, -1.0).astype(px.dtype)
        n3 = jnp.stack([ay - by, bx - ax, ax * by - ay * bx], axis=-1)  # (A, 1) × (B, 1)
        t_k = jnp.asarray(_np_nodes(nodes)[0], ax.dtype)  # nodes along the image segment (S, nodes)
        node_x = ax[:, None] + t_k * (bx - ax)[:, None]
        node_y = ay[:, None] + t_k * (by - ay)[:, None]
        p = dict(edge=edge, view=view, va=va, vb=vb, ax=ax, ay=ay, az=az, bx=bx, by=by, bz=bz, w=w, n3=n3)
        return dict(p, node_x=node_x, node_y=node_y), filled

    pair, filled = stage(gather, pos, px, py, qz, front, table.a, table.b, table.t1)
    return pair, filled, total, (px, py)


def _boxes(pair, filled, directions, shell):
    """Pixel bounding box ``c0, c1, r0, r1`` (S,) of each projected edge (columns along x)."""
    ny, nx = directions
    tan_a = 1.0 / math.sqrt(shell * shell - 1.0)
    ax, ay, bx, by = (pair[k] for k in ("ax", "ay", "bx", "by"))
    c0, c1 = _cell(jnp.minimum(ax, bx), tan_a, nx), _cell(jnp.maximum(ax, bx), tan_a, nx)
    r0, r1 = _cell(jnp.minimum(ay, by), tan_a, ny), _cell(jnp.maximum(ay, by), tan_a, ny)
    return c0, c1, r0, r1


def _small_divmod(a: Int[Array, "..."], b: Int[Array, "..."], bound: int) -> tuple[Array, Array]:
    """``(a // b, a % b)`` of int32 ``0 ≤ a < bound``, ``b ≥ 1``. For ``bound ≤ 2^20`` through a float32
    quotient: ``(a + 0.5) / b`` is computed within ``2^-3 / b`` of its value, less than its ``0.5 / b``
    margin to the next integer, so its floor is exact (integer division was 5 of the 9 ms of the
    bunny's pixel-list expansion, BENCHMARKS.md); integer division above that bound."""
    if bound > 1 << 20:
        return a // b, a % b
    quo = jnp.floor((a.astype(jnp.float32) + 0.5) / b.astype(jnp.float32)).astype(a.dtype)
    return quo, a - quo * b


def _pixel_lists(pair, filled, *, directions, shell, views, piece_slots, window):
    """The silhouette edges of each pixel: every (pair, pixel) of the edges' bounding boxes, sorted
    by (view, pixel), as a table (Q + window, 5) of :func:`_entries` and per pixel its
    ``start`` and length ``size`` ((G·N_y·N_x,) each, row-major pixels); and the overflow flag.

    The entries are expanded in the order of the pairs (grouped by view) and sorted by one int32 key
    (view, pixel, entry within the view) (:func:`jshadow._sorting.sort_keys`: NumPy's sort on the
    CPU): a sort of one operand is several times faster than an argsort. The (view, pixel) part
    takes ``b = ⌈log₂(G·N_y·N_x + 1)⌉`` bits and the entry index the other ``31 − b`` (the default
    12×20 views at 32²: 8192 entries per view); a view with more entries sets the overflow flag.
    When fewer than 12 bits would remain, the slower stable argsort of the keys is used instead.
    """
    ny, nx = directions
    q = piece_slots
    c0, c1, r0, r1 = _boxes(pair, filled, directions, shell)
    wid = c1 - c0 + 1
    k = jnp.where(filled, wid * (r1 - r0 + 1), 0)
    cum = _cumsum(k)
    first = cum - k
    total = cum[-1]
    # entry i belongs to the last pair whose first entry is at or before i
    mark = jnp.zeros(q, jnp.int32).at[first].add(1, mode="drop")
    owner = jnp.clip(_cumsum(mark) - 1, 0, k.shape[0] - 1)
    i = jnp.arange(q, dtype=jnp.int32)
    valid = i < total
    local = i - first[owner]
    w_o = wid[owner]
    quo, rem = _small_divmod(local, w_o, nx * ny)  # a box holds fewer than nx·ny entries
    row, col = r0[owner] + quo, c0[owner] + rem
    view = pair["view"][owner]
    cells = views * ny * nx
    key = jnp.where(valid, (view * ny + row) * nx + col, cells)
    key_bits = int(cells).bit_length()
    idx_bits = 31 - key_bits
    if idx_bits >= 12:
        per_view = jnp.zeros(views, jnp.int32).at[pair["view"]].add(k)
        view_first = _cumsum(per_view) - per_view
        idx = i - view_first[view]
        packed = jnp.where(valid, (key << idx_bits) | idx, jnp.iinfo(jnp.int32).max)
        s = sort_keys(packed)
        skey = s >> idx_bits
        sview = jnp.minimum(skey // (ny * nx), views - 1)
        sowner = owner[jnp.clip(view_first[sview] + (s & ((1 << idx_bits) - 1)), 0, q - 1)]
        overflow = jnp.max(jnp.where(valid, idx, 0)) >= (1 << idx_bits)
    else:
        perm = argsort_keys(key.astype(jnp.uint32))
        skey, sowner = key[perm], owner[perm]
        overflow = jnp.zeros((), bool)
    table = _entries(pair, skey, sowner, directions=directions, shell=shell, window=window)
    # each pixel's run in the sorted keys, from its first and last entries (padding keys, >= cells,
    # land in the dropped last slot): no pass over all G·N_y·N_x pixels but the zeros
    pix = jnp.minimum(skey, cells)
    head = jnp.concatenate([jnp.ones(1, bool), pix[1:] != pix[:-1]])
    tail = jnp.concatenate([pix[1:] != pix[:-1], jnp.ones(1, bool)])
    start = jnp.zeros(cells + 1, jnp.int32).at[jnp.where(head, pix, cells)].set(i)[:cells]
    end = jnp.zeros(cells + 1, jnp.int32).at[jnp.where(tail, pix, cells)].set(i + 1)[:cells]
    return table, start, end - start, overflow | (total > q)


def _entries(pair, skey, sowner, *, directions, shell, window):
    """The sorted list entries as rows ``A'_x, A'_y, B'_x, B'_y, c·(slot + 1)`` (Q + window, 5) for
    :func:`_crossings`: the end points relative to the centre C of the entry's pixel, ordered so that
    C lies to the right of A' → B' (``orient(A', B', 0) < 0``), and the count change ``c`` on
    crossing from C's side to the other, ``−w'·sgn orient(A, B, C)`` (0 when C lies on the line: such
    an edge never counts as crossed), times the entry's pair slot + 1 (exact in float32 below 2^24
    slots), so that a node can leave its own pair out. ``window`` zero rows past the end keep every
    node's window of the list in bounds."""
    if pair["ax"].shape[0] >= 1 << 24:
        raise ValueError("more than 2^24 silhouette pair slots: their ids are not exact in float32")
    ny, nx = directions
    tan_a = 1.0 / math.sqrt(shell * shell - 1.0)
    dtype = pair["ax"].dtype
    col, row = skey % nx, (skey // nx) % ny  # (padding keys: any pixel; masked by the list sizes)
    cx, cy = _centre(col, tan_a, nx, dtype), _centre(row, tan_a, ny, dtype)
    ax, ay = pair["ax"][sowner] - cx, pair["ay"][sowner] - cy
    bx, by = pair["bx"][sowner] - cx, pair["by"][sowner] - cy
    side = jnp.sign(_orient(ax, ay, bx, by, 0.0, 0.0))
    flip = side > 0
    ax, bx = jnp.where(flip, bx, ax), jnp.where(flip, ax, bx)
    ay, by = jnp.where(flip, by, ay), jnp.where(flip, ay, by)
    change = -pair["w"][sowner] * side * (sowner + 1).astype(dtype)
    data = jnp.stack([ax, ay, bx, by, change], axis=-1)
    return jnp.concatenate([data, jnp.zeros((window, 5), dtype)])


_TIERS = (16, 32)  # pixel-list entries every node reads, then the nodes of longer lists; the rest
# of the longest lists (over 48 entries) is read by their nodes alone


def _crossings(padded, st, sz, sid, ux, uy, *, lo, width):
    """``Σ w'·(sgn s'(q) − sgn s'(C))/2`` over the list entries ``lo … lo + width − 1`` of each
    node's pixel that cross the segment C → q (and are not the node's own pair ``sid``): (M,).
    ``u = q − C`` and the entries (:func:`_entries`) are relative to the pixel centre C, each edge
    oriented with C on its right (``s'(C) < 0``), so a crossing is ``s'(q) > 0`` with the end points
    on either side of the line C → q, and it changes the count by the entry's ``c``."""
    cols = padded.shape[1]
    zero = jnp.zeros((), st.dtype)
    win = jax.vmap(lambda s0: lax.dynamic_slice(padded, (s0 + lo, zero), (width, cols)))(st)
    wx0, wy0, wx1, wy1, tagged = (win[..., m] for m in range(5))
    own = (sid + 1).astype(ux.dtype)[:, None]
    ok = (lo + jnp.arange(width, dtype=sz.dtype) < sz[:, None]) & (jnp.abs(tagged) != own)
    xq, yq = ux[:, None], uy[:, None]
    s_q = _orient(wx0, wy0, wx1, wy1, xq, yq)
    d_a = xq * wy0 - yq * wx0  # orient(C, q, A')
    d_b = xq * wy1 - yq * wx1
    cross = ok & (s_q > 0) & (d_a * d_b < 0)
    return jnp.sum(jnp.where(cross, jnp.sign(tagged), 0.0), axis=-1)


def _live_blocks(rows: int) -> int:
    """Blocks that :func:`_crossings_live` splits ``rows`` into (1 = no split): on XLA:CPU one per
    32768 rows, at most 8, so that a block past the live rows is skipped by a conditional. The
    airplane's node visibility took 32–33 instead of 55–68 ms with 8 blocks (its 1.5× static margins
    leave a third of the rows empty). Elsewhere 1: on a GPU a conditional may cost a host round trip,
    and the split was not measured there."""
    return max(1, min(8, rows // 32768)) if jax.default_backend() == "cpu" else 1


def _crossings_live(n_live, table, st, sz, sid, ux, uy, *, lo, width):
    """:func:`_crossings` of rows of which only the first ``n_live`` (a run-time count) are used: the
    rest are padding, whose values the caller masks. Computed in blocks; a block wholly past
    ``n_live`` is not computed (zeros)."""
    m = ux.shape[0]
    blocks = _live_blocks(m)
    if blocks == 1:
        return _crossings(table, st, sz, sid, ux, uy, lo=lo, width=width)
    size = -(-m // blocks)

    def run(args):
        return _crossings(table, *args, lo=lo, width=width)

    def skip(args):
        return jnp.zeros_like(args[3])

    out = []
    for first in range(0, m, size):
        args = tuple(a[first : first + size] for a in (st, sz, sid, ux, uy))
        out.append(lax.cond(first < n_live, run, skip, args))
    return jnp.concatenate(out)


def _winding_chi(pair, filled, counts, table, start, size, *, directions, shell, window, long_slots):
    """Visibility χ (S, nodes) of each node: the silhouette bounds the occluded region there.

    The forward pass's layer count at pixel centres is the winding number ``c`` of the projected
    silhouette (module docstring of :mod:`jshadow.visibility._edgescan`); it changes by ``±w'``
    exactly where a silhouette edge is crossed. A node q on edge e in pixel (i, j) gets its count
    from the pixel centre C: ``c(q⁻) = c(C) + Σ w'·(sgn s'(q) − sgn s'(C))/2`` over the edges e' ≠ e
    of the pixel's list that cross the segment C → q (``s'`` the side of e'), which lies inside the
    pixel. Crossing e itself changes the count by ``−w·sgn s_e(C)``; q is on the boundary of the
    occluded region iff one of the two counts is 0. Exact up to rounding (a pixel centre on an
    edge), unlike any test on the sampled image.

    Every node reads the first 16 entries of its pixel's list; the nodes of longer lists (the bunny:
    23 % at 32²) are compacted into ``long_slots[0]`` slots and read the next 32, and those of lists
    longer than 48 into ``long_slots[1]`` slots that read the rest, up to ``window``. Returns χ, the
    longest list met and the node counts of the two tiers (overflow when they exceed the sizes).
    """
    ny, nx = directions
    tan_a = 1.0 / math.sqrt(shell * shell - 1.0)
    s_, k_ = pair["node_x"].shape
    sid = jnp.broadcast_to(jnp.arange(s_, dtype=jnp.int32)[:, None], (s_, k_)).reshape(-1)
    x, y = pair["node_x"].reshape(-1), pair["node_y"].reshape(-1)
    view = pair["view"][sid]
    col, row = _cell(x, tan_a, nx), _cell(y, tan_a, ny)
    key = (view * ny + row) * nx + col
    st, sz = start[key], size[key]
    dtype = x.dtype
    cx, cy = _centre(col, tan_a, nx, dtype), _centre(row, tan_a, ny, dtype)
    ux, uy = x - cx, y - cy
    # every node reads the first tier; the nodes of longer lists are compacted for the next ones
    # (nodes of padding pairs are no silhouette nodes: left out, whatever list their pixel has)
    real = filled[sid]
    # the filled pairs are a prefix of the slots (compacted), so the real nodes are the first ones
    n_real = jnp.sum(filled.astype(jnp.int32)) * k_
    lo = min(_TIERS[0], window)
    part = _crossings_live(n_real, table, st, sz, sid, ux, uy, lo=0, width=lo)
    n_tier = []
    for width, slots in zip((_TIERS[1], window), long_slots, strict=True):
        width = min(width, window - lo)
        if width <= 0:
            n_tier.append(jnp.zeros((), jnp.int32))
            continue
        pos, n = _compact(_pack((sz > lo) & real), slots)
        n_tier.append(n)
        live, i = pos >= 0, jnp.maximum(pos, 0)
        rest = _crossings_live(n, table, st[i], sz[i], sid[i], ux[i], uy[i], lo=lo, width=width)
        part = part.at[i].add(jnp.where(live, rest, 0.0))
        lo += width
    c_near = counts[view, col, row] + part
    ax, ay, bx, by, w = (pair[m][sid] for m in ("ax", "ay", "bx", "by", "w"))
    c_far = c_near - w * jnp.sign(_orient(ax, ay, bx, by, cx, cy))
    chi = ((c_near == 0) | (c_far == 0)) & real
    return chi.reshape(s_, k_), jnp.max(sz), tuple(n_tier)


def _visible_nodes(
    vertices, faces, table, counts, *, grid, directions, shell, slots, nodes, piece_slots, window, long_slots
):
    """``pair``, χ (S, nodes), the pair count (), overflow of the pixel lists () (staged steps)."""
    views = grid[0] * grid[1]
    pair, filled, total, _ = _pairs(
        vertices, faces, table, grid=grid, directions=directions, shell=shell, slots=slots, nodes=nodes
    )
    stage = partial(staged, always(vertices))
    lists = partial(
        _pixel_lists, directions=directions, shell=shell, views=views, piece_slots=piece_slots, window=window
    )
    ptable, start, size, over = stage(lists, pair, filled)
    chi_fn = partial(_winding_chi, directions=directions, shell=shell, window=window, long_slots=long_slots)
    chi, longest, n_long = stage(chi_fn, pair, filled, counts.astype(pair["ax"].dtype), ptable, start, size)
    tiers = (n_long[0] > long_slots[0]) | (n_long[1] > long_slots[1])
    return pair, chi, total, over | (longest > window) | tiers, (longest, n_long)


def _slot_terms(
    vertices,
    faces,
    table,
    counts,
    *,
    grid,
    directions,
    shell,
    slots,
    node_slots,
    nodes,
    piece_slots,
    window,
    long_slots,
):
    """Primal per-node terms of the boundary integral (no derivative flows here).

    The visible nodes (:func:`_winding_chi`) are compacted into ``node_slots`` entries. Returns
    ``va, vb`` (N,) vertex ids, ``view`` (N,), ``normal`` (N, 3) = F n₃ (world), ``corner`` (N, 4)
    flat corner indices, ``ca, cb`` (N, 4) splat weights of ``n₃·δq_a`` and ``n₃·δq_b`` (zero on empty
    entries), the silhouette pair count (), the visible node count () and the pixel lists' overflow ().
    """
    ny, nx = directions
    tan_a = 1.0 / math.sqrt(shell * shell - 1.0)
    dx, dy = 2.0 * tan_a / nx, 2.0 * tan_a / ny
    pair, chi, total, over, _ = _visible_nodes(
        vertices,
        faces,
        table,
        counts,
        grid=grid,
        directions=directions,
        shell=shell,
        slots=slots,
        nodes=nodes,
        piece_slots=piece_slots,
        window=window,
        long_slots=long_slots,
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

    def finish(p):
        # bilinear splat onto the corner grid (G, N_y + 1, N_x + 1)
        node_x, node_y = p["node_x"], p["node_y"]
        u, v = (node_x + tan_a) / dx, (node_y + tan_a) / dy
        j0 = jnp.clip(jnp.floor(u), 0, nx - 1)
        i0 = jnp.clip(jnp.floor(v), 0, ny - 1)
        fu, fv = jnp.clip(u - j0, 0.0, 1.0), jnp.clip(v - i0, 0.0, 1.0)
        j0, i0 = j0.astype(jnp.int32), i0.astype(jnp.int32)
        base = p["view"] * ((ny + 1) * (nx + 1)) + i0 * (nx + 1) + j0
        corner = jnp.stack([base, base + 1, base + nx + 1, base + nx + 2], axis=-1)  # (N, 4)
        bil = jnp.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], axis=-1)
        t_k = p["t_k"]
        k = (p["w"] * p["w_k"] * p["live"].astype(node_x.dtype))[:, None] * bil  # (N, 4)
        ca = k * ((1.0 - t_k) / p["az"])[:, None]
        cb = k * (t_k / p["bz"])[:, None]
        _, frames = bsv_sample_points(jnp.zeros(3, node_x.dtype), jnp.ones((), node_x.dtype), grid, shell)
        frames = frames.reshape(-1, 3, 3)
        normal = jnp.einsum("sij,sj->si", frames[p["view"]], p["n3"])  # F n₃: n₃·Fᵀδ = (F n₃)·δ
        return p["va"], p["vb"], p["view"], normal, corner, ca, cb

    return (*stage(finish, node), total, count, over)


# one compiled call for a concrete pose (an eager jax.grad / jax.jvp): op by op, its many small
# steps each compile (a 12-view icosphere's eager derivative took 22 s); traced, it is inlined
_slot_terms_jit = jax.jit(
    _slot_terms,
    static_argnames=(
        "grid",
        "directions",
        "shell",
        "slots",
        "node_slots",
        "nodes",
        "piece_slots",
        "window",
        "long_slots",
    ),
)


def _node_speeds(terms, dvertices, dpoints):
    """``n₃·δq_a`` and ``n₃·δq_b`` (N,) of every node from the vertex motion (V, 3) and the
    viewpoint motion (G, 3): what both linear parts below weight."""
    va, vb, view, normal = terms[:4]
    dp = dpoints[view]
    ta = jnp.sum(normal * (dvertices[va] - dp), axis=-1)
    tb = jnp.sum(normal * (dvertices[vb] - dp), axis=-1)
    return ta, tb


def _apply(terms, corner_basis, speeds, *, views):
    """The linear part: dV (G, n²) from the nodes' speeds (:func:`_node_speeds`)."""
    corner, ca, cb = terms[4:]
    ta, tb = speeds
    s = ca * ta[:, None] + cb * tb[:, None]  # (N, 4)
    c = corner_basis.shape[0]
    d = jnp.zeros(views * c, s.dtype).at[corner.reshape(-1)].add(s.reshape(-1))
    return -(d.reshape(views, c) @ corner_basis)  # V = √(4π)e₀ − O


def _apply_pixels(terms, speeds, *, views, directions, area):
    """The linear part for the coverage images: d cov (G, N_y, N_x) from the same node speeds.

    The coverage of a pixel is the fraction of its area (``area`` in gnomonic units) inside Ω, so
    its change is the boundary integral ``∮ v dl`` over the part of ∂Ω in that pixel, over the
    area: each node's whole term (its bilinear weights summed) goes to the pixel that holds it.
    """
    view, corner, ca, cb = terms[2], *terms[4:]
    ta, tb = speeds
    ny, nx = directions
    s = jnp.sum(ca, -1) * ta + jnp.sum(cb, -1) * tb  # (N,)
    rest = corner[:, 0] % ((ny + 1) * (nx + 1))  # the node's lower-left corner = its pixel (i0, j0)
    pixel = view * (ny * nx) + (rest // (nx + 1)) * nx + rest % (nx + 1)
    d = jnp.zeros(views * ny * nx, s.dtype).at[pixel].add(s)
    return (d / area).reshape(views, ny, nx)


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
    grad_slots: int | tuple[int, ...] | Callable[[], int | tuple[int, ...] | None] | None = None,
    nodes: int = 2,
) -> Float[Array, "T P n2"]:
    """Edge-scan BSV coefficients (T, P, n²) with the silhouette derivative (module docstring).

    The primal is exactly :func:`jshadow.visibility.bsv_mesh_edgescan` ``(...).coeffs``. Its
    ``jax.jvp`` is the image-plane boundary term, including the motion of the sample points
    ``p = c(X) + shell·r(X)·u``; ``jax.grad``/``jax.vjp`` are its transpose.

    Args:
        vertices: (V, 3) float, world units. faces: (F, 3) int, concrete, closed, consistently
            wound, edge-manifold (as for the edge-scan).
        n, grid, directions, shell, edge_table, slots: as in :func:`bsv_mesh_edgescan`; under a
            trace, a pose that overflows ``slots`` reruns with 4× them (the other branch of a
            conditional; the same quadrature), and only an overflow of those raises.
        grad_slots: static sizes ``(pairs, nodes, pieces, window, long, longer)`` of the
            derivative (:func:`edgescan_grad_slots` on the rest pose): (silhouette edge, view)
            slots, visible nodes, pixel-list entries, the longest list and the nodes in the second
            and third tier of list reading; an int gives the pairs only (every node keeps a slot,
            generous pixel lists, slower); None: 30 % of all (edge, view) pairs (a derivative
            sees traced vertices: measure a concrete pose with :func:`edgescan_grad_slots` for
            speed); or a function of no arguments returning one of those, called (outside any
            trace, so it must close over concrete values only) each time a derivative is traced
            and never by a forward pass (cache inside it if it measures). An overflow raises at
            run time.
        nodes: Gauss–Legendre nodes per projected edge (2: exact for the bilinear part on edges of
            constant visibility; most projected edges are shorter than a pixel).

    Limitations: see the module docstring (2 nodes per projected edge, bilinear Y·J, one-sided
    derivative at visual events; a node within float rounding of another edge may get the wrong
    χ). The ``center`` and ``radius`` of the BSV are not returned here; take them
    from :func:`jshadow.geometry.bounding_sphere`, which is differentiable.
    """
    return _edgescan_diff(
        vertices, faces, n, grid, directions, shell, edge_table, slots, grad_slots, nodes, False
    )


def bsv_and_coverage_edgescan_diff(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    n: int = 4,
    grid: tuple[int, int] = (12, 20),
    directions: tuple[int, int] = (32, 32),
    shell: float = 1.5,
    *,
    edge_table: EdgeTable | None = None,
    slots: tuple[int, int, int, int] | None = None,
    grad_slots: int | tuple[int, ...] | Callable[[], int | tuple[int, ...] | None] | None = None,
    nodes: int = 2,
) -> tuple[Float[Array, "T P n2"], Float[Array, "T P Ny Nx"]]:
    """:func:`bsv_mesh_edgescan_diff` and the occlusion images as *coverage*, from one edge-scan.

    The coverage ``cov[i, j, y, x]`` is, in value, exactly :func:`jshadow.visibility.edgescan_occlusion`'s
    binary image as 0.0 / 1.0 (the pixel centre's ray hits the mesh). Its derivative is that of
    the pixel's covered area fraction ``|Ω ∩ pixel| / |pixel|`` (gnomonic units), i.e. of the box
    filter of the occluded region Ω at the pixel, whose point sample at the centre the value is:

        d cov_p = (1 / |pixel|) ∫_{∂Ω ∩ pixel} v dl,

    the same visible-silhouette nodes and per-node terms as the SH derivative (module docstring),
    each node's term going to the pixel that holds it instead of being dotted with ``Y J``. Summed
    over a view's pixels with weights ``Y_i J |pixel|`` it is the SH derivative up to the bilinear
    table (``tests/test_image_lookup_grad.py``). One pass, one set of derivative terms and one set
    of node speeds serve both outputs.

    Returns ``(coeffs (T, P, n²), coverage (T, P, N_y, N_x))``. Arguments, sizes and limitations as
    :func:`bsv_mesh_edgescan_diff`; a pixel's derivative is a quadrature of its boundary (2 nodes
    per projected edge), so per pixel it is rough and only sums over many pixels are accurate.
    """
    return _edgescan_diff(
        vertices, faces, n, grid, directions, shell, edge_table, slots, grad_slots, nodes, True
    )


def _edgescan_diff(vertices, faces, n, grid, directions, shell, edge_table, slots, grad_slots, nodes, images):
    """The SH coefficients (T, P, n²) with their derivative, and with ``images`` also the coverage
    images (T, P, N_y, N_x): the body of the two public functions above."""
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
    cap, width = int(table.a.shape[0]) * grid[0] * grid[1], directions[1]
    n, nodes = int(n), int(nodes)
    views = grid[0] * grid[1]

    def sizes():
        """The derivative's static sizes, rounded and capped."""
        gs = _measured(grad_slots) if callable(grad_slots) else grad_slots
        if gs is None:  # a derivative always sees traced vertices: there is no pose to measure
            gs = _default_grad_slots(table, grid)
        return _rounded_grad_slots(gs, cap, nodes, directions, views)

    # given sizes are checked now (bad ones are an error of this call, not of a later derivative)
    fixed = None if callable(grad_slots) else sizes()
    basis_w = _basis_weights(directions, shell, n, vertices.dtype)

    # Traced, a pose may need more edge-scan slots than the measured ones: that call then reruns
    # with 4× the slots (and the full column span) in the other branch of a conditional, the same
    # quadrature; only an overflow of those raises.
    larger = _check_slots((4 * slots[0], 4 * slots[1], 4 * slots[2], width), cap, width)

    def forward(x):
        """Coefficients (G, n²) and layer counts (G, N_x, N_y) of one edge-scan pass."""
        if isinstance(x, jax.core.Tracer):
            diff, overflow, _, _ = _compute(x, faces_np, table, grid, directions, shell, slots, check=False)
            rerun = partial(
                _compute, faces=faces_np, table=table, grid=grid, directions=directions, shell=shell
            )
            diff = lax.cond(overflow, lambda v: rerun(v, slots=larger)[0], lambda v: diff, x)
        else:
            diff, _, _, _ = _compute(x, faces_np, table, grid, directions, shell, slots)
        counts = _stage_counts(diff)
        return _project_sh(counts != 0, basis_w, n), counts

    def coverage(counts):
        """The binary images (G, N_y, N_x) as 0/1 floats (row-major, as edgescan_occlusion's)."""
        return jnp.swapaxes(counts != 0, -1, -2).astype(vertices.dtype)

    @jax.custom_jvp
    def bsv(x):
        out, counts = forward(x)
        return (out, coverage(counts)) if images else out

    @bsv.defjvp
    def bsv_jvp(primals, tangents):
        (x,), (dx,) = primals, tangents
        x0 = lax.stop_gradient(x)
        pair_slots, node_slots, piece_slots, window, long_slots = fixed or sizes()
        out, counts = forward(x0)
        slot_terms = _slot_terms if isinstance(x0, jax.core.Tracer) else _slot_terms_jit
        *terms, total, count, over = slot_terms(
            x0,
            faces_np,
            table,
            counts,
            grid=grid,
            directions=directions,
            shell=shell,
            slots=pair_slots,
            node_slots=node_slots,
            nodes=nodes,
            piece_slots=piece_slots,
            window=window,
            long_slots=long_slots,
        )
        overflow = (total > pair_slots) | (count > node_slots) | over
        out = eqx.error_if(out, overflow, _GRAD_OVERFLOW)
        # the tangent carries the check too: under jax.jit(jax.grad(...)) the primal is dead code
        # and its check would be dropped with it, leaving a silently incomplete gradient
        ok = eqx.error_if(jnp.ones((), out.dtype), overflow, _GRAD_OVERFLOW)
        _, dpoints = jax.jvp(lambda v: _sample_points(v, grid, shell)[0], (x0,), (dx,))
        corner_basis = _corner_basis(directions, shell, n, out.dtype)
        speeds = _node_speeds(terms, dx, dpoints)  # shared by the SH and the coverage tangents
        dout = ok * _apply(terms, corner_basis, speeds, views=views).astype(out.dtype)
        if not images:
            return out, dout
        tan_a = 1.0 / math.sqrt(shell * shell - 1.0)
        area = (2.0 * tan_a / directions[0]) * (2.0 * tan_a / directions[1])
        dcov = _apply_pixels(terms, speeds, views=views, directions=directions, area=area)
        cov = coverage(counts)
        return (out, cov), (dout, ok * dcov.astype(cov.dtype))

    if images:
        out, cov = bsv(vertices)
        return out.reshape(*grid, n * n), cov.reshape(*grid, *directions)
    return bsv(vertices).reshape(*grid, n * n)
