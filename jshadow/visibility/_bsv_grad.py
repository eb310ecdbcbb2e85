"""Vertex gradients of the base sphere visibility (BSV) through its silhouette boundary term.

Autodiff through binary visibility returns zero. The derivative of the local SH coefficients
``S_i = ∫ V(ω) Y_i(ω) dω`` seen from a point p is instead a line integral along the visible parts
of the silhouette edges (Reynolds transport on the sphere; see :mod:`jshadow.visibility._silhouette`
and ``notes/visibility-gradients.md`` §2). With V = 1 − O and the occluded region Ω bounded by the
silhouette edges a→b (oriented as in their front-facing face), ``m = (a − p) × (b − p)``:

    dS_i = − Σ_edges Σ_nodes q Y_i(Fᵀω) m·(δx − δp),     δx = (1 − s) δa + s δb,

where the node weight ``q = w_ψ χ / (r |m|)`` comes from Gauss–Legendre nodes in the angle ψ at p
and F is the (fixed) local frame of the viewpoint. The rule is linear in (δX, δp), so JAX transposes
it for reverse mode: a cotangent is contracted with the per-slot SH weights first and then scattered
onto the two vertices of each slot; no (n², V, 3) array is formed.

:func:`bsv_mesh_diff` wraps a BSV forward pass (deformable-shadow-fields paper Sec. 4.1; Zhou et al.
2005 "Precomputed shadow fields" Sec. 4) in a ``jax.custom_jvp`` whose tangent is this boundary
term, including the motion of the sample points ``p = c(X) + R(X)·u`` (AABB centre c and radius to
the farthest vertex, so only the extreme vertices see that part; the local frames depend on u only
and stay fixed while p moves).

Accuracy (biased where noted): the tangent is the derivative of the *exact* integral ∫ V Y dω, not of
the 32×32 sampled forward pass, which is a noisy quadrature of it. Edges whose visibility changes
along their length are integrated to first order only: about 4 % of ‖dS/dX‖ at 8 nodes per edge on
the bunny, 1 % at 32 (notes §5); convex meshes are exact to quadrature precision. Silhouette edges
beyond ``slots`` are dropped by :func:`bsv_sh_tangent` (which returns the count; :func:`bsv_mesh_diff`
raises instead). S has kinks
where p crosses the plane of a face next to a visible silhouette edge; there the one-sided
derivative of the current facing configuration is returned.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike, Float, Int

from ..geometry import bounding_sphere
from ..sh import sh_basis
from ._bsv import bsv_mesh, bsv_sample_points
from ._silhouette import EdgeTable, SilhouetteSamples, silhouette_edges_table, silhouette_samples

__all__ = ["bsv_sh_tangent", "bsv_mesh_diff", "bsv_silhouette_counts", "default_slots"]


def default_slots(num_edges: int) -> int:
    """Slot count K used when none is given: every edge (never overflows, slowest).

    Silhouettes of closed meshes hold about 0.14·E edges (notes §6); for speed pass
    ``slots ≈ 1.25 × max(bsv_silhouette_counts(...))``.
    """
    return int(max(1, num_edges))


def _check_static(n, slots, nodes):
    if not (isinstance(n, int | np.integer) and n >= 1):
        raise ValueError(f"n (number of SH bands) must be a positive int, got {n!r}")
    if not (isinstance(slots, int | np.integer) and slots >= 1):
        raise ValueError(f"slots (silhouette slots per viewpoint) must be a positive int, got {slots!r}")
    if not (isinstance(nodes, int | np.integer) and nodes >= 1):
        raise ValueError(f"nodes (Gauss–Legendre nodes per edge) must be a positive int, got {nodes!r}")


def _samples_all(vertices, faces, table, points, slots, nodes) -> SilhouetteSamples:
    """Silhouette samples of every viewpoint (P, ...), one viewpoint at a time to bound memory."""
    return lax.map(lambda p: silhouette_samples(vertices, faces, table, p, slots, nodes), points)


def _slot_weights(samples: SilhouetteSamples, frames, n):
    """Per-slot SH weights of the *visibility* tangent: (P, K, n²) for δa and for δb.

    ``wa_i = −Σ_nodes q (1 − s) Y_i(Fᵀω)``, ``wb_i = −Σ_nodes q s Y_i(Fᵀω)`` (minus: V = 1 − O).
    """
    local = jnp.einsum("pknw,pwv->pknv", samples.omega, frames)  # ω_loc = Fᵀ ω
    y = sh_basis(local, n)  # (P, K, nodes, n²)
    qa = samples.q * (1.0 - samples.s)
    qb = samples.q * samples.s
    wa = -jnp.einsum("pkn,pkni->pki", qa, y)
    wb = -jnp.einsum("pkn,pkni->pki", qb, y)
    return wa, wb


@partial(jax.jit, static_argnames=("slots", "nodes", "n"))
def _slot_terms(vertices, faces, table, points, frames, *, slots, nodes, n):
    """Primal-only part (jitted): slot vertex ids, m, the two SH weight arrays and the counts."""
    vertices, points, frames = (lax.stop_gradient(v) for v in (vertices, points, frames))
    samples = _samples_all(vertices, faces, table, points, slots, nodes)
    wa, wb = _slot_weights(samples, frames, n)
    return samples.a, samples.b, samples.m, wa, wb, samples.count


@jax.jit
def _apply_tangent(wa, wb, a, b, m, dvertices, dpoints):
    """Linear in (dvertices, dpoints): Σ_slots wa·(m·(δa − δp)) + wb·(m·(δb − δp))  -> (P, n²)."""
    da = dvertices[a] - dpoints[:, None, :]  # (P, K, 3)
    db = dvertices[b] - dpoints[:, None, :]
    ta = jnp.sum(m * da, axis=-1)
    tb = jnp.sum(m * db, axis=-1)
    return jnp.einsum("pki,pk->pi", wa, ta) + jnp.einsum("pki,pk->pi", wb, tb)


def _check_inputs(vertices, faces):
    vertices = jnp.asarray(vertices)
    if vertices.ndim != 2 or vertices.shape[-1] != 3 or vertices.shape[0] == 0:
        raise ValueError(f"vertices must have shape (V, 3) with V >= 1, got {vertices.shape}")
    if not jnp.issubdtype(vertices.dtype, jnp.floating):
        raise ValueError(f"vertices must be a float array, got {vertices.dtype}")
    if isinstance(faces, jax.core.Tracer):  # traced topology: only bsv_sh_tangent accepts it
        if faces.ndim != 2 or faces.shape[-1] != 3 or not jnp.issubdtype(faces.dtype, jnp.integer):
            raise ValueError(f"faces must be an int array of shape (F, 3), got {faces.dtype} {faces.shape}")
        return vertices, faces.astype(jnp.int32)
    faces = np.asarray(faces)  # concrete topology stays a numpy constant under jit
    if faces.ndim != 2 or faces.shape[-1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"faces must be an int array of shape (F, 3), got {faces.dtype} {faces.shape}")
    return vertices, faces.astype(np.int32)


def bsv_sh_tangent(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    edge_table: EdgeTable,
    points: Float[ArrayLike, "P 3"],
    frames: Float[ArrayLike, "P 3 3"],
    n: int,
    slots: int,
    nodes_per_edge: int,
    dvertices: Float[ArrayLike, "V 3"],
    dpoints: Float[ArrayLike, "P 3"],
) -> tuple[Float[Array, "P n2"], Int[Array, " P"]]:
    """Directional derivative of the local SH visibility coefficients at P viewpoints.

    Args:
        vertices: (V, 3) mesh positions X; faces: (F, 3) outward-wound triangles; edge_table: from
            :func:`jshadow.visibility.silhouette_edges_table` ``(faces)``.
        points: (P, 3) viewpoints p, outside the mesh. frames: (P, 3, 3) local frames
            (``world = frame @ local``); SH are evaluated at ``frameᵀ ω``. The frames are held fixed.
        n: SH bands. slots: K silhouette slots per viewpoint (static). nodes_per_edge: Gauss–Legendre
            nodes in the angle at p per edge (static).
        dvertices: (V, 3) vertex motion δX; dpoints: (P, 3) viewpoint motion δp.

    Returns:
        ``dS`` (P, n²): d/dt of ``S_i(p) = ∫ V(ω) Y_i(Fᵀω) dω`` (V = 1 free, 0 blocked) along
        (δX, δp); and ``count`` (P,) int32, the number of silhouette edges per viewpoint
        (``count > slots`` means edges were dropped and the tangent is incomplete).

    Sample terms (silhouette, nodes, visibility χ) are computed under ``stop_gradient``; the result
    is linear in (dvertices, dpoints) and JAX can transpose it. See the module docstring for the
    accuracy (first order in the nodes for partly visible edges) and the kinks of S.
    """
    vertices, faces = _check_inputs(vertices, faces)
    _check_static(n, slots, nodes_per_edge)
    points = jnp.asarray(points)
    frames = jnp.asarray(frames)
    n_p = points.shape[0] if points.ndim == 2 else -1
    if points.ndim != 2 or points.shape[-1] != 3:
        raise ValueError(f"points must have shape (P, 3), got {points.shape}")
    if frames.shape != (n_p, 3, 3):
        raise ValueError(f"frames must have shape ({n_p}, 3, 3) to match points, got {frames.shape}")
    dvertices = jnp.asarray(dvertices)
    dpoints = jnp.asarray(dpoints)
    if dvertices.shape != vertices.shape:
        raise ValueError(f"dvertices must have the shape of vertices {vertices.shape}, got {dvertices.shape}")
    if dpoints.shape != points.shape:
        raise ValueError(f"dpoints must have the shape of points {points.shape}, got {dpoints.shape}")
    a, b, m, wa, wb, count = _slot_terms(
        vertices, faces, edge_table, points, frames, slots=int(slots), nodes=int(nodes_per_edge), n=int(n)
    )
    return _apply_tangent(wa, wb, a, b, m, dvertices, dpoints), count


@partial(jax.jit, static_argnames=("grid", "shell"))
def _sample_points(vertices, grid, shell):
    center, radius = bounding_sphere(vertices)
    points, frames = bsv_sample_points(center, radius, grid, shell)
    return points.reshape(-1, 3), frames.reshape(-1, 3, 3)


def bsv_silhouette_counts(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    grid: tuple[int, int] = (12, 20),
    shell: float = 1.0,
) -> Int[Array, "T P"]:
    """Number of silhouette edges seen from each BSV sample point (T, P): choose ``slots`` from it."""
    vertices, faces = _check_inputs(vertices, faces)
    table = silhouette_edges_table(faces)
    points, _ = _sample_points(vertices, tuple(grid), float(shell))
    rel = vertices[faces][None] - points[:, None, None, :]  # (P, F, 3, 3)
    nrm = jnp.cross(rel[..., 1, :] - rel[..., 0, :], rel[..., 2, :] - rel[..., 0, :])
    front = jnp.sum(nrm * rel[..., 0, :], axis=-1) < 0
    f0, f1 = table.faces[:, 0], table.faces[:, 1]
    fr0 = front[:, f0]
    fr1 = jnp.where(f1 >= 0, front[:, jnp.maximum(f1, 0)], ~fr0)
    return jnp.sum(fr0 != fr1, axis=-1, dtype=jnp.int32).reshape(grid)


_SLOT_OVERFLOW = (
    "ray-cast gradient slots overflowed: a BSV sample point sees more silhouette edges than slots; "
    "pass a larger slots (see bsv_silhouette_counts)"
)


def bsv_mesh_diff(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    n: int = 4,
    grid: tuple[int, int] = (12, 20),
    directions: tuple[int, int] = (32, 32),
    shell: float = 1.0,
    *,
    forward: Callable[[Float[Array, "V 3"]], Float[Array, "T P n2"]] | None = None,
    slots: int | None = None,
    nodes: int = 8,
) -> Float[Array, "T P n2"]:
    """BSV coefficients (T, P, n²) of a mesh, differentiable with respect to its vertices.

    The primal output is ``forward(vertices)`` (default: the brute-force BSV,
    ``bsv_mesh(vertices, faces, n, grid, directions, shell, method="brute").coeffs``). Its derivative is
    the silhouette boundary term of the *exact* visibility integral (module docstring), so ``jax.jvp``,
    ``jax.grad`` and ``jax.vjp`` of losses of the coefficients return useful vertex gradients, with
    the motion of the sample points ``p = c(X) + shell·r(X)·u`` included.

    Args:
        vertices: (V, 3) float, world units (the differentiated input).
        faces: (F, 3) int, concrete (the topology is static), consistently outward-wound, no
            degenerate faces; open meshes are allowed.
        n, grid, directions, shell: as in :func:`jshadow.visibility.bsv_mesh`.
        forward: optional ``vertices -> (T, P, n²)`` primal; it is not differentiated.
        slots: silhouette slots per viewpoint (default: all edges, never overflows); choose it from
            :func:`bsv_silhouette_counts`. A viewpoint with more silhouette edges raises at run time
            when the derivative is evaluated (its edges would be missing from the gradient).
        nodes: Gauss–Legendre nodes per silhouette edge in the angle at p (8: about 4 % error on
            self-occluding meshes, exact on convex ones; the error falls like 1/nodes).

    Limitations: the gradient is biased for partly visible silhouette edges (first order in
    ``nodes``) and one-sided at visual events (p crossing a face plane). The 32×32 primal is a noisy
    quadrature of the integral whose derivative is returned.
    """
    vertices, faces = _check_inputs(vertices, faces)
    grid = tuple(int(g) for g in grid)
    directions = tuple(int(d) for d in directions)
    if len(grid) != 2 or len(directions) != 2:
        raise ValueError(f"grid and directions must be pairs (T, P), got {grid} and {directions}")
    if not float(shell) >= 1.0:
        raise ValueError(
            f"shell must be >= 1 (sample points on or outside the bounding sphere), got {shell!r}"
        )
    with jax.ensure_compile_time_eval():  # concrete even under a trace: the jvp rule closes over it
        table = silhouette_edges_table(faces)
    k = default_slots(table.num_edges) if slots is None else slots
    _check_static(n, k, nodes)
    n, k, nodes, shell = int(n), int(k), int(nodes), float(shell)
    if forward is None:

        def forward(x):
            return bsv_mesh(x, faces, n, grid, directions, shell, method="brute").coeffs

    @jax.custom_jvp
    def bsv(x):
        return forward(x)

    @bsv.defjvp
    def bsv_jvp(primals, tangents):
        (x,), (dx,) = primals, tangents
        out = lax.stop_gradient(forward(x))
        (points, frames), (dpoints, _) = jax.jvp(lambda v: _sample_points(v, grid, shell), (x,), (dx,))
        a, b, m, wa, wb, count = _slot_terms(x, faces, table, points, frames, slots=k, nodes=nodes, n=n)
        # on the tangent, not the primal: under jax.jit(jax.grad(...)) the primal is dead code
        ok = eqx.error_if(jnp.ones((), out.dtype), jnp.any(count > k), _SLOT_OVERFLOW)
        dout = _apply_tangent(wa, wb, a, b, m, dx, dpoints)
        return out, ok * dout.reshape(out.shape).astype(out.dtype)

    return bsv(vertices)
