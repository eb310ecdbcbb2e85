"""Fast BSV of a closed mesh: silhouette-edge scanline on a gnomonic cone image ("edge-scan").

The base sphere visibility (BSV; deformable-shadow-fields paper Sec. 4.1, after Zhou et al. 2005,
"Precomputed shadow fields" Sec. 4) needs, at each of the T×P shell points ``p = c + R·u``
(R = shell · r > r, conventions in :mod:`jshadow.visibility._frames`), the occluded directions
of the sphere. Seen from outside its bounding sphere, the mesh lies inside the cone of half-angle
``α = asin(r/R)`` around the local +z axis (toward the centre). The cone is sampled by a gnomonic
(perspective) image on the plane z = 1 of the local frame: ``N_y × N_x`` pixels over
``[−tan α, tan α]²``; pixel ``(i, j)`` (row i along local y, column j along local x) has its centre at
``x_j = −tan α + (j + ½)·Δx``, ``y_i = −tan α + (i + ½)·Δy`` and its ray direction is
``(x_j, y_i, 1) / |(x_j, y_i, 1)|``. Directions outside the image are free of the mesh.

Method (notes/bsv-speed.md, "edge-scan"). For a closed, consistently oriented mesh seen from an
outside point, the number of front-facing layers over an image point is the winding number of
the projected *silhouette* edges around it (edges between two front faces or two back faces
cancel). An edge (a, b) whose half-edge a→b belongs to face t₁ and b→a to t₂ carries the weight
``w = front(t₁) − front(t₂)`` and, in the trapezoid form of that winding number, adds
``w·sgn(x_b − x_a)`` to every pixel centre with ``x_j ∈ [min x, max x)`` below which the edge
passes (``y_i > y_edge(x_j)``). One scatter-add per (silhouette edge, crossed column) into a
difference image with ``N_y + 1`` rows, a prefix sum over rows (a triangular matmul) gives the
layer count, and a pixel is occluded iff its count is non-zero. The column an edge starts at is
a per-vertex integer ``⌈(x − x₀)/Δx⌉``, computed once per (vertex, view), so edges that share a
vertex agree on it and the count is exact at pixel centres (up to rounding when a centre lies
on a projected edge). Facing is one sign per (face, view), so every face is counted consistently.

Stages (each a separate ``jax.jit``, and each a :func:`staged` conditional when traced: XLA:CPU
fuses gathers into their consumers and recomputes them, so one plainly fused jit is slower;
notes/bsv-speed.md. Concrete input runs all stages as one compiled call of such conditionals):

1. views: bounding sphere, shell points and frames, face planes (small);
2. project: the (vertex, view) image coordinates and start columns, the (face, view) facing bits;
3. candidates: the (edge, view) pairs that are silhouette edges and cross at least one column;
4. slots: the candidates packed 32 per word and compacted into one list of ``S`` slots for all
   views (prefix of popcounts, a small scatter and a running maximum, both as parallel scans, and
   select-nth-set-bit): no scatter over all (edge, view) pairs, no sort;
5. gather: per slot, the column range, start point, slope and weight of its (edge, view);
6. emit: every slot's first column crossing, the second one of the ``S2`` slots spanning more
   than one column, and the crossings 2 … K − 1 of the ``S3`` slots spanning more than two, as
   one scatter-add into the difference images;
7. SH: row prefix sums as one matmul (images stored column by column), ``count ≠ 0``, and
   ``coeffs = √(4π)·e0 − occ @ (w·Y)`` with exact per-pixel solid angles ``w`` (basis rows in the
   same column-major pixel order, so nothing is transposed).

``S``, ``S2``, ``S3`` and ``K`` are static. When a pose needs more, the ``overflow`` flag is set;
:func:`bsv_mesh_edgescan` then recomputes with larger slots (concrete input) or raises at run time
(traced input): the result is never silently wrong.

Limitations: closed, edge-manifold, consistently wound meshes only (:func:`build_edge_table`
checks this); ``shell > 1``; the output is binary visibility sampled on a grid and has no useful
gradient with respect to the vertices (notes/visibility-gradients.md gives the boundary term).
"""

from __future__ import annotations

import math
from functools import lru_cache, partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ..geometry import bounding_sphere
from ..sh import sh_basis
from ._bsv import BSV
from ._frames import bsv_frames, bsv_grid_angles

__all__ = [
    "EdgeTable",
    "build_edge_table",
    "edgescan_cone_directions",
    "edgescan_occlusion",
    "edgescan_slots",
    "bsv_mesh_edgescan",
    "bsv_and_occlusion_edgescan",
]

_WORD = 32  # edges per packed word


class EdgeTable(eqx.Module):
    """Static edge table of a closed, consistently wound, edge-manifold triangle mesh.

    Attributes (E undirected edges, padded with inert entries to ``E_pad``, a multiple of 32 and
    at least E + 1; padding has ``a = b = 0`` and ``t1 = t2 = 0``, so it never contributes):
        a, b: (E_pad,) int32 vertex ids, the half-edge a→b belongs to face ``t1``;
        t1, t2: (E_pad,) int32 the faces holding a→b and b→a.
        num_edges: E (static). num_vertices, num_faces: static sizes the table was built for.
    """

    a: Int[Array, " E_pad"]
    b: Int[Array, " E_pad"]
    t1: Int[Array, " E_pad"]
    t2: Int[Array, " E_pad"]
    num_edges: int = eqx.field(static=True)
    num_vertices: int = eqx.field(static=True)
    num_faces: int = eqx.field(static=True)


def build_edge_table(faces: Int[ArrayLike, "F 3"], num_vertices: int | None = None) -> EdgeTable:
    """Edge table of a closed mesh, built once per topology (host side, numpy).

    Raises ``ValueError`` unless the faces form a closed, edge-manifold, consistently wound
    surface: no face repeats a vertex, every directed edge a→b occurs exactly once and its reverse
    b→a occurs too. ``faces`` must be concrete (not traced).
    """
    try:
        f = np.asarray(faces)
    except jax.errors.TracerArrayConversionError as err:
        raise ValueError("build_edge_table needs concrete faces (build it outside jit)") from err
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer) or f.shape[0] == 0:
        raise ValueError(f"faces must be a non-empty int array of shape (F, 3), got {f.dtype} {f.shape}")
    f = f.astype(np.int64)
    nv = int(f.max()) + 1 if num_vertices is None else int(num_vertices)
    if f.min() < 0 or f.max() >= nv:
        raise ValueError(f"face indices must lie in [0, {nv}), got [{f.min()}, {f.max()}]")
    if np.any((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])):
        raise ValueError("faces must not repeat a vertex (degenerate face found)")
    nf = f.shape[0]
    src = f.reshape(-1)
    dst = np.roll(f, -1, axis=1).reshape(-1)
    face_of = np.repeat(np.arange(nf), 3)
    key = src * nv + dst
    order = np.argsort(key, kind="stable")
    ks = key[order]
    if np.any(ks[1:] == ks[:-1]):
        raise ValueError(
            "mesh is not consistently wound or not edge-manifold: a directed edge occurs twice "
            "(edge-scan needs a closed, consistently oriented manifold mesh)"
        )
    rev = dst * nv + src
    pos = np.searchsorted(ks, rev)
    found = (pos < ks.size) & (ks[np.minimum(pos, ks.size - 1)] == rev)
    if not np.all(found):
        raise ValueError(
            f"mesh is not closed: {int(np.sum(~found))} directed edges have no opposite half-edge "
            "(edge-scan needs a closed, consistently oriented manifold mesh)"
        )
    twin_face = face_of[order[pos]]
    keep = src < dst  # one entry per undirected edge: the half-edge running low -> high id
    a, b, t1, t2 = src[keep], dst[keep], face_of[keep], twin_face[keep]
    ne = a.size
    e_pad = -(-(ne + 1) // _WORD) * _WORD

    def pad(x):
        return jnp.asarray(np.concatenate([x, np.zeros(e_pad - ne, np.int64)]).astype(np.int32))

    return EdgeTable(pad(a), pad(b), pad(t1), pad(t2), ne, nv, nf)


def _check_pair(value, name):
    if not (
        isinstance(value, tuple | list)
        and len(value) == 2
        and all(isinstance(g, int | np.integer) and not isinstance(g, bool) and g >= 1 for g in value)
    ):
        raise ValueError(f"{name} must be two positive ints, got {value!r}")
    return int(value[0]), int(value[1])


def _check_shell(shell):
    if not (isinstance(shell, int | float | np.floating) and math.isfinite(shell) and shell > 1.0):
        raise ValueError(
            f"edge-scan needs shell > 1 (sample points outside the bounding sphere), got {shell!r}; "
            "use bsv_mesh(method='brute') for shell = 1"
        )
    return float(shell)


@lru_cache(maxsize=32)
def _np_cone(ny: int, nx: int, shell: float):
    """Pixel-centre directions (ny·nx, 3), exact pixel solid angles (ny·nx,), half-width tan α."""
    tan_a = 1.0 / math.sqrt(shell * shell - 1.0)
    xe = np.linspace(-tan_a, tan_a, nx + 1)
    ye = np.linspace(-tan_a, tan_a, ny + 1)
    xc = 0.5 * (xe[1:] + xe[:-1])
    yc = 0.5 * (ye[1:] + ye[:-1])
    d = np.stack(np.broadcast_arrays(xc[None, :], yc[:, None], 1.0), axis=-1).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    # solid angle of [x0, x1] × [y0, y1] on the plane z = 1: the integral of the gnomonic density
    # dx dy / (1 + x² + y²)^{3/2}, whose antiderivative is atan(x·y / √(1 + x² + y²))
    prim = np.arctan(xe[None, :] * ye[:, None] / np.sqrt(1.0 + xe[None, :] ** 2 + ye[:, None] ** 2))
    w = prim[1:, 1:] - prim[1:, :-1] - prim[:-1, 1:] + prim[:-1, :-1]
    return d, w.reshape(-1), tan_a


def edgescan_cone_directions(
    directions: tuple[int, int] = (32, 32), shell: float = 1.5, dtype=None
) -> tuple[Float[Array, "K 3"], Float[Array, " K"]]:
    """Local pixel-centre directions (K = N_y·N_x, 3), row-major (row = local y), and solid angles (K,).

    The gnomonic image covers ``[−tan α, tan α]²`` on the local plane z = 1 with
    ``sin α = 1/shell``; the weights are the exact solid angles of the pixels (steradians), i.e.
    the integral of ``dx dy / (1 + x² + y²)^{3/2}`` over each pixel.
    """
    ny, nx = _check_pair(directions, "directions")
    d, w, _ = _np_cone(ny, nx, _check_shell(shell))
    dtype = jnp.result_type(float) if dtype is None else dtype
    return jnp.asarray(d, dtype), jnp.asarray(w, dtype)


# --------------------------------------------------------------------------------------------
# Stage 1: projection of vertices and facing of faces, per view
# --------------------------------------------------------------------------------------------


@partial(jax.jit, static_argnames=("grid", "shell"))
def _stage_views(vertices, faces, *, grid, shell):
    """Bounding sphere, shell points and frames, face planes; coordinates as separate 1-D arrays."""
    dtype = vertices.dtype
    center, radius = bounding_sphere(vertices)
    theta, phi = bsv_grid_angles(*grid, dtype)
    u, frames = bsv_frames(theta[:, None], phi[None, :])
    points = (center + (shell * radius) * u).reshape(-1, 3)  # p (G, 3)
    frames = frames.reshape(-1, 3, 3)  # world = frame @ local
    tri = vertices[faces]  # (F, 3, 3)
    nrm = jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # (F, 3), outward for CCW faces
    offset = jnp.sum(nrm * tri[:, 0], axis=-1)  # the face plane is n·x = offset
    # contiguous 1-D components: XLA:CPU vectorises the dense (vertex, view) pass far better than
    # with strided reads of (…, 3) arrays
    comps = (
        [vertices[:, m] for m in range(3)],
        [points[:, m] for m in range(3)],
        [[frames[:, m, k] for k in range(3)] for m in range(3)],
        [nrm[:, m] for m in range(3)],
    )
    return center, radius, comps, offset


def _local_coords(comps):
    """Local coordinates ``frameᵀ(x − p)`` per (vertex, view) as three (V, G) arrays, and ``n·p``
    per (face, view) (F, G) (compare with the face plane's offset for its facing)."""
    vs, ps, fs, ns = comps
    rel = [vs[m][:, None] - ps[m][None, :] for m in range(3)]  # x − p
    qx, qy, qz = (rel[0] * fs[0][k] + rel[1] * fs[1][k] + rel[2] * fs[2][k] for k in range(3))
    side = ns[0][:, None] * ps[0] + ns[1][:, None] * ps[1] + ns[2][:, None] * ps[2]
    return qx, qy, qz, side


@partial(jax.jit, static_argnames=("directions", "shell"))
def _stage_project(comps, offset, *, directions, shell):
    """Image coordinates and start columns per (vertex, view) (V, G); facing per (face, view) (F, G)."""
    ny, nx = directions
    tan_a = 1.0 / math.sqrt(shell * shell - 1.0)
    qx, qy, qz, side = _local_coords(comps)
    inv = 1.0 / qz  # qz ≥ R − r > 0 for every vertex
    px, py = qx * inv, qy * inv  # gnomonic image coordinates
    dx = 2.0 * tan_a / nx
    col_dtype = jnp.uint8 if nx < 255 else jnp.int32  # less memory traffic in the (edge, view) pass
    col = jnp.clip(jnp.ceil((px + tan_a) / dx - 0.5), 0, nx).astype(col_dtype)  # first column x_j ≥ x
    front = side > offset[:, None]  # the face turns its front toward p
    return px, py, col, front


# --------------------------------------------------------------------------------------------
# Stage 2: compaction of the (edge, view) candidates into S slots (all views together)
# --------------------------------------------------------------------------------------------


def _select_bit(x, nth):
    """Position of the ``nth`` (0-based) set bit of the uint32 ``x`` (elementwise, binary search)."""
    pos = jnp.zeros(x.shape, jnp.uint32)
    nth = nth.astype(jnp.int32)
    for width in (16, 8, 4, 2, 1):
        mask = jnp.uint32((1 << width) - 1)
        c = lax.population_count((x >> pos) & mask).astype(jnp.int32)
        skip = nth >= c
        nth = jnp.where(skip, nth - c, nth)
        pos = jnp.where(skip, pos + jnp.uint32(width), pos)
    return pos.astype(jnp.int32)


def _pack(mask):
    """Bool (32·W,) -> uint32 words (W,), bit k of word w = ``mask[32w + k]``."""
    bits = mask.reshape(-1, _WORD).astype(jnp.uint32)
    shifts = jnp.arange(_WORD, dtype=jnp.uint32)
    return jnp.sum(bits << shifts, axis=-1, dtype=jnp.uint32)  # distinct bits: the sum is an OR


def _cumsum(x):
    """Inclusive prefix sum of a 1-D array (a parallel scan: 2-4x faster than ``jnp.cumsum`` on XLA:CPU).

    Traced, ``x`` is made a buffer first (a stage, :func:`staged`): XLA:CPU fused the computation
    of ``x`` into every level of the scan and recomputed it there (the pixel lists' box sizes over
    204768 silhouette pairs: the sizes 0.26 ms and their scan 0.48 ms apart, 4.8 ms fused; the
    bunny's ``image`` derivative's primal 44.3 → 40.4 ms, BENCHMARKS.md).
    """
    if x.size == 0:
        return x
    return staged(always(x), partial(lax.associative_scan, jnp.add), x)


def _compact(words, slots):
    """Positions of the set bits of ``words`` (W,), in order, in ``slots`` slots.

    Returns ``pos`` (slots,) int32 (bit position ``32w + k``; −1 past the count) and the count of
    set bits (). Slot s finds the word holding the set bit of rank s and the bit inside it
    (select-nth-set-bit). Only parallel scans, one small scatter and gathers are used: no scatter
    over all bits, no sort (``lax.cummax`` and ``jnp.cumsum`` are several times slower on XLA:CPU
    than ``lax.associative_scan``).
    """
    n_words = words.shape[0]
    counts = lax.population_count(words).astype(jnp.int32)
    before = _cumsum(counts) - counts  # set bits in earlier words
    total = before[-1] + counts[-1]
    wid = jnp.arange(n_words, dtype=jnp.int32)
    # each non-empty word marks the slot of its first set bit; a running maximum carries it on
    first = jnp.full((slots,), -1, jnp.int32).at[jnp.where(counts > 0, before, slots)].max(wid, mode="drop")
    word = jnp.maximum(lax.associative_scan(jnp.maximum, first), 0)  # the word holding rank s: (slots,)
    rank = jnp.arange(slots, dtype=jnp.int32)
    bit = _select_bit(words[word], rank - before[word])
    return jnp.where(rank < total, word * _WORD + bit, -1), total


@jax.jit
def _stage_candidates(front, col, a, b, t1, t2):
    # row gathers (E_pad, G); kept apart from the packing below, which XLA:CPU would otherwise fuse
    # with these gathers and recompute them per bit (measured 10x slower)
    return (front[t1] != front[t2]) & (col[a] != col[b])


@partial(jax.jit, static_argnames=("slots",))
def _stage_slots(cand, *, slots):
    # one list over all views, in memory order: bit e·G + g is the candidate (edge e, view g)
    e_pad, g = cand.shape
    pos, total = _compact(_pack(cand.reshape(-1)), slots)
    sentinel = (e_pad - 1) * g  # view 0, a padding edge: never contributes
    return jnp.where(pos >= 0, pos, sentinel), total


# --------------------------------------------------------------------------------------------
# Stage 3: column crossings of the slotted edges, scattered into the difference image
# --------------------------------------------------------------------------------------------


@partial(jax.jit, static_argnames=("directions",))
def _stage_gather(slot, px, py, col, front, a, b, t1, *, directions):
    """Per slot: column range, start point, slope, image offset and weight of its (edge, view)."""
    ny, nx = directions
    dtype = px.dtype
    g = front.shape[1]
    edge, view = slot // g, slot % g  # (S,)
    va, vb = a[edge], b[edge]
    fa, fb = va * g + view, vb * g + view  # flat (vertex, view) indices
    pxf, pyf, colf = px.reshape(-1), py.reshape(-1), col.reshape(-1)
    xa, ya, ca = pxf[fa], pyf[fa], colf[fa].astype(jnp.int32)
    xb, yb, cb = pxf[fb], pyf[fb], colf[fb].astype(jnp.int32)
    f1 = front.reshape(-1)[t1[edge] * g + view]
    # silhouette weight front(t1) − front(t2) = ±1 (slots hold silhouette edges or the inert pad),
    # times the direction of the edge along x
    sgn = jnp.where(f1, 1.0, -1.0).astype(dtype) * jnp.sign(cb - ca).astype(dtype)
    lo, hi = jnp.minimum(ca, cb), jnp.maximum(ca, cb)
    crosses = hi > lo
    run = jnp.where(crosses, xb - xa, 1.0)  # double where: no division by zero for idle slots
    slope = jnp.where(crosses, (yb - ya) / run, 0.0)
    base = view * ((ny + 1) * nx)  # the image of view g, stored column by column: (N_x, N_y + 1)
    return lo, hi, xa, ya, slope, base, sgn


def _tiers(params, most, *, directions, shell, long_slots, span):
    """Every column crossing of the slotted (edge, view) pairs, and the counts the tiers needed.

    Every slot gives its first crossing; the slots spanning more columns are compacted into S2 slots
    that give the second crossing, and those spanning more than two into S3 slots that give the
    crossings 2 … K − 1. Returns a dict of (C,) arrays, ``C = S + S2 + S3·(K − 2)``: ``sid`` (the
    slot), ``col`` (j), ``y`` (the crossing's height), ``row`` (pixel centres at or below it: its row
    in the difference image), ``cell`` (flat (view, column, row) index of the difference images),
    ``w`` (±1: the change of the layer count going up) and ``valid``; and the needed ``(S, S2, S3,
    K)`` (4,) int32.
    """
    ny, nx = directions
    tan_a = 1.0 / math.sqrt(shell * shell - 1.0)
    dx, dy = 2.0 * tan_a / nx, 2.0 * tan_a / ny
    s2, s3 = long_slots
    lo, hi = params[0], params[1]
    dtype = params[2].dtype
    p1 = (*params, jnp.arange(lo.shape[0], dtype=jnp.int32))

    def longer(p, than, n):
        """The entries of ``p`` spanning more than ``than`` columns, compacted into n slots."""
        pos, count = _compact(_pack(p[1] - p[0] > than), n)
        out = [x[jnp.maximum(pos, 0)] for x in p]
        out[1] = jnp.where(pos >= 0, out[1], out[0])  # empty slots span nothing
        return tuple(out), count

    p2, n2 = longer(p1, 1, s2)
    p3, n3 = longer(p2, 2, s3)
    out = {k: [] for k in ("sid", "col", "y", "row", "cell", "w", "valid")}
    tiers = [(p1, 0), (p2, 1)] + [(p3, k) for k in range(2, span)]
    for (lo_, hi_, xa, ya, slope, base, sgn, sid), k in tiers:
        j = lo_ + k
        xj = (j.astype(dtype) + 0.5) * dx - tan_a
        y = ya + (xj - xa) * slope
        row = jnp.clip(jnp.floor((y + tan_a) / dy - 0.5) + 1.0, 0, ny).astype(jnp.int32)  # rows y_i ≤ y
        for key, val in (("sid", sid), ("col", j), ("y", y), ("row", row), ("w", sgn), ("valid", j < hi_)):
            out[key].append(val)
        out["cell"].append(base + j * (ny + 1) + row)
    need = jnp.stack([most, n2, n3, jnp.max(hi - lo)]).astype(jnp.int32)  # vs static (S, S2, S3, K)
    return {k: jnp.concatenate(v) for k, v in out.items()}, need


@partial(jax.jit, static_argnames=("views", "directions", "shell", "long_slots", "span", "with_crossings"))
def _stage_emit(params, most, *, views, directions, shell, long_slots, span, with_crossings=False):
    """Scatter-add of every column crossing (:func:`_tiers`) into the difference images
    (G, N_x, N_y + 1); the overflow flag and the needed counts; with ``with_crossings`` also the
    crossings."""
    ny, nx = directions
    n_slots = params[0].shape[0]
    size = views * (ny + 1) * nx
    cr, need = _tiers(params, most, directions=directions, shell=shell, long_slots=long_slots, span=span)
    idx = jnp.where(cr["valid"], cr["cell"], size)
    diff = jnp.zeros((size,), cr["y"].dtype).at[idx].add(cr["w"], mode="drop")
    overflow = jnp.any(need > jnp.asarray([n_slots, *long_slots, span], jnp.int32))
    out = (diff.reshape(views, nx, ny + 1), overflow, need)
    return (*out, cr) if with_crossings else out


# --------------------------------------------------------------------------------------------
# Stage 4: layer counts, occlusion, SH projection
# --------------------------------------------------------------------------------------------


@jax.jit
def _stage_counts(diff):
    """Layer counts (G, N_x, N_y) (column-major images) from the difference images (G, N_x, N_y + 1):
    the winding number of the projected silhouette at each pixel centre."""
    g, nx, ny1 = diff.shape
    triu = (jnp.arange(ny1)[:, None] <= jnp.arange(ny1 - 1)[None, :]).astype(diff.dtype)  # (N_y + 1, N_y)
    count = diff.reshape(g * nx, ny1) @ triu  # prefix sums over rows as one matmul
    return count.reshape(g, nx, ny1 - 1)


@jax.jit
def _stage_occlusion(diff):
    """Occlusion (G, N_x, N_y) (column-major images) from the difference images (G, N_x, N_y + 1)."""
    return _stage_counts(diff) != 0


@partial(jax.jit, static_argnames=("n", "grid"))
def _stage_sh(diff, basis_w, *, n, grid):
    return _project_sh(_stage_occlusion(diff), basis_w, n).reshape(*grid, n * n)


def _project_sh(occ, basis_w, n):
    """``√(4π)·e0 − occ @ (w·Y)``: (G, n²) from the occlusion images (G, N_x, N_y) (column-major)."""
    occ = occ.reshape(occ.shape[0], -1).astype(basis_w.dtype)
    full = jnp.zeros(n * n, basis_w.dtype).at[0].set(math.sqrt(4.0 * math.pi))
    return full - occ @ basis_w


# --------------------------------------------------------------------------------------------
# Drivers
# --------------------------------------------------------------------------------------------


_TABLES: dict = {}  # topology -> EdgeTable, for calls that pass no edge_table
_REST_SLOTS: dict = {}  # (topology, configuration) -> slots measured on the first pose seen


def _topology_key(faces, num_vertices):
    f = np.ascontiguousarray(np.asarray(faces))
    return (f.shape, str(f.dtype), num_vertices, hash(f.tobytes()))


def _cached_edge_table(faces, num_vertices):
    key = _topology_key(faces, num_vertices)
    if key not in _TABLES:
        if len(_TABLES) >= 64:
            _TABLES.clear()
        # concrete arrays even when first reached under a trace (ensure_compile_time_eval is not
        # enough inside a custom_jvp rule under jax.jit(jax.grad(...)): its arrays came out traced)
        with jax.core.eval_context():
            _TABLES[key] = build_edge_table(faces, num_vertices)
    return _TABLES[key]


def _prepare(vertices, faces, edge_table):
    vertices = jnp.asarray(vertices)
    if vertices.ndim != 2 or vertices.shape[-1] != 3 or vertices.shape[0] == 0:
        raise ValueError(f"vertices must have shape (V, 3) with V >= 1, got {vertices.shape}")
    if not jnp.issubdtype(vertices.dtype, jnp.floating):
        vertices = vertices.astype(jnp.result_type(float))
    if not isinstance(faces, jax.Array):  # NumPy faces stay concrete under a trace
        faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[-1] != 3 or not jnp.issubdtype(faces.dtype, jnp.integer):
        raise ValueError(f"faces must be an int array of shape (F, 3), got {faces.dtype} {faces.shape}")
    if edge_table is None:
        edge_table = _cached_edge_table(faces, vertices.shape[0])
    faces = jnp.asarray(faces)
    if edge_table.num_faces != faces.shape[0] or edge_table.num_vertices > vertices.shape[0]:
        raise ValueError(
            f"edge_table was built for {edge_table.num_faces} faces and {edge_table.num_vertices} "
            f"vertices, got {faces.shape[0]} faces and {vertices.shape[0]} vertices"
        )
    return vertices, faces.astype(jnp.int32), edge_table


def _round_up(x, m):
    return int(-(-x // m) * m)


def always(x) -> Bool[Array, ""]:
    """A run-time True that XLA cannot fold, for :func:`staged`: the first element of ``x``'s bits,
    with the lowest set, is non-zero (``abs(x) >= 0`` and similar predicates are folded, and the
    conditional with them)."""
    x = jnp.asarray(x).reshape(-1)[0]
    bits = lax.bitcast_convert_type(
        x, {1: jnp.uint8, 2: jnp.uint16, 4: jnp.uint32, 8: jnp.uint64}[x.dtype.itemsize]
    )
    return (bits | 1) != 0


def staged(live, fn, *args):
    """``fn(*args)``; inside a trace, computed in a conditional on ``live`` so that it is a stage.

    Eagerly each stage is its own compiled call. Traced (a caller's ``jax.jit``, a custom
    derivative), XLA:CPU would fuse the stages into one another and recompute gathers and index
    arithmetic per consumer element (the edge-scan 3× slower, its derivative's node tests 5×);
    ``lax.optimization_barrier`` does not survive its fusion passes, but a conditional's results are
    buffers. ``live`` is a run-time True (:func:`always`; the other branch gives zeros, so XLA
    cannot remove the conditional).
    """
    if not any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(args)):
        return fn(*args)
    shapes = jax.eval_shape(fn, *args)
    return lax.cond(live, fn, lambda *_: jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), shapes), *args)


def _run(vertices, faces, table, grid, directions, shell, slots, with_params=False):
    """The edge-scan pass: difference images (G, N_x, N_y + 1), overflow flag, needed counts, centre
    and radius; with ``with_params`` also the slots and their per-slot parameters (stage 5), which the
    scanline derivative (:mod:`._edgescan_scan`) reads: the slots, the crossings of
    :func:`_tiers` and the projection (image x, y per (vertex, view) and facing per (face, view))."""
    s, s2, s3, k = slots
    center, radius, comps, offset = _stage_views(vertices, faces, grid=grid, shell=shell)
    stage = partial(staged, always(radius))
    px, py, col, front = stage(partial(_stage_project, directions=directions, shell=shell), comps, offset)
    cand = stage(_stage_candidates, front, col, table.a, table.b, table.t1, table.t2)
    slot, most = stage(partial(_stage_slots, slots=s), cand)
    params = stage(
        partial(_stage_gather, directions=directions), slot, px, py, col, front, table.a, table.b, table.t1
    )
    emit = partial(
        _stage_emit,
        views=grid[0] * grid[1],
        directions=directions,
        shell=shell,
        long_slots=(s2, s3),
        span=k,
        with_crossings=with_params,
    )
    diff, overflow, counts, *crossings = stage(emit, params, most)
    if with_params:
        return diff, overflow, counts, center, radius, (slot, crossings[0], (px, py, front))
    return diff, overflow, counts, center, radius


_run_jit = jax.jit(_run, static_argnums=(3, 4, 5, 6), static_argnames=("with_params",))


def edgescan_slots(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    grid: tuple[int, int] = (12, 20),
    directions: tuple[int, int] = (32, 32),
    shell: float = 1.5,
    *,
    margin: float = 1.5,
    edge_table: EdgeTable | None = None,
) -> tuple[int, int, int, int]:
    """Static slot sizes ``(S, S2, S3, K)`` measured on a pose (e.g. the rest pose), times ``margin``.

    ``S``: (silhouette edge, view) pairs crossing at least one pixel column, over all views;
    ``S2``: those crossing more than one column; ``S3``: more than two; ``K``: columns crossed by
    one edge (maximum), at most the image width. S2, S3 and K also get a small additive slack
    (256, 64, 1); S and S2 are rounded up to a multiple of 32. Needs concrete vertices.
    """
    grid = _check_pair(grid, "grid")
    directions = _check_pair(directions, "directions")
    shell = _check_shell(shell)
    if not (isinstance(margin, int | float) and margin >= 1.0):
        raise ValueError(f"margin must be a number >= 1, got {margin!r}")
    vertices, faces, table = _prepare(vertices, faces, edge_table)
    _, _, comps, offset = _stage_views(vertices, faces, grid=grid, shell=shell)
    _, _, col, front = _stage_project(comps, offset, directions=directions, shell=shell)
    return _slots_of_starts(col, np.asarray(front), table, margin, directions[1])


def _slots_of_starts(start, front, table, margin, width):
    """``(S, S2, S3, K)`` from the start indices (V, G) of one scan and the facing (F, G) (host
    arrays): the silhouette pairs spanning more than 0, 1 and 2 scan lines and the longest span,
    times ``margin`` (shared by the column scan and the scanline derivative's row scan)."""
    a, b, t1, t2 = (np.asarray(x) for x in (table.a, table.b, table.t1, table.t2))
    start = np.asarray(start).astype(np.int64)
    span = np.abs(start[a] - start[b]) * (front[t1] != front[t2])  # (E_pad, G)
    e_pad = int(a.shape[0])
    s = min(_round_up(max(1, math.ceil(int(np.sum(span > 0)) * margin)), _WORD), e_pad * span.shape[1])
    # S2, S3 and K are small: an additive slack on top of the margin costs next to nothing
    s2 = _round_up(math.ceil(int(np.sum(span > 1)) * margin) + 256, _WORD)
    s3 = math.ceil(int(np.sum(span > 2)) * margin) + 64
    k = min(math.ceil(int(np.max(span)) * margin) + 1, width)
    return s, s2, s3, k


def _check_slots(slots, cap, width):
    if not (
        isinstance(slots, tuple | list)
        and len(slots) == 4
        and all(isinstance(x, int | np.integer) and not isinstance(x, bool) and x >= 1 for x in slots)
    ):
        raise ValueError(
            f"slots must be four positive ints (S, S2, S3, K) (see edgescan_slots), got {slots!r}"
        )
    s, s2, s3, k = (int(x) for x in slots)
    s = min(_round_up(s, _WORD), cap)
    s2 = min(_round_up(s2, _WORD), s)
    return s, s2, min(s3, s2), min(max(k, 1), width)


def _traced_default_slots(num_faces, grid, directions):
    """Generous slot sizes when the pose cannot be measured (traced vertices).

    Measured on the shipped meshes at 32² pixels, a view crosses at most about 4·√F (edge, column)
    candidates on average, 29 % of them span more than one column, and no edge spans more than 11
    columns; these defaults take twice that. An overflow still raises at run time.
    """
    views = grid[0] * grid[1]
    s = math.ceil(8.0 * math.sqrt(num_faces) * max(directions[1], 8) / 32.0) * views
    return s, max(1, s // 2), max(1, s // 4), max(2, directions[1] // 2)


def _resolve(vertices, faces, grid, directions, shell, edge_table, slots):
    grid = _check_pair(grid, "grid")
    directions = _check_pair(directions, "directions")
    shell = _check_shell(shell)
    vertices, faces, table = _prepare(vertices, faces, edge_table)
    if slots is None:
        if isinstance(vertices, jax.core.Tracer):
            slots = _traced_default_slots(table.num_faces, grid, directions)
        else:  # measured on the first pose seen with this topology (the rest pose), then reused
            slots = _rest_slots(vertices, faces, table, grid, directions, shell)
    slots = _check_slots(slots, *_slot_bounds(table, grid, directions))
    return vertices, faces, table, grid, directions, shell, slots


def _rest_key(faces, num_vertices, dtype, grid, directions, shell):
    """Key of ``_REST_SLOTS``: the topology, the vertices' dtype and the configuration."""
    return (_topology_key(faces, num_vertices), jnp.dtype(dtype).name, grid, directions, shell)


def _rest_slots(vertices, faces, table, grid, directions, shell):
    """The slots of this topology and configuration, measured on ``vertices`` (concrete) if it is the
    first pose seen with them, else those measured then."""
    key = _rest_key(faces, vertices.shape[0], vertices.dtype, grid, directions, shell)
    if key not in _REST_SLOTS:
        if len(_REST_SLOTS) >= 256:
            _REST_SLOTS.clear()
        _REST_SLOTS[key] = edgescan_slots(vertices, faces, grid, directions, shell, edge_table=table)
    return _REST_SLOTS[key]


def _slot_bounds(table, grid, directions):
    """``(cap, width)`` of :func:`_check_slots` for this edge table and configuration."""
    return int(table.a.shape[0]) * grid[0] * grid[1], directions[1]


_OVERFLOW = "edge-scan slots overflowed: pass larger slots=(S, S2, S3, K) (see edgescan_slots)"
_GROWN: dict = {}  # slots that overflowed -> the larger slots that worked (per configuration)


def _compute(vertices, faces, table, grid, directions, shell, slots, finish=lambda diff: diff, check=True):
    """``finish(diff)`` of the difference images, retrying with larger slots on overflow (concrete)
    or flagging it (traced: raising at run time unless ``check`` is False).

    ``finish`` is dispatched before the host waits for the overflow flag, so it runs without a gap.
    Concrete overflows are remembered: later calls with the same configuration and slots start
    from the grown slots (one extra compile in all, not one extra pass per call).
    """
    if isinstance(vertices, jax.core.Tracer):
        diff, overflow, _, center, radius = _run(vertices, faces, table, grid, directions, shell, slots)
        diff = eqx.error_if(diff, overflow, _OVERFLOW) if check else diff
        return finish(diff), overflow, center, radius

    def call(slots):  # one compiled call of staged conditionals (~25 % faster than inlined)
        diff, overflow, counts, center, radius = _run_jit(
            vertices, faces, table, grid, directions, shell, slots
        )
        return finish(diff), overflow, counts, center, radius

    out, overflow, _, center, radius = _until_fits(call, table, grid, directions, shell, slots)
    return out, overflow, center, radius


def _grown_key(table, grid, directions, shell, slots):
    """Key of ``_GROWN``: the configuration and the slots it started from."""
    return (table.num_edges, table.num_faces, table.num_vertices, grid, directions, shell, slots)


def _until_fits(call, table, grid, directions, shell, slots):
    """``call(slots) -> (out, overflow, counts, ...)`` on concrete data, starting from the slots an
    earlier overflow of this configuration grew ``slots`` to, and rerun with larger ones after an
    overflow: each at least 1.25× the count it needed, remembered in ``_GROWN`` for later calls. The
    counts are exact for the slotted edges, so one retry suffices unless S itself overflowed (then
    the long-edge count is a lower bound and a second retry may follow)."""
    cap, width = _slot_bounds(table, grid, directions)
    key = _grown_key(table, grid, directions, shell, slots)
    slots = _GROWN.get(key, slots)
    while True:
        out = call(slots)  # (``finish`` is dispatched inside, before the host waits for the flag)
        if not bool(out[1]):
            return out
        need = [int(x) for x in np.asarray(out[2])]
        grow = [max(x, math.ceil(1.25 * y)) for x, y in zip(slots, need, strict=True)]
        slots = _check_slots(tuple(grow), cap, width)
        _GROWN[key] = slots


def edgescan_occlusion(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    grid: tuple[int, int] = (12, 20),
    directions: tuple[int, int] = (32, 32),
    shell: float = 1.5,
    *,
    edge_table: EdgeTable | None = None,
    slots: tuple[int, int, int, int] | None = None,
) -> tuple[Bool[Array, "T P Ny Nx"], Bool[Array, ""]]:
    """Occlusion images (T, P, N_y, N_x) of the gnomonic cone rays, and the ``overflow`` flag.

    ``occ[i, j, y, x]`` is True iff the ray from the shell point ``p_ij`` through the centre of
    pixel (y, x) (directions of :func:`edgescan_cone_directions`, in the local frame at
    (θ_i, φ_j)) hits the mesh at t > 0. With concrete vertices an overflow of the static slots
    is repaired by recomputing with larger ones (the flag is then False); with traced vertices an
    overflow raises at run time (``eqx.error_if``) and the flag is True.
    """
    vertices, faces, table, grid, directions, shell, slots = _resolve(
        vertices, faces, grid, directions, shell, edge_table, slots
    )
    diff, overflow, _, _ = _compute(vertices, faces, table, grid, directions, shell, slots)
    occ = jnp.swapaxes(_stage_occlusion(diff), -1, -2)  # (G, N_y, N_x)
    return occ.reshape(*grid, *directions), jnp.asarray(overflow)


def bsv_mesh_edgescan(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    n: int = 4,
    grid: tuple[int, int] = (12, 20),
    directions: tuple[int, int] = (32, 32),
    shell: float = 1.5,
    *,
    edge_table: EdgeTable | None = None,
    slots: tuple[int, int, int, int] | None = None,
    on_overflow: str = "raise",
) -> BSV:
    """BSV of a closed mesh by the silhouette-edge scanline on a gnomonic cone image.

    Args:
        vertices: (V, 3) float, world units. faces: (F, 3) int, closed, consistently wound,
            edge-manifold (checked by :func:`build_edge_table`).
        n: SH bands (n² coefficients). grid: (T, P) shell points (see ``_frames``).
        directions: (N_y, N_x) pixels of the gnomonic image of the cone holding the bounding
            sphere (half-angle ``asin(1/shell)``); pixel centres are the ray directions.
        shell: R / r > 1.
        edge_table: :func:`build_edge_table` of ``faces``; if None it is built once per topology
            and cached (keyed by a hash of the faces).
        slots: static ``(S, S2, S3, K)`` from :func:`edgescan_slots` on the rest pose. If None and
            the vertices are concrete, they are measured on the first pose seen with this topology
            and configuration and reused for later poses (an overflow then grows them once); if
            the vertices are traced, generous defaults from the face count are used (pass slots
            for speed under ``jit``).

    Returns:
        :class:`BSV` with ``coeffs`` (T, P, n²) = ``√(4π)·e0 − Σ_pixels occ·w·Y``: directions
        outside the image are free and enter exactly through the constant term.

    Overflow of the static slots is never silent: with concrete vertices the computation is
    redone with larger slots (one more compile, remembered for later calls). Under tracing,
    ``on_overflow="raise"`` raises at run time (``eqx.error_if``); ``on_overflow="brute"`` returns
    the brute-force BSV of :func:`jshadow.visibility.bsv_mesh` instead (rays over a
    Gauss–Legendre hemisphere of the same ``directions``: another quadrature of the same integral,
    compiled as the other branch of a conditional and run only when the slots overflow). The
    coefficients have zero derivative with respect to the vertices (binary visibility); ``center``
    and ``radius`` are differentiable.
    """
    if not (isinstance(n, int | np.integer) and n >= 1):
        raise ValueError(f"n (number of SH bands) must be a positive int, got {n!r}")
    if on_overflow not in ("raise", "brute"):
        raise ValueError(f"on_overflow must be 'raise' or 'brute', got {on_overflow!r}")
    vertices, faces, table, grid, directions, shell, slots = _resolve(
        vertices, faces, grid, directions, shell, edge_table, slots
    )
    basis_w = _basis_weights(directions, shell, int(n), vertices.dtype)

    def finish(diff):
        return _stage_sh(diff, basis_w, n=int(n), grid=grid)

    fallback = on_overflow == "brute" and isinstance(vertices, jax.core.Tracer)
    coeffs, overflow, center, radius = _compute(
        vertices, faces, table, grid, directions, shell, slots, finish, check=not fallback
    )
    if fallback:
        from ._bsv import bsv_mesh  # (_bsv imports this module lazily too)

        def brute(v):
            return bsv_mesh(v, faces, int(n), grid, directions, shell, method="brute").coeffs

        coeffs = lax.cond(overflow, brute, lambda v: coeffs, vertices)
    return BSV(coeffs, center, radius, shell * radius)


_OF: dict = {}  # (topology, dtype, grid, directions, shell, n) -> the compiled vertices-then-BSV call


def bsv_mesh_edgescan_of(
    vertices_fn,
    args: tuple,
    faces: Int[np.ndarray, "F 3"],
    num_vertices: int,
    dtype,
    n: int = 4,
    grid: tuple[int, int] = (12, 20),
    directions: tuple[int, int] = (32, 32),
    shell: float = 1.5,
) -> BSV:
    """:func:`bsv_mesh_edgescan` of the vertices ``vertices_fn(*args)``, computed together with them
    in one compiled call (for a renderer's per-frame BSV of a deforming mesh).

    Same values as ``bsv_mesh_edgescan(vertices_fn(*args), faces, n, grid, directions, shell)`` on
    concrete vertices, with the same slots: measured on the first pose of this topology and
    configuration (``vertices_fn`` then also runs once on its own), grown after an overflow, which
    reruns the call with the larger slots (one compile per slot size, as there). Slots measured or
    grown here are the ones :func:`bsv_mesh_edgescan` uses later, and the other way round.

    Args:
        vertices_fn: a jit-compatible function of ``args`` returning (V, 3) float vertices of
            ``dtype``; the same function object is compiled once per slot size (it is a static
            argument of the compiled call). args: concrete arrays and pytrees, traced in the call.
        faces: (F, 3) concrete int array (closed, consistently wound, edge-manifold).
        num_vertices: V. dtype: the vertices' float dtype.
    """
    if not (isinstance(n, int | np.integer) and n >= 1):
        raise ValueError(f"n (number of SH bands) must be a positive int, got {n!r}")
    grid, directions = _check_pair(grid, "grid"), _check_pair(directions, "directions")
    shell = _check_shell(shell)
    faces = np.asarray(faces, np.int32)  # as bsv_mesh_edgescan keys them: the same slots
    dtype = jnp.dtype(dtype)
    key = _rest_key(faces, num_vertices, dtype, grid, directions, shell)
    table = _cached_edge_table(faces, num_vertices)
    if key in _REST_SLOTS:
        slots = _REST_SLOTS[key]
    else:  # measured on this first pose, as bsv_mesh_edgescan measures it
        slots = _rest_slots(jnp.asarray(vertices_fn(*args), dtype), faces, table, grid, directions, shell)
    slots = _check_slots(slots, *_slot_bounds(table, grid, directions))
    run_key = (*key, int(n))
    if run_key not in _OF:
        if len(_OF) >= 16:
            _OF.clear()
        _OF[run_key] = _vertices_then_bsv(faces, _basis_weights(directions, shell, int(n), dtype), int(n))
    run = partial(_OF[run_key], vertices_fn, args, table, grid, directions, shell)
    coeffs, _, _, center, radius = _until_fits(run, table, grid, directions, shell, slots)
    return BSV(coeffs, center, radius, shell * radius)


def _vertices_then_bsv(faces: np.ndarray, basis_w, n: int):
    """The compiled call of :func:`bsv_mesh_edgescan_of` for one topology (``faces`` closed over:
    concrete in the trace)."""

    @eqx.filter_jit
    def run(vertices_fn, args, table, grid, directions, shell, slots):
        v = vertices_fn(*args)
        f = jnp.asarray(faces, jnp.int32)
        diff, overflow, counts, center, radius = _run(v, f, table, grid, directions, shell, slots)
        return _stage_sh(diff, basis_w, n=n, grid=grid), overflow, counts, center, radius

    return run


def bsv_and_occlusion_edgescan(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    n: int = 4,
    grid: tuple[int, int] = (12, 20),
    directions: tuple[int, int] = (32, 32),
    shell: float = 1.5,
) -> tuple[BSV, Bool[Array, "T P Ny Nx"]]:
    """:func:`bsv_mesh_edgescan` and :func:`edgescan_occlusion` of the same pose from one pass.

    Both are finishes of the same difference images, so a caller that needs the SH and the
    binary images (``light_visibility = "images"`` on a deforming mesh) pays for one edge-scan.
    Same values as the two functions called apart; concrete vertices only (overflows repaired as
    there).
    """
    if not (isinstance(n, int | np.integer) and n >= 1):
        raise ValueError(f"n (number of SH bands) must be a positive int, got {n!r}")
    if isinstance(vertices, jax.core.Tracer):
        raise TypeError(
            "bsv_and_occlusion_edgescan takes concrete vertices (call the two functions under jit)"
        )
    vertices, faces, table, grid, directions, shell, slots = _resolve(
        vertices, faces, grid, directions, shell, None, None
    )
    basis_w = _basis_weights(directions, shell, int(n), vertices.dtype)

    def finish(diff):
        occ = jnp.swapaxes(_stage_occlusion(diff), -1, -2).reshape(*grid, *directions)
        return _stage_sh(diff, basis_w, n=int(n), grid=grid), occ

    (coeffs, occ), _, center, radius = _compute(
        vertices, faces, table, grid, directions, shell, slots, finish
    )
    return BSV(coeffs, center, radius, shell * radius), occ


@lru_cache(maxsize=32)
def _np_basis_weights(directions, shell, n, dtype_name):
    ny, nx = directions
    with jax.ensure_compile_time_eval():
        d, w = edgescan_cone_directions(directions, shell, dtype_name)
        bw = np.asarray(sh_basis(d, n) * w[:, None])
    return np.ascontiguousarray(bw.reshape(ny, nx, -1).transpose(1, 0, 2).reshape(ny * nx, -1))


_DEVICE_BASIS: dict = {}


def _basis_weights(directions, shell, n, dtype):
    """``w_k · Y(ω_k)`` (K, n²) of the pixel-centre directions, column-major pixel order, cached."""
    key = (directions, shell, n, jnp.dtype(dtype).name)
    if key not in _DEVICE_BASIS:
        with jax.ensure_compile_time_eval():
            _DEVICE_BASIS[key] = jnp.asarray(_np_basis_weights(*key))
    return _DEVICE_BASIS[key]
