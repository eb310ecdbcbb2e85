"""Vertex derivative of the edge-scan BSV along its pixel columns and rows ("scanline" derivative).

The edge-scan (:mod:`jshadow.visibility._edgescan`) finds, in each pixel column ``x_j`` of a view's
gnomonic image, the points ``y_c`` where projected silhouette edges cross the column; the layer
count at a pixel centre is the signed number of crossings below it, and a pixel is occluded iff its
count is non-zero. With ``O_i = ∫_Ω Y_i J dx dy`` the occluded part of the visibility integral
(``J = ρ⁻³``, ``ρ = |(x, y, 1)|``; the BSV is ``V_i = √(4π)·δ_i0 − O_i``, notation of
:mod:`._edgescan_grad`), a motion of the boundary of Ω changes it by the line integral
``dO_i = ∮ Y_i J v dl``. Along one projected edge, with slope ``s`` in the image, ``v dl = ẏ dx``
where ``ẏ`` is the edge's vertical speed at fixed x (and ``= ẋ dy`` with the roles traded), so the
edge's part of the line integral can be summed over the pixel columns it crosses,

    Σ_j Δx · σ_c · Y_i J (x_j, y_c) · ẏ_c,

or over the pixel rows. σ_c = +1 where the scan line leaves Ω going up (count before ≠ 0, after = 0),
−1 where it enters it, 0 elsewhere (a crossing between two occluded layers). A Riemann sum at the
pixel spacing converges slowly for steep edges (few crossings with large ``ẏ_c``: a convex mesh's
derivative is 20 % off at 32² with columns alone), so each edge's integral is split by the direction
of the edge: the share cos²φ = 1/(1 + s²) is taken along the columns and sin²φ along the rows (both
sums are of the same integral, so any split that adds to one is consistent): 1.3 % there.

The count before a crossing is exact: the forward pass's count at the pixel centre before it plus
the signed crossings between that centre and it. The row scan runs the forward pass's slot stages on
the transposed image; its count at a pixel centre is the column scan's, negated (a transposition
reverses orientation; only count = 0 matters). The crossings of one cell (between two pixel centres
on a line) are ordered by one stable argsort of uint32 keys (cell, height in the cell, sign) over
both scans (:func:`jshadow._sorting.argsort_keys`: NumPy's sort on the CPU, where XLA's sort with a
payload is slow); the height is quantised to 1/2^12 of a pixel at the default sizes, so crossings
closer than that may be taken in either order (equal keys in the order of the crossing list). No
ray is cast and no per-pixel list is built.

The crossing of edge (a, b) with column x_j is ``y_c = y_a + (x_j − x_a)·s``. With
``t = (x_j − x_a)/(x_b − x_a)``, local coordinates ``q = Fᵀ(X − p)`` and the line's normal
``n = (−s, 1, s·x_a − y_a)`` (the same at both ends),

    ẏ_c = (1 − t)/q_a,z · (F n)·(δX_a − δp) + t/q_b,z · (F n)·(δX_b − δp),

linear in the vertex and viewpoint motion (p = c(X) + shell·r(X)·u, differentiated as in
:mod:`._edgescan_grad`). ``Y_i J`` is read from a table on every line at ``refine`` points per pixel
(linear between them). Only the crossings with σ ≠ 0 are carried into the linear part (compacted
into measured static slots).

What this derivative is, and is not: a Riemann sum at the pixel spacing of the boundary integral
that :mod:`._edgescan_grad` integrates with Gauss nodes on every projected edge. An edge smaller than
a pixel crosses a scan line or not, so the derivative of a single vertex is noisier (whole-frame
per-vertex gradients of the shipped scenes: 4–19 % from the Gauss-node one), while smooth motions
agree with it and with finite differences (tests/test_edgescan_scan.py, BENCHMARKS.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import lru_cache, partial
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike, Float, Int

from .._sorting import PAD, argsort_keys
from ..sh._grids import _np_sh_basis
from ._bsv_grad import _sample_points
from ._edgescan import (
    _WORD,
    EdgeTable,
    _basis_weights,
    _cached_edge_table,
    _check_slots,
    _compact,
    _compute,
    _cumsum,
    _pack,
    _project_sh,
    _resolve,
    _round_up,
    _run,
    _slot_bounds,
    _slots_of_starts,
    _stage_candidates,
    _stage_counts,
    _stage_gather,
    _stage_project,
    _stage_slots,
    _stage_views,
    _tiers,
    always,
    bsv_mesh_edgescan,
    staged,
)

__all__ = ["bsv_mesh_edgescan_scan_diff", "edgescan_scan_slots", "scan_crossings"]

_OVERFLOW = (
    "edge-scan slots overflowed in the scanline derivative: a traced pose needs more (silhouette "
    "edge, view) slots than were measured, and crossings would be missing from the derivative. "
    "Pass larger slots (see jshadow.visibility.edgescan_slots) or differentiate once at a concrete "
    "pose as deformed as the traced ones"
)


@lru_cache(maxsize=32)
def _np_line_basis(directions, shell, n, refine):
    """``Y_i J`` along the scan lines, per view: (L, n²) with ``L = N_x·(refine·N_y + 1) +
    N_y·(refine·N_x + 1)``: first every pixel column x_j at ``refine·N_y + 1`` heights (column j's
    contiguous), then every pixel row y_i at ``refine·N_x + 1`` positions (row i's contiguous)."""
    ny, nx = directions
    tan_a = 1.0 / math.sqrt(shell * shell - 1.0)
    xc = -tan_a + (np.arange(nx) + 0.5) * (2.0 * tan_a / nx)
    yc = -tan_a + (np.arange(ny) + 0.5) * (2.0 * tan_a / ny)
    ye = np.linspace(-tan_a, tan_a, refine * ny + 1)
    xe = np.linspace(-tan_a, tan_a, refine * nx + 1)
    cols = np.stack(np.broadcast_arrays(xc[:, None], ye[None, :], 1.0), axis=-1).reshape(-1, 3)
    rows = np.stack(np.broadcast_arrays(xe[None, :], yc[:, None], 1.0), axis=-1).reshape(-1, 3)
    d = np.concatenate([cols, rows])
    rho = np.linalg.norm(d, axis=-1)
    return _np_sh_basis(d / rho[:, None], n) * (rho**-3.0)[:, None]


def _line_basis(directions, shell, n, refine, dtype):
    with jax.core.eval_context():
        return jnp.asarray(_np_line_basis(directions, shell, n, refine), dtype)


def _key_bits(views, directions):
    """Bits of the sort key: (cell bits, fraction bits); one bit is left for the crossing's sign."""
    ny, nx = directions
    cells = views * (nx * (ny + 1) + ny * (nx + 1))  # the column scan's cells, then the row scan's
    cbits = int(cells).bit_length()  # cells < 2^cbits: the all-ones cell is free for padding
    fbits = 31 - cbits
    if fbits < 6:
        raise ValueError(
            f"the scanline derivative's sort key has room for {views} views of {ny}×{nx} pixels only "
            f"with {fbits} bits of height within a pixel (at least 6 are needed): use fewer directions"
        )
    return cbits, fbits


def _merge(cols, rows, counts, slot, slot_r, *, views, directions):
    """The crossings of both scans as one list (field ``tr``: the row scan), with cell and slot
    indices offset past the column scan's, and the layer counts both scans read (flat): the column
    scan's (G, N_x, N_y) then the row scan's, the transposed and negated counts (a transposition
    reverses orientation; only count = 0 matters)."""
    ny, nx = directions
    rows = dict(rows, sid=rows["sid"] + slot.shape[0], cell=rows["cell"] + views * nx * (ny + 1))
    cr = {k: jnp.concatenate([cols[k], rows[k]]) for k in cols}
    cr["tr"] = jnp.arange(cr["y"].shape[0]) >= cols["y"].shape[0]
    flat = jnp.concatenate([counts.reshape(-1), -jnp.swapaxes(counts, 1, 2).reshape(-1)])
    return cr, flat, jnp.concatenate([slot, slot_r])


def _boundary_sign(cr, counts, *, views, directions, shell):
    """σ per crossing (C,): +1 where its scan line leaves the occluded set going up (rows: right),
    −1 where it enters it, 0 elsewhere and on padding; from the exact layer count just before the
    crossing: the count at the pixel centre before it plus the signed crossings between the two
    (those of the same cell, found by one stable argsort of uint32 keys (cell, height in the cell,
    sign); padding takes the key ``PAD`` and is left out of the CPU sort)."""
    ny, nx = directions
    tan_a = 1.0 / math.sqrt(shell * shell - 1.0)
    cbits, fbits = _key_bits(views, directions)
    valid, cell, row, w, tr = cr["valid"], cr["cell"], cr["row"], cr["w"], cr["tr"]
    lines = jnp.where(tr, nx, ny)  # pixel centres along this crossing's scan line
    step = 2.0 * tan_a / lines
    frac = (cr["y"] + tan_a) / step - 0.5 - (row - 1).astype(cr["y"].dtype)  # from the centre before
    yq = jnp.clip(jnp.floor(frac * (1 << fbits)), 0, (1 << fbits) - 1).astype(jnp.uint32)
    key = (cell.astype(jnp.uint32) << (fbits + 1)) | (yq << 1) | (w > 0).astype(jnp.uint32)
    key = jnp.where(valid, key, jnp.uint32(PAD))  # a valid cell is below the all-ones one
    perm = argsort_keys(key)
    sk = key[perm]
    scell = sk >> (fbits + 1)
    sw = jnp.where((sk & 1) == 1, 1, -1).astype(jnp.int32)
    idx = jnp.arange(sk.shape[0], dtype=jnp.int32)
    first = jnp.concatenate([jnp.ones((1,), bool), scell[1:] != scell[:-1]])
    start = lax.associative_scan(jnp.maximum, jnp.where(first, idx, 0))
    cs = _cumsum(sw)
    before = cs - sw - (cs[start] - sw[start])  # signed crossings earlier in the same cell
    extra = jnp.zeros_like(before).at[perm].set(before, unique_indices=True)
    offset = jnp.where(tr, views * nx * (ny + 1), 0)
    line = (cell - offset - row) // (lines + 1)  # view·(lines of the scan) + line
    flat = jnp.where(tr, views * nx * ny, 0) + line * lines + row - 1
    flat = jnp.clip(flat, 0, counts.shape[0] - 1)
    below = jnp.where(row >= 1, counts[flat], 0.0) + extra.astype(counts.dtype)
    above = below + w
    leave = (below != 0) & (above == 0)
    enter = (below == 0) & (above != 0)
    return jnp.where(valid, leave.astype(w.dtype) - enter.astype(w.dtype), 0.0)


def _compact_boundary(cr, sigma, size):
    """The crossings with σ ≠ 0 (the only ones the tangent carries), compacted into ``size`` slots
    (all of them, uncompacted, when ``size`` ≥ their number C); and how many there are ()."""
    live = sigma != 0
    count = jnp.sum(live, dtype=jnp.int32)
    c = sigma.shape[0]
    if size >= c:
        return cr, sigma, count
    pos, _ = _compact(_pack(jnp.pad(live, (0, (-c) % _WORD))), size)
    ok = pos >= 0
    p = jnp.where(ok, pos, 0)
    out = {k: v[p] for k, v in cr.items()}
    out["valid"] = out["valid"] & ok
    return out, jnp.where(ok, sigma[p], 0.0), count


class _CrossingEdges(NamedTuple):
    """Per crossing (C,), its edge in its view's frame (for the row scan x and y trade places)."""

    va: Array  # the edge's vertex ids
    vb: Array
    view: Array
    frame: Array  # (C, 3, 3) world = frame @ local
    qaz: Array  # the end points' depths (1 where the crossing is not valid)
    qbz: Array
    xa: Array  # the first end point in the image
    ya: Array
    run: Array  # x_b − x_a (1 where it does not cross)
    slope: Array  # along the scan (0 where it does not cross)
    crosses: Array  # valid, not parallel to its line within 1e-6 (its tangent is dropped)
    xj: Array  # the crossing line's centre coordinate


def _crossing_edges(x, cr, slot, table, *, grid, directions, shell) -> _CrossingEdges:
    """The edge of each crossing recomputed from its two vertices and its view's sample point and
    frame (differentiable in ``x``; :func:`_terms`, and the coverage images' crossing heights)."""
    ny, nx = directions
    views = grid[0] * grid[1]
    tan_a = 1.0 / math.sqrt(shell * shell - 1.0)
    tr = cr["tr"]
    s = slot[cr["sid"]]
    edge, view = s // views, s % views
    va, vb = table.a[edge], table.b[edge]
    points, frames = _sample_points(x, grid, shell)
    f = frames[view]  # (C, 3, 3) world = F @ local
    f = jnp.where(tr[:, None, None], f[:, :, jnp.array([1, 0, 2])], f)  # rows: local' = (y, x, z)
    qa = jnp.einsum("cji,cj->ci", f, x[va] - points[view])  # Fᵀ(X − p)
    qb = jnp.einsum("cji,cj->ci", f, x[vb] - points[view])
    valid = cr["valid"] & (qa[:, 2] > 0) & (qb[:, 2] > 0)
    qaz = jnp.where(valid, qa[:, 2], 1.0)
    qbz = jnp.where(valid, qb[:, 2], 1.0)
    xa, ya, xb, yb = qa[:, 0] / qaz, qa[:, 1] / qaz, qb[:, 0] / qbz, qb[:, 1] / qbz
    run = xb - xa
    crosses = valid & (run != 0)
    run = jnp.where(crosses, run, 1.0)  # double where: no division for padding
    slope = jnp.where(crosses, (yb - ya) / run, 0.0)
    # an edge steeper than 1e6 along this scan has a share below 1e-12 here (the other scan takes
    # it): dropped, so that a near-zero run cannot make the slope overflow (inf · 0 below)
    crosses = crosses & (jnp.abs(slope) < 1e6)
    slope = jnp.where(crosses, slope, 0.0)
    lines = jnp.where(tr, ny, nx)  # lines of this scan (columns: N_x; rows: N_y)
    xj = (cr["col"].astype(x.dtype) + 0.5) * (2.0 * tan_a / lines) - tan_a
    return _CrossingEdges(va, vb, view, f, qaz, qbz, xa, ya, run, slope, crosses, xj)


def _terms(x, cr, sigma, slot, table, *, grid, directions, shell, refine):
    """Primal per-crossing terms of the tangent: vertex ids ``va, vb`` (C,), view (C,), ``fa, fb``
    (C, 3) world vectors with ``share·σ·Δ·ẏ_c = fa·(δX_a − δp) + fb·(δX_b − δp)`` (for the row scan
    x and y trade places), and the linear splat of each crossing onto its line's table positions
    (:func:`_np_line_basis`): ``idx`` (C, 2) within a view's table, ``lin`` (C, 2)."""
    ny, nx = directions
    tan_a = 1.0 / math.sqrt(shell * shell - 1.0)
    dtype = x.dtype
    tr = cr["tr"]
    e = _crossing_edges(x, cr, slot, table, grid=grid, directions=directions, shell=shell)
    va, vb, view, f, qaz, qbz, xa, ya, run, slope, crosses, xj = e
    lines = jnp.where(tr, ny, nx)  # lines of this scan (columns: N_x; rows: N_y)
    heights = jnp.where(tr, nx, ny) * refine  # table intervals along one line
    spacing = 2.0 * tan_a / lines
    t = jnp.clip((xj - xa) / run, 0.0, 1.0)
    nrm = jnp.stack([-slope, jnp.ones_like(slope), slope * xa - ya], axis=-1)
    fn = jnp.einsum("cij,cj->ci", f, nrm)  # F n (world)
    # the share of this edge's boundary integral taken along this scan's lines: cos²φ = 1/(1 + s²)
    # of its direction to the lines' normal (the other scan takes sin²φ; s is its slope here)
    share = 1.0 / (1.0 + slope * slope)
    k = jnp.where(crosses, sigma * spacing * share, 0.0)
    fa = fn * (k * (1.0 - t) / qaz)[:, None]
    fb = fn * (k * t / qbz)[:, None]
    u = (cr["y"] + tan_a) * (heights / (2.0 * tan_a))
    k0 = jnp.clip(jnp.floor(u), 0, heights - 1)
    g = jnp.clip(u - k0, 0.0, 1.0)
    first = jnp.where(tr, nx * (refine * ny + 1), 0)  # the row scan's part of the table
    i0 = first + cr["col"] * (heights + 1) + k0.astype(jnp.int32)
    idx = view[:, None] * _np_line_basis_rows(directions, refine) + jnp.stack([i0, i0 + 1], axis=-1)
    lin = jnp.stack([1.0 - g, g], axis=-1).astype(dtype)
    return va, vb, view, fa, fb, idx, lin


def _np_line_basis_rows(directions, refine):
    """Rows of :func:`_np_line_basis` per view."""
    ny, nx = directions
    return nx * (refine * ny + 1) + ny * (refine * nx + 1)


def _apply(terms, line_basis, dvertices, dpoints, *, views):
    """The linear part: dV (G, n²) from the vertex motion (V, 3) and the viewpoint motion (G, 3)."""
    va, vb, view, fa, fb, idx, lin = terms
    dp = dpoints[view]
    u = jnp.sum(fa * (dvertices[va] - dp), axis=-1) + jnp.sum(fb * (dvertices[vb] - dp), axis=-1)
    c = line_basis.shape[0]
    d = jnp.zeros(views * c, u.dtype).at[idx.reshape(-1)].add((lin * u[:, None]).reshape(-1))
    return -(d.reshape(views, c) @ line_basis)  # V = √(4π)e₀ − O


def _start_rows(py, *, directions, shell):
    """First pixel-centre row ``y_i ≥ y`` per (vertex, view): the row scan's start index (as the
    forward pass's start column)."""
    ny, _ = directions
    tan_a = 1.0 / math.sqrt(shell * shell - 1.0)
    dy = 2.0 * tan_a / ny
    dtype = jnp.uint8 if ny < 255 else jnp.int32
    return jnp.clip(jnp.ceil((py + tan_a) / dy - 0.5), 0, ny).astype(dtype)


def _scan_lists(x, faces, table, grid, directions, shell, slots, row_slots, n, with_counts=False):
    """One edge-scan pass and both scans' crossings: the forward coefficients (G, n²), the merged
    crossings (:func:`_merge`), their σ (:func:`_boundary_sign`), the slots of both scans (for the
    crossings' ``sid``) and the sizes needed (8,): the column scan's ``(S, S2, S3, K)``, then the
    row scan's; ``with_counts`` appends the layer counts at the pixel centres (G, N_x, N_y)."""
    views = grid[0] * grid[1]
    ny, nx = directions
    diff, _, need, _, radius, (slot, cols, (px, py, front)) = _run(
        x, faces, table, grid, directions, shell, slots, with_params=True
    )
    stage = partial(staged, always(radius))
    counts = stage(_stage_counts, diff)  # (G, N_x, N_y): winding number at the pixel centres
    out = _project_sh(counts != 0, _basis_weights(directions, shell, n, x.dtype), n)
    # the row scan: the forward pass's steps on the transposed image, with its own slots of the
    # edges that cross a pixel row
    start = stage(partial(_start_rows, directions=directions, shell=shell), py)
    cand = stage(_stage_candidates, front, start, table.a, table.b, table.t1, table.t2)
    slot_r, most_r = stage(partial(_stage_slots, slots=row_slots[0]), cand)
    gather = partial(_stage_gather, directions=(nx, ny))
    params_r = stage(gather, slot_r, py, px, start, front, table.a, table.b, table.t1)
    tiers = partial(_tiers, directions=(nx, ny), shell=shell, long_slots=row_slots[1:3], span=row_slots[3])
    rows, need_r = stage(tiers, params_r, most_r)
    merge = partial(_merge, views=views, directions=directions)
    cr, flat, slot_all = stage(merge, cols, rows, counts, slot, slot_r)
    sigma = stage(partial(_boundary_sign, views=views, directions=directions, shell=shell), cr, flat)
    if with_counts:
        return out, cr, sigma, slot_all, jnp.concatenate([need, need_r]), counts
    return out, cr, sigma, slot_all, jnp.concatenate([need, need_r])


def _primal(x, faces, table, grid, directions, shell, slots, scan_slots, refine, n):
    """The forward coefficients (G, n²) and the tangent's primal terms of one pass (column and row
    scans); the overflow flag and the sizes needed (9,): the column scan's ``(S, S2, S3, K)``, the
    row scan's, and the boundary crossings."""
    out, cr, sigma, slot_all, need = _scan_lists(
        x, faces, table, grid, directions, shell, slots, scan_slots[:4], n
    )
    stage = partial(staged, always(x))
    cr, sigma, n_boundary = stage(partial(_compact_boundary, size=scan_slots[4]), cr, sigma)
    term_fn = partial(_terms, grid=grid, directions=directions, shell=shell, refine=refine)
    terms = stage(term_fn, x, cr, sigma, slot_all, table)
    need = jnp.concatenate([need, n_boundary[None]]).astype(jnp.int32)
    limit = jnp.asarray([*slots, *scan_slots], jnp.int32)
    return (out, terms), jnp.any(need > limit), need


_primal_jit = jax.jit(_primal, static_argnums=(3, 4, 5, 6, 7, 8, 9))


def _entries(s):
    """Crossing entries of a scan with slots ``(S, S2, S3, K)``: ``S + S2 + S3·(K − 2)``."""
    return s[0] + s[1] + s[2] * max(s[3] - 2, 0)


def _check_scan_slots(scan_slots, slots, cap, directions):
    """``scan_slots`` as five ints: the row scan's ``(S, S2, S3, K)`` (rounded and capped as the
    edge-scan's) and the boundary crossings of both scans (at most all their crossings: all of them
    means no compaction). None: the column scan's slots for the rows and no compaction."""
    if scan_slots is None:
        scan_slots = (*slots, 2 * _entries(slots))
    if not (
        isinstance(scan_slots, tuple | list)
        and len(scan_slots) == 5
        and all(isinstance(x, int | np.integer) and not isinstance(x, bool) and x >= 1 for x in scan_slots)
    ):
        raise ValueError(
            "scan_slots must be five positive ints (row S, S2, S3, K, boundary crossings) "
            f"(see edgescan_scan_slots), got {scan_slots!r}"
        )
    rows = _check_slots(tuple(int(x) for x in scan_slots[:4]), cap, directions[0])
    boundary = min(_round_up(int(scan_slots[4]), _WORD), _entries(slots) + _entries(rows))
    return (*rows, boundary)


def _grow(sizes, need, slots, cap, directions):
    """Sizes (forward slots, scan slots) grown to at least 1.25× what a pose needed."""
    want = [max(x, math.ceil(1.25 * y)) for x, y in zip((*slots, *sizes), need, strict=True)]
    slots = _check_slots(tuple(want[:4]), cap, directions[1])
    return slots, _check_scan_slots(tuple(want[4:]), slots, cap, directions)


def edgescan_scan_slots(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    grid: tuple[int, int] = (12, 20),
    directions: tuple[int, int] = (32, 32),
    shell: float = 1.5,
    *,
    margin: float = 1.5,
    edge_table: EdgeTable | None = None,
    slots: tuple[int, int, int, int] | None = None,
) -> tuple[int, int, int, int, int]:
    """Static sizes for :func:`bsv_mesh_edgescan_scan_diff`'s ``scan_slots``, measured on a concrete
    pose, times ``margin``: the row scan's ``(S, S2, S3, K)`` (as :func:`edgescan_slots` for the
    columns) and the boundary crossings (σ ≠ 0) of both scans together (the bunny at 32²: about a fifth
    of its crossings). ``slots``: the forward pass's (None: measured on the first pose
    of this topology, as :func:`bsv_mesh_edgescan` does)."""
    if not (isinstance(margin, int | float) and margin >= 1.0):
        raise ValueError(f"margin must be a number >= 1, got {margin!r}")
    vertices, faces_j, table, grid, directions, shell, slots = _resolve(
        vertices, faces, grid, directions, shell, edge_table, slots
    )
    if isinstance(vertices, jax.core.Tracer):
        raise TypeError("edgescan_scan_slots measures a concrete pose")
    # the row scan's slots: edgescan_slots of the transposed image, counted on the host
    _, _, comps, offset = _stage_views(vertices, faces_j, grid=grid, shell=shell)
    _, py, _, front = _stage_project(comps, offset, directions=directions, shell=shell)
    start = _start_rows(py, directions=directions, shell=shell)
    cap, width = int(table.a.shape[0]) * grid[0] * grid[1], directions[0]
    rows = _slots_of_starts(start, np.asarray(front), table, margin, width)
    rows = _check_slots(rows, cap, width)
    # boundary crossings: one pass without compaction (sizes grown and rerun if the pose needs more),
    # with the row slots rounded up to powers of two so that the poses of one mesh share its
    # compilation (any slots at least the counts give the same crossings)
    pow2 = tuple(1 << max(5, (int(x) - 1).bit_length()) for x in rows[:3])
    sizes = _check_scan_slots((*pow2, width, 1 << 30), slots, cap, directions)
    while True:
        _, overflow, need = _primal_jit(vertices, faces_j, table, grid, directions, shell, slots, sizes, 1, 1)
        if not bool(overflow):
            break
        slots, sizes = _grow(sizes, [int(x) for x in np.asarray(need)], slots, cap, directions)
        sizes = _check_scan_slots((*sizes[:4], 1 << 30), slots, cap, directions)
    boundary = _round_up(max(1, math.ceil(int(np.asarray(need)[8]) * margin)), _WORD)
    return (*rows, boundary)


def bsv_mesh_edgescan_scan_diff(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    n: int = 4,
    grid: tuple[int, int] = (12, 20),
    directions: tuple[int, int] = (32, 32),
    shell: float = 1.5,
    *,
    edge_table: EdgeTable | None = None,
    slots: tuple[int, int, int, int] | None = None,
    scan_slots: tuple[int, ...] | Callable[[], tuple[int, ...] | None] | None = None,
    refine: int = 4,
) -> Float[Array, "T P n2"]:
    """Edge-scan BSV coefficients (T, P, n²) with the scanline derivative (module docstring).

    The primal is exactly :func:`jshadow.visibility.bsv_mesh_edgescan` ``(...).coeffs``. Its
    ``jax.jvp`` is the boundary term of the visibility integral, taken along the pixel columns and
    the pixel rows of the edge-scan's image (each edge's share by its direction), including the
    motion of the sample points ``p = c(X) + shell·r(X)·u``; ``jax.grad``/``jax.vjp`` are its
    transpose.

    Args:
        vertices: (V, 3) float, world units. faces: (F, 3) int, concrete, closed, consistently
            wound, edge-manifold (as for the edge-scan).
        n, grid, directions, shell, edge_table, slots: as in :func:`bsv_mesh_edgescan`.
        scan_slots: static sizes of the derivative (:func:`edgescan_scan_slots` on the rest pose):
            the row scan's ``(S, S2, S3, K)`` and the boundary crossings of each scan; None: the
            column scan's slots for the rows and no compaction (slower); or a function of no
            arguments returning one of those, called (outside any trace; it must close over
            concrete values only) each time a derivative is traced and never by a forward pass.
            On concrete vertices (an eager derivative) sizes a pose overflows grow and the pass
            reruns; under a trace the primal reruns with 4× the forward slots, and a derivative
            whose sizes overflow raises at run time (crossings would be missing).
        refine: table heights per pixel for ``Y J`` (linear between them).

    Limitations (module docstring): a Riemann sum at the pixel spacing along both image axes, so
    the derivative of one vertex is noisier than the Gauss-node boundary integral of
    :func:`bsv_mesh_edgescan_diff` while smooth motions agree with it; crossings closer than the
    sort key's quantum in one pixel may be taken in either order. The ``center`` and ``radius``
    of the BSV are not returned; take them from :func:`jshadow.geometry.bounding_sphere`.
    """
    if not (isinstance(n, int | np.integer) and n >= 1):
        raise ValueError(f"n (number of SH bands) must be a positive int, got {n!r}")
    if not (isinstance(refine, int | np.integer) and not isinstance(refine, bool) and refine >= 1):
        raise ValueError(f"refine must be a positive int, got {refine!r}")
    faces_np = np.asarray(faces, np.int32)  # concrete topology (raises for traced faces)
    if edge_table is None:
        edge_table = _cached_edge_table(faces_np, jnp.shape(vertices)[0])
    # faces stay numpy: a jnp array made here would be a tracer of the caller's jit, which the
    # derivative rule (traced later, e.g. under jax.grad(jax.jit(...))) must not close over
    vertices, _, table, grid, directions, shell, slots = _resolve(
        vertices, faces_np, grid, directions, shell, edge_table, slots
    )
    n, refine = int(n), int(refine)
    views = grid[0] * grid[1]
    _key_bits(views, directions)  # sizes the sort key cannot hold are an error of this call
    cap, width = _slot_bounds(table, grid, directions)
    larger = _check_slots((4 * slots[0], 4 * slots[1], 4 * slots[2], width), cap, width)
    basis_w = _basis_weights(directions, shell, n, vertices.dtype)

    def sizes():
        with jax.core.eval_context():
            given = scan_slots() if callable(scan_slots) else scan_slots
        return _check_scan_slots(given, slots, cap, directions)

    fixed = None if callable(scan_slots) else sizes()  # bad sizes are an error of this call

    def project(diff):
        return _project_sh(_stage_counts(diff) != 0, basis_w, n)

    def with_rerun(x, out, overflow):
        """``out``, or (a traced pose that overflows the slots) the pass with 4× them, which raises
        at run time only if those overflow too."""
        rerun = partial(_compute, faces=faces_np, table=table, grid=grid, directions=directions, shell=shell)
        return lax.cond(overflow, lambda v: project(rerun(v, slots=larger)[0]), lambda v: out, x)

    @jax.custom_jvp
    def bsv(x):
        if isinstance(x, jax.core.Tracer):
            diff, overflow, *_ = _run(x, faces_np, table, grid, directions, shell, slots)
            return with_rerun(x, project(diff), overflow)
        return bsv_mesh_edgescan(
            x, faces_np, n, grid, directions, shell, edge_table=table, slots=slots
        ).coeffs.reshape(views, -1)

    @bsv.defjvp
    def bsv_jvp(primals, tangents):
        (x,), (dx,) = primals, tangents
        x0 = lax.stop_gradient(x)
        scan = fixed or sizes()
        if isinstance(x0, jax.core.Tracer):
            (out, terms), overflow, need = _primal(
                x0, faces_np, table, grid, directions, shell, slots, scan, refine, n
            )
            out = with_rerun(x0, out, jnp.any(need[:4] > jnp.asarray(slots, jnp.int32)))
            ok = eqx.error_if(jnp.ones((), out.dtype), overflow, _OVERFLOW)
        else:  # concrete (an eager derivative): sizes that overflow grow and the pass reruns
            sl = slots
            while True:
                (out, terms), overflow, need = _primal_jit(
                    x0, faces_np, table, grid, directions, shell, sl, scan, refine, n
                )
                if not bool(overflow):
                    break
                sl, scan = _grow(scan, [int(v) for v in np.asarray(need)], sl, cap, directions)
            ok = jnp.ones((), out.dtype)
        _, dpoints = jax.jvp(lambda v: _sample_points(v, grid, shell)[0], (x0,), (dx,))
        basis = _line_basis(directions, shell, n, refine, out.dtype)
        dout = _apply(terms, basis, dx, dpoints, views=views)
        return out, ok * dout.astype(out.dtype)

    return bsv(vertices).reshape(*grid, n * n)


def scan_crossings(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    grid: tuple[int, int] = (12, 20),
    directions: tuple[int, int] = (32, 32),
    shell: float = 1.5,
    *,
    edge_table: EdgeTable | None = None,
    slots: tuple[int, int, int, int] | None = None,
) -> dict[str, np.ndarray]:
    """The crossings of both scans on one concrete pose and their boundary signs σ (for inspection
    and tests): a dict of numpy arrays ``view``, ``edge``, ``rows`` (True: the row scan), ``line``
    (the column j, or the row i), ``at`` (the crossing's y, or its x), ``w`` (±1, the layer count's
    change going up, or for the row scan its negation going right) and ``sigma``, padding removed."""
    vertices, faces, table, grid, directions, shell, slots = _resolve(
        vertices, faces, grid, directions, shell, edge_table, slots
    )
    if isinstance(vertices, jax.core.Tracer):
        raise TypeError("scan_crossings takes concrete vertices")
    views = grid[0] * grid[1]
    row_slots = edgescan_scan_slots(vertices, faces, grid, directions, shell, edge_table=table, slots=slots)
    run = jax.jit(_scan_lists, static_argnums=(3, 4, 5, 6, 7, 8))
    _, cr, sigma, slot_all, need = run(
        vertices, faces, table, grid, directions, shell, slots, row_slots[:4], 1
    )
    if np.any(np.asarray(need) > np.asarray([*slots, *row_slots[:4]])):
        raise ValueError("edge-scan slots overflowed: pass larger slots (see edgescan_slots)")
    keep = np.asarray(cr["valid"])
    s = np.asarray(slot_all)[np.asarray(cr["sid"])]
    pick = {"rows": "tr", "line": "col", "at": "y", "w": "w"}
    out = {k: np.asarray(cr[v])[keep] for k, v in pick.items()}
    return {"view": (s % views)[keep], "edge": (s // views)[keep], **out, "sigma": np.asarray(sigma)[keep]}
