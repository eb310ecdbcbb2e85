"""Coverage images: the edge-scan's occlusion images made continuous along its scan lines.

The edge-scan (:mod:`jshadow.visibility._edgescan`) samples each shell point's gnomonic image at the
pixel centres: a pixel is occluded (1) or free (0) by the layer count at its centre, a piecewise
constant function of the mesh's vertices with no useful derivative. Along every pixel column,
though, the scan knows more: the heights ``y_i`` where the column's centre line crosses the
boundary of the occluded region Ω, with the sign of the change (the scanline derivative's boundary
crossings, σ ≠ 0, :mod:`jshadow.visibility._edgescan_scan`). The *column coverage* of a pixel is
the fraction of its column's centre line inside the pixel that lies in Ω,

    c = b + Σ_i t_i,   t_i = s_i (1 − f_i) if f_i > ½ else −s_i f_i,

with ``b`` the pixel's centre value, ``f_i`` the crossing's height within the pixel (0 at its lower
edge, 1 at its upper) and ``s_i = +1`` where the line enters Ω going up (−1 where it leaves), the
sum over the boundary crossings inside the pixel: the exact measure of Ω on that segment. The *row
coverage* is the same along the pixel rows (the row scan), and the default is their mean.

Unlike the centre samples, the coverage is a continuous function of the vertices: a crossing that
moves through a pixel centre swaps a unit of ``b`` for the same unit of its term, one that moves into
the next pixel takes a term that has gone to 0, and crossings appear and vanish in pairs of opposite
sign at the same height. It is piecewise smooth, and its derivative is exact; only the boundary
crossings carry a tangent (its cost is not measured apart from the lookups'): the
integer structure (which crossing, which pixel, which side of the centre) is the scan's, on
``stop_gradient`` vertices, and each boundary crossing's height is recomputed differentiably from
its edge's two vertices and the view's sample point (p = c(X) + shell·r(X)·u moves with them), so
``dc = −Σ_i s_i dy_i / Δy``. A lookup that reads such images bilinearly is then differentiable
exactly, instead of through a model of the box-filtered pixel (:func:`jshadow.visibility.
image_fan_visibility_components`, whose derivative for the 0/1 images is an estimate).

:func:`coverage_sh` projects such images to BSV coefficients with the edge-scan's pixel weights
(``[method] bsv_images = "coverage"``), whose derivative is then exact as well; for it the
crossings are weighted by their edges' share of each scan (``scans = "split"``), whose derivative
is within 0.5–2.3 % of converged differences where the plain mean's is 13–39 % off.

Accuracy and cost: BENCHMARKS.md "Coverage images" and "BSV from coverage images". Limitations:
the coverage of a pixel is measured on its centre lines only (a feature between two lines is
missed as by the centre samples); the mesh must be one the edge-scan samples (closed, consistently
wound manifold, shell > 1); sizes are static (the scanline derivative's slots, measured on a
concrete pose), and a traced pose that overflows them raises at run time; a crossing of an edge
within 1e-6 of parallel to its scan line carries no derivative (and with "split" no share).
Read by the lookups, rays whose line misses the bounding sphere stay free: where the mesh touches
its bounding sphere a bilinear read can see some coverage there, and the lookup can jump at that
cut (not met by the tests' differences).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ._edgescan import _basis_weights, _cached_edge_table, _grown_key, _project_sh, _resolve, _slot_bounds
from ._edgescan_scan import (
    _check_scan_slots,
    _compact_boundary,
    _crossing_edges,
    _grow,
    _scan_lists,
    edgescan_scan_slots,
)

__all__ = ["scan_coverage", "coverage_sh"]

SCANS = ("both", "split", "columns", "rows")

_COVERAGE_OVERFLOW = (
    "coverage images: the edge-scan's or the scan lines' static sizes overflowed for this pose, and "
    "crossings would be missing; pass larger slots and scan_slots (see edgescan_slots and "
    "edgescan_scan_slots), measured on a pose as deformed as this one"
)


def scan_coverage(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    grid: tuple[int, int] = (12, 20),
    directions: tuple[int, int] = (32, 32),
    shell: float = 1.5,
    *,
    scans: str = "both",
    edge_table=None,
    slots: tuple[int, int, int, int] | None = None,
    scan_slots: tuple[int, ...] | None = None,
) -> Float[Array, "T P Ny Nx"]:
    """Coverage images (T, P, N_y, N_x) in [0, 1] of a closed mesh on the BSV's shell (module
    docstring), in the layout of :func:`jshadow.visibility.edgescan_occlusion`'s 0/1 images, which
    they equal wherever no boundary crosses a pixel's centre lines.

    Args:
        vertices: (V, 3) float, world units; differentiable (``jax.jvp``/``jax.grad``: the exact
            derivative of the coverage, module docstring). faces: (F, 3) int, concrete, closed,
            consistently wound, edge-manifold.
        grid, directions, shell: as for :func:`jshadow.visibility.bsv_mesh_edgescan`.
        scans: "both" (default: the mean of the column and the row coverage), "split" (each
            crossing's term weighted by its edge's share ``1/(1 + s²)`` of its scan, s the edge's
            slope against the scan line: cos²φ along the columns and sin²φ along the rows, so that
            the derivative is the direction-split sum of the scanline derivative rather than the
            plain mean of two Riemann sums, closer to the converged derivative; BENCHMARKS.md "BSV
            from coverage images"), "columns" or "rows".
        edge_table, slots: as for :func:`jshadow.visibility.bsv_mesh_edgescan`.
        scan_slots: the scan lines' sizes (:func:`jshadow.visibility.edgescan_scan_slots`); None
            measures them on concrete ``vertices``, and for traced ones takes the column scan's
            ``slots`` for the rows and keeps every crossing (generous, slower).

    Concrete vertices that overflow the static sizes run again with them grown to 1.25× the counts
    the pose needed (remembered for later calls with the same sizes, as the edge-scan's own
    retries are); traced ones raise at run time (also under ``jax.jit``).
    """
    if scans not in SCANS:
        raise ValueError(f"scans must be one of {SCANS}, got {scans!r}")
    faces_np = np.asarray(faces, np.int32)  # concrete topology (raises for traced faces)
    if edge_table is None:
        edge_table = _cached_edge_table(faces_np, jnp.shape(vertices)[0])
    vertices, faces_j, table, grid, directions, shell, slots = _resolve(
        vertices, faces_np, grid, directions, shell, edge_table, slots
    )
    traced = isinstance(vertices, jax.core.Tracer)
    if scan_slots is None and not traced:
        scan_slots = edgescan_scan_slots(
            vertices, faces_np, grid, directions, shell, edge_table=table, slots=slots
        )
    cap, _ = _slot_bounds(table, grid, directions)
    scan_slots = _check_scan_slots(None if scan_slots is None else tuple(scan_slots), slots, cap, directions)
    key = (_grown_key(table, grid, directions, shell, slots), scan_slots)
    slots, scan_slots = _GROWN.get(key, (slots, scan_slots))
    if traced:
        out, overflow, _ = _coverage_jit(
            vertices, faces_j, table, grid, directions, shell, slots, scan_slots, scans
        )
        return eqx.error_if(out, overflow, _COVERAGE_OVERFLOW)
    while True:  # concrete: sizes a pose overflows grow to 1.25x its counts (the scanline's _grow)
        out, overflow, need = _coverage_jit(
            vertices, faces_j, table, grid, directions, shell, slots, scan_slots, scans
        )
        if not bool(overflow):
            return out
        need = [int(n) for n in np.asarray(need)]
        slots, scan_slots = _GROWN[key] = _grow(scan_slots, need, slots, cap, directions)


def coverage_sh(
    coverage: Float[ArrayLike, "T P Ny Nx"], n: int, directions: tuple[int, int], shell: float
) -> Float[Array, "T P n2"]:
    """BSV coefficients (T, P, n²) projected from occlusion images in [0, 1] (T, P, N_y, N_x), such as
    :func:`scan_coverage`'s: ``√(4π)·e0 − Σ_pixels cov · w·Y`` with the edge-scan's pixel weights
    (solid angle) and directions, so that 0/1 images give exactly the edge-scan's coefficients.
    Linear in the images: the derivative of coverage images carries over exactly."""
    cov = jnp.asarray(coverage)
    t_n, p_n, ny, nx = cov.shape
    if (ny, nx) != tuple(directions):
        raise ValueError(f"coverage_sh: images of {(ny, nx)} pixels, directions {tuple(directions)}")
    cols = jnp.swapaxes(cov.reshape(t_n * p_n, ny, nx), 1, 2)  # the edge-scan's column-major pixels
    basis = _basis_weights(tuple(directions), float(shell), int(n), cov.dtype)
    return _project_sh(cols, basis, int(n)).reshape(t_n, p_n, n * n)


_GROWN: dict = {}  # (configuration, sizes given) -> the sizes they grew to on a concrete pose


def _coverage(x, faces, table, grid, directions, shell, slots, scan_slots, scans):
    ny, nx = directions
    views = grid[0] * grid[1]
    xs = jax.lax.stop_gradient(x)
    _, cr, sigma, slot_all, need, counts = _scan_lists(
        xs, faces, table, grid, directions, shell, slots, scan_slots[:4], 1, with_counts=True
    )
    cr, sigma, n_boundary = _compact_boundary(cr, sigma, scan_slots[4])
    need = jnp.concatenate([need, n_boundary[None]]).astype(jnp.int32)  # as the scanline's _primal
    overflow = jnp.any(need > jnp.asarray([*slots, *scan_slots], jnp.int32))
    tan_a = 1.0 / math.sqrt(shell * shell - 1.0)
    tr = cr["tr"]
    lines = jnp.where(tr, nx, ny)  # pixels along this crossing's scan line
    step = 2.0 * tan_a / lines
    tangent, share = _height_tangent(x, cr, slot_all, table, grid, directions, shell)
    height = cr["y"] + tangent
    pos = (height + tan_a) / step  # continuous pixel coordinate along the line
    cell = jnp.clip(jnp.floor(jax.lax.stop_gradient(pos)), 0, lines - 1)
    frac = pos - cell
    s = -sigma  # +1 where the line enters the occluded set going up (rows: right)
    live = cr["valid"] & (sigma != 0)
    term = jnp.where(live, jnp.where(frac > 0.5, s * (1.0 - frac), -s * frac), 0.0).astype(x.dtype)
    if scans == "split":  # both scans, each crossing weighted by its edge's share (cos²φ, sin²φ)
        term = share * term
    cell = cell.astype(jnp.int32)
    view = slot_all[cr["sid"]] % views
    line = cr["col"]
    # column scan: (view, row = cell, column = line); row scan: (view, row = line, column = cell)
    iy = jnp.where(tr, line, cell)
    ix = jnp.where(tr, cell, line)
    flat = (view * ny + iy) * nx + ix
    binary = (jnp.swapaxes(counts, 1, 2) != 0).astype(x.dtype).reshape(-1)
    size = views * ny * nx
    col = jnp.zeros(size, x.dtype).at[flat].add(jnp.where(tr, 0.0, term))
    row = jnp.zeros(size, x.dtype).at[flat].add(jnp.where(tr, term, 0.0))
    extra = {"both": 0.5 * (col + row), "split": col + row, "columns": col, "rows": row}[scans]
    return (binary + extra).reshape(grid[0], grid[1], ny, nx), overflow, need


_coverage_jit = jax.jit(_coverage, static_argnums=(3, 4, 5, 6, 7, 8))


def _height_tangent(x, cr, slot_all, table, grid, directions, shell):
    """Zero in value, with the derivative of each crossing's height along its line (C,): the height
    of its edge's line at the line's centre coordinate (:func:`._edgescan_scan._crossing_edges`, as
    the scanline derivative's terms recompute it; no tangent for an edge within 1e-6 of parallel
    to its line); and the edge's share ``1/(1 + s²)`` of its scan (C,), differentiable (0 for such
    an edge)."""
    e = _crossing_edges(x, cr, slot_all, table, grid=grid, directions=directions, shell=shell)
    y = e.ya + (e.xj - e.xa) * e.slope
    share = jnp.where(e.crosses, 1.0 / (1.0 + e.slope * e.slope), 0.0)
    return jnp.where(e.crosses, y - jax.lax.stop_gradient(y), 0.0), share
