"""Base sphere visibility (BSV): the visibility of an occluder sampled on a shell around it.

Deformable-shadow-fields paper, Sec. 4.1 (after Zhou et al. 2005, "Precomputed shadow fields"):
each frame in which an occluder deforms, its visibility is sampled at T×P points ``p_ij`` on a shell
of radius ``R = shell · r`` around its bounding sphere (centre c, radius r; AABB centre, radius to
the farthest vertex) and projected onto n bands of real SH in the local frame of each point (see
:mod:`jshadow.visibility._frames` for the parametrisation and frames, polar axis world +z).

``coeffs[i, j]`` are the SH coefficients of the visibility ``V(ω)`` (1 = free, 0 = blocked) seen
from ``p_ij`` over the whole sphere of directions, in local coordinates. Only the local hemisphere
facing the centre (local z > 0) is cast; the other one is always visible and is added exactly:
with the Gauss–Legendre hemisphere quadrature of :mod:`._directions` the unoccluded hemisphere
projects exactly, so ``coeffs = √(4π)·e0 − Σ_k w_k occ_k Y(ω_k)``.

Rays leave ``p_ij`` and count as occluded if they hit any triangle at t > 0. The result is binary
visibility sampled on a grid: it has no useful derivative with respect to the vertices (see
notes/visibility-gradients.md for the boundary term that supplies one).
"""

from __future__ import annotations

import functools
import math
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._numerics import eps
from ..geometry import bounding_sphere
from ..sh import sh_basis
from ._directions import cap_sh_projection, hemisphere_directions
from ._frames import bsv_frames, bsv_grid_angles
from ._raycast import DEFAULT_FAN_FACE_CHUNK, DEFAULT_FAN_ORIGIN_CHUNK, ray_fan_any_hit, ray_sphere_any_hit

__all__ = [
    "BSV",
    "bsv_sample_points",
    "bsv_mesh",
    "bsv_sphere",
    "bsv_sphere_traced",
    "bsv_unit_vertices",
    "bsv_update",
    "BSVCache",
    "is_closed_manifold",
]


class BSV(eqx.Module):
    """Base sphere visibility of one occluder.

    Attributes:
        coeffs: (T, P, n²) SH coefficients of the visibility seen from the shell point (θ_i, φ_j),
            in that point's local frame (:func:`jshadow.visibility.bsv_frames`).
        center: (3,) bounding-sphere centre c (world units).
        radius: () bounding-sphere radius r.
        shell_radius: () radius R = shell · r of the sampling shell (R ≥ r; R = r in the paper).
    """

    coeffs: Float[Array, "T P n2"]
    center: Float[Array, "3"]
    radius: Float[Array, ""]
    shell_radius: Float[Array, ""]


def _check_grid(grid, name="grid"):
    if not (
        isinstance(grid, tuple | list)
        and len(grid) == 2
        and all(isinstance(g, int | np.integer) and g >= 1 for g in grid)
    ):
        raise ValueError(f"{name} must be two positive ints, got {grid!r}")
    return int(grid[0]), int(grid[1])


def _check_shell(shell):
    if isinstance(shell, int | float | np.floating) and not shell >= 1.0:
        raise ValueError(f"shell must be >= 1 (a multiple of the bounding radius), got {shell}")
    return float(shell)


def _check_bands(n):
    if not (isinstance(n, int | np.integer) and n >= 1):
        raise ValueError(f"n (number of SH bands) must be a positive int, got {n!r}")
    return int(n)


def bsv_sample_points(
    center: Float[ArrayLike, "3"],
    radius: float | Float[ArrayLike, ""],
    grid: tuple[int, int] = (12, 20),
    shell: float = 1.0,
) -> tuple[Float[Array, "T P 3"], Float[Array, "T P 3 3"]]:
    """Shell points ``p_ij = c + shell·r·u(θ_i, φ_j)`` (T, P, 3) and their local frames (T, P, 3, 3)."""
    t, p = _check_grid(grid)
    shell = _check_shell(shell)
    center = jnp.asarray(center)
    if center.shape != (3,):
        raise ValueError(f"center must have shape (3,), got {center.shape}")
    dtype = jnp.result_type(center, jnp.asarray(radius))
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.result_type(float)
    theta, phi = bsv_grid_angles(t, p, dtype)
    u, frames = bsv_frames(theta[:, None], phi[None, :])
    points = center.astype(dtype) + (shell * jnp.asarray(radius, dtype)) * u
    return points, frames


def _world_dirs(frames, local):
    """frames (G, 3, 3) @ local (K, 3) -> (G, K, 3), as explicit multiply-adds."""
    return (
        frames[:, None, :, 0] * local[None, :, 0, None]
        + frames[:, None, :, 1] * local[None, :, 1, None]
        + frames[:, None, :, 2] * local[None, :, 2, None]
    )


def _project(occ, local, weights, n, grid):
    """coeffs (T, P, n²) = √(4π)·e0 − occ (G, K) @ (w·Y) (K, n²)."""
    dtype = local.dtype
    basis_w = sh_basis(local, n) * weights[:, None]
    full = jnp.zeros(n * n, dtype).at[0].set(math.sqrt(4.0 * math.pi))
    coeffs = full - occ.astype(dtype) @ basis_w
    return coeffs.reshape(*grid, n * n)


@partial(jax.jit, static_argnames=("n", "grid", "directions", "shell", "face_chunk", "origin_chunk"))
def _bsv_brute(vertices, faces, *, n, grid, directions, shell, face_chunk, origin_chunk):
    dtype = vertices.dtype
    center, radius = bounding_sphere(vertices)
    points, frames = bsv_sample_points(center, radius, grid, shell)
    local, weights = hemisphere_directions(*directions, dtype=dtype)
    world = _world_dirs(frames.reshape(-1, 3, 3), local)
    occ = ray_fan_any_hit(
        points.reshape(-1, 3), world, vertices, faces, face_chunk=face_chunk, origin_chunk=origin_chunk
    )
    coeffs = _project(occ, local, weights, n, grid)
    return BSV(coeffs, center, radius, shell * radius)


def is_closed_manifold(faces: Int[ArrayLike, "F 3"]) -> bool:
    """Whether a (concrete) face array is a closed, edge-manifold, consistently oriented surface.

    True iff no face repeats a vertex, every directed edge a→b occurs exactly once and its reverse
    b→a occurs too (so each undirected edge has exactly two faces, oppositely oriented). Traced
    (abstract) faces cannot be checked and give False.
    """
    try:
        f = np.asarray(faces)
    except jax.errors.TracerArrayConversionError:
        return False
    if f.ndim != 2 or f.shape[-1] != 3 or f.shape[0] == 0:
        return False
    return _closed_manifold_cached(f.astype(np.int64).tobytes(), f.shape[0])


@functools.lru_cache(maxsize=64)
def _closed_manifold_cached(buf: bytes, num_faces: int) -> bool:
    # cached per topology: the check is O(F log F) numpy work, run on every frame otherwise
    f = np.frombuffer(buf, np.int64).reshape(num_faces, 3)
    if np.any((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])):
        return False
    a = f.reshape(-1)
    b = np.roll(f, -1, axis=1).reshape(-1)
    base = int(f.max()) + 1
    codes = a * base + b
    if np.unique(codes).size != codes.size:
        return False
    return bool(np.all(np.isin(b * base + a, codes)))


def bsv_mesh(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    n: int = 4,
    grid: tuple[int, int] = (12, 20),
    directions: tuple[int, int] = (32, 32),
    shell: float = 1.0,
    method: str = "auto",
    *,
    face_chunk: int = DEFAULT_FAN_FACE_CHUNK,
    origin_chunk: int = DEFAULT_FAN_ORIGIN_CHUNK,
) -> BSV:
    """BSV of a triangle mesh: (T, P, n²) local SH visibility on the shell R = shell · r.

    Args:
        vertices: (V, 3) float, world units; faces: (F, 3) int.
        n: SH bands (n² coefficients). grid: (T, P) shell points. directions: (n_theta, n_phi)
            hemisphere directions per point (Gauss–Legendre in cos θ × uniform φ; brute force only).
        shell: R / r ≥ 1 (1 = the paper's setting: samples on the bounding sphere).
        method: "brute" casts ``T·P·n_theta·n_phi`` rays with :func:`ray_fan_any_hit` (any mesh,
            any shell); "edgescan" uses ``jshadow.visibility.bsv_mesh_edgescan`` (closed manifold
            meshes, shell > 1; its ``directions`` are a gnomonic cone image); "auto" takes edgescan
            when shell > 1 and the faces are concrete and closed-manifold, and brute otherwise.
            Under ``jax.jit`` it casts rays (the faces become a tracer when converted inside the
            trace, and a traced edge-scan needs static slot sizes measured on a concrete pose): call
            ``bsv_mesh_edgescan(..., slots=edgescan_slots(rest_pose, ...))`` for the edge-scan there.
        face_chunk, origin_chunk: chunk sizes of the brute-force ray caster.

    Binary visibility: the result has no useful gradient with respect to the vertices.
    """
    n = _check_bands(n)
    grid = _check_grid(grid)
    directions = _check_grid(directions, "directions")
    shell = _check_shell(shell)
    if method not in ("auto", "brute", "edgescan"):
        raise ValueError(f"method must be 'auto', 'brute' or 'edgescan', got {method!r}")
    vertices = jnp.asarray(vertices)
    faces = jnp.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[-1] != 3 or vertices.shape[0] == 0:
        raise ValueError(f"vertices must have shape (V, 3) with V >= 1, got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[-1] != 3 or not jnp.issubdtype(faces.dtype, jnp.integer):
        raise ValueError(f"faces must be an int array of shape (F, 3), got {faces.dtype} {faces.shape}")
    if not jnp.issubdtype(vertices.dtype, jnp.floating):
        vertices = vertices.astype(jnp.result_type(float))
    if method == "auto" and shell > 1.0 and is_closed_manifold(faces):
        try:
            from ._edgescan import bsv_mesh_edgescan
        except ImportError:
            method = "brute"
        else:
            return bsv_mesh_edgescan(vertices, faces, n=n, grid=grid, directions=directions, shell=shell)
    if method == "edgescan":
        from ._edgescan import bsv_mesh_edgescan

        return bsv_mesh_edgescan(vertices, faces, n=n, grid=grid, directions=directions, shell=shell)
    return _bsv_brute(
        vertices,
        faces.astype(jnp.int32),
        n=n,
        grid=grid,
        directions=directions,
        shell=shell,
        face_chunk=face_chunk,
        origin_chunk=origin_chunk,
    )


def _sphere_inputs(center, radius):
    center = jnp.asarray(center)
    radius = jnp.asarray(radius)
    if center.shape != (3,) or radius.shape != ():
        raise ValueError(f"center must be (3,) and radius a scalar, got {center.shape} and {radius.shape}")
    dtype = jnp.result_type(center, radius)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.result_type(float)
    return center.astype(dtype), radius.astype(dtype)


def bsv_sphere(
    center: Float[ArrayLike, "3"],
    radius: float | Float[ArrayLike, ""],
    n: int = 4,
    grid: tuple[int, int] = (12, 20),
    shell: float = 1.0,
) -> BSV:
    """Analytic BSV of a sphere occluder (the sphere is its own bounding sphere).

    From a point at distance R = shell · r the sphere covers the cap of half-angle ``asin(r/R)``
    around local +z (toward the centre), the same at every shell point, so
    ``coeffs = √(4π)·e0 − cap(cos α = √(1 − 1/shell²))``; at R = r the cap is the whole local
    hemisphere. Differentiable in centre and radius (the coefficients themselves do not depend on
    them, only on ``shell``).
    """
    n = _check_bands(n)
    t, p = _check_grid(grid)
    shell = _check_shell(shell)
    center, radius = _sphere_inputs(center, radius)
    cos_a = jnp.asarray(math.sqrt(max(1.0 - 1.0 / (shell * shell), 0.0)), center.dtype)
    full = jnp.zeros(n * n, center.dtype).at[0].set(math.sqrt(4.0 * math.pi))
    coeffs = jnp.broadcast_to(full - cap_sh_projection(cos_a, n), (t, p, n * n))
    return BSV(coeffs, center, radius, shell * radius)


@partial(jax.jit, static_argnames=("n", "grid", "directions", "shell"))
def _bsv_sphere_traced(center, radius, *, n, grid, directions, shell):
    points, frames = bsv_sample_points(center, radius, grid, shell)
    local, weights = hemisphere_directions(*directions, dtype=center.dtype)
    world = _world_dirs(frames.reshape(-1, 3, 3), local)
    occ = ray_sphere_any_hit(points.reshape(-1, 1, 3), world, center, radius)
    return BSV(_project(occ, local, weights, n, grid), center, radius, shell * radius)


def bsv_sphere_traced(
    center: Float[ArrayLike, "3"],
    radius: float | Float[ArrayLike, ""],
    n: int = 4,
    grid: tuple[int, int] = (12, 20),
    directions: tuple[int, int] = (32, 32),
    shell: float = 1.0,
) -> BSV:
    """BSV of a sphere occluder through the ray caster (:func:`ray_sphere_any_hit`), for checking
    :func:`bsv_sphere` and the quadrature: same layout, quadrature error O(1/n_theta)."""
    n = _check_bands(n)
    grid = _check_grid(grid)
    directions = _check_grid(directions, "directions")
    shell = _check_shell(shell)
    center, radius = _sphere_inputs(center, radius)
    return _bsv_sphere_traced(center, radius, n=n, grid=grid, directions=directions, shell=shell)


# --------------------------------------------------------------------------------------------
# Reuse across frames
# --------------------------------------------------------------------------------------------


def bsv_unit_vertices(vertices: Float[ArrayLike, "V 3"]) -> Float[Array, "V 3"]:
    """Vertices mapped so their bounding sphere is the unit sphere: ``(x − c) / r``.

    Two poses with equal unit vertices differ by a translation and a uniform scale only, and have
    identical BSV coefficients (the shell points, frames and rays move with the similarity; the
    frames are fixed in world, so a rotation is *not* such a change).
    """
    v = jnp.asarray(vertices)
    center, radius = bounding_sphere(v)
    return (v - center) / jnp.where(radius > 0, radius, 1.0)


def _same_shape(prev_unit, vertices) -> bool:
    return tuple(jnp.shape(prev_unit)) == tuple(jnp.shape(vertices))


def bsv_update(
    prev_bsv: BSV,
    prev_unit_vertices: Float[ArrayLike, "V 3"],
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    n: int = 4,
    grid: tuple[int, int] = (12, 20),
    directions: tuple[int, int] = (32, 32),
    shell: float = 1.0,
    method: str = "auto",
    atol: float | None = None,
) -> tuple[BSV, Float[Array, "V 3"], Bool[Array, ""]]:
    """The BSV of ``vertices``, reusing ``prev_bsv`` when only a translation / uniform scale changed.

    ``prev_bsv`` must have been computed with the same faces and options from vertices whose
    :func:`bsv_unit_vertices` are ``prev_unit_vertices``. If the new unit vertices match them
    within ``atol`` (default ``eps(dtype, 100)``, about 1e-4 of the bounding radius in float32),
    the coefficients are reused with the new centre and radii; otherwise the BSV is recomputed with
    :func:`bsv_mesh`. Returns ``(bsv, unit_vertices, recomputed)``; the unit vertices are the ones
    the returned BSV belongs to. With concrete inputs the skip is a Python branch; under ``jit`` it
    is a ``lax.cond`` (only the taken branch runs).
    """
    vertices = jnp.asarray(vertices)
    prev_unit = jnp.asarray(prev_unit_vertices)
    unit = bsv_unit_vertices(vertices)
    center, radius = bounding_sphere(vertices)
    tol = eps(vertices.dtype, 100.0) if atol is None else float(atol)
    kw = dict(n=n, grid=grid, directions=directions, shell=shell, method=method)
    if not _same_shape(prev_unit, vertices) or prev_bsv.coeffs.shape[:2] != tuple(grid):
        return bsv_mesh(vertices, faces, **kw), unit, jnp.asarray(True)
    same = jnp.max(jnp.abs(unit - prev_unit.astype(unit.dtype))) <= tol

    def reuse():
        return BSV(prev_bsv.coeffs, center, radius, shell * radius), prev_unit.astype(unit.dtype)

    def recompute():
        return bsv_mesh(vertices, faces, **kw), unit

    try:
        take = bool(same)
    except jax.errors.ConcretizationTypeError:
        bsv, u = lax.cond(same, reuse, recompute)
        return bsv, u, ~same
    bsv, u = reuse() if take else recompute()
    return bsv, u, jnp.asarray(not take)


class BSVCache:
    """Stateful per-occluder BSV cache for frame loops (concrete inputs, outside ``jit``).

    ``cache(vertices, faces)`` returns the BSV, recomputing it only when the pose changed by more
    than a translation and uniform scale (see :func:`bsv_update`) or the faces changed.
    ``computations`` and ``hits`` count the two outcomes.
    """

    def __init__(
        self,
        n: int = 4,
        grid: tuple[int, int] = (12, 20),
        directions: tuple[int, int] = (32, 32),
        shell: float = 1.0,
        method: str = "auto",
        atol: float | None = None,
    ):
        self.options = dict(n=n, grid=tuple(grid), directions=tuple(directions), shell=shell, method=method)
        self.atol = atol
        self.computations = 0
        self.hits = 0
        self._bsv = None
        self._unit = None
        self._faces = None

    def __call__(self, vertices: Float[ArrayLike, "V 3"], faces: Int[ArrayLike, "F 3"]) -> BSV:
        faces_np = np.asarray(faces)
        if self._bsv is None or self._faces is None or not np.array_equal(self._faces, faces_np):
            self._bsv = bsv_mesh(vertices, faces, **self.options)
            self._unit = bsv_unit_vertices(vertices)
            self._faces = faces_np.copy()
            self.computations += 1
            return self._bsv
        bsv, unit, recomputed = bsv_update(
            self._bsv, self._unit, vertices, faces, atol=self.atol, **self.options
        )
        self._bsv, self._unit = bsv, unit
        if bool(recomputed):
            self.computations += 1
        else:
            self.hits += 1
        return bsv
