"""Visibility of a mesh at its own vertices, by rays (self-shadowing without the field's extrapolation).

A receiver on an occluder's own surface lies inside the occluder's sampling shell, where the shadow
field extrapolates the shell's visibility inward (k = R/d > 1). That model is made for receivers
outside the occluder and limits self-shadowing to about 10 % relative RMSE of irradiance on the
bunny's vertices under a constant sky, whatever the shell radius or band counts
(``experiments/self_shadow.py``, BENCHMARKS.md "Self-shadowing"). Casting each vertex's view of the
mesh directly removes that error at the price of a ray cast per vertex: V × K × F ray–triangle
tests (the bunny: 1901 vertices × 576 directions over each vertex's normal hemisphere × 3798
faces, about a second on two CPU cores), affordable once for a mesh whose shape does not change,
not per frame. A concrete mesh's rays are tested against only the faces above each vertex's
tangent plane within their sector of azimuth (0.15 s for the bunny; :mod:`._hemisphere`).
Projected as the vertex's shadowed transfer V·max(0, n·ω) from origins lifted as the reference's
are (``transfer``, ``offset``: what ``self_visibility = "rays"`` casts), the bunny's vertices under
the sky come to 0.34 % (9.68 % with the field; 1.26 % with V's SH from the vertex itself;
BENCHMARKS.md "The default against the paper").
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int

from ..geometry import vertex_normals
from ..sh import hemisphere_grid, project, rotate, sphere_grid
from ._hemisphere import hemisphere_fan_any_hit
from ._raycast import _onb, ray_fan_any_hit

__all__ = ["vertex_transfer_and_lamps", "vertex_visibility_sh"]


def vertex_visibility_sh(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    n: int,
    grid: tuple[int, int] = (12, 48),
    hemisphere: bool = True,
    offset: float | Float[ArrayLike, ""] | None = None,
    transfer: bool = False,
) -> Float[Array, "V n2"]:
    """n-band SH (world frame) of the visibility of the mesh from each of its own vertices, or of
    its shadowed diffuse transfer.

    ``V_v(ω) = 1`` if the ray ``x_v + t·ω`` (t > 0) hits no face of the mesh, else 0, projected to
    n bands with a Gauss–Legendre (in cos θ) × uniform (in φ) rule of ``grid`` = (θ nodes, φ cells).
    The faces around a vertex are seen edge-on from it and never hit (:func:`ray_fan_any_hit`), so
    the surface does not shadow itself at the origin.

    With ``hemisphere`` (default) the rays cover the hemisphere about each vertex's area-weighted
    normal (:func:`jshadow.geometry.vertex_normals`; :func:`jshadow.sh.hemisphere_grid` in the
    vertex's frame, projected there and rotated to world) and V = 0 below it, where the surface
    itself lies: half the rays of the whole sphere at the same density. For a convex mesh this is
    exact, since every direction above the normal's plane leaves the mesh. For the bunny (1901
    vertices) at 12 × 48 the cast took 1.1–1.3 s against 2.0–3.0 s for the whole sphere at 24 × 48
    (``hemisphere=False``: rays in every direction, those into the mesh hitting its far side) in
    one run of ``experiments/self_shadow.py``, and it is no less accurate: 1.26 against 1.31 %
    relative RMSE on the vertices under a sky (BENCHMARKS.md "Self-shadowing").

    This is the self-shadowing term of Zhou et al. 2005 computed exactly where the deformable-shadow-
    fields paper extrapolates its shell (Sec. 4.2) — a replacement for the field's rows at an
    occluder's own vertices (``[method] self_visibility = "rays"``, :func:`jshadow.scene.render`).

    ``offset`` (the scene's :func:`jshadow.entities.surface_offset` ε): each vertex's rays start
    ε along its normal and ignore hits closer than ε, the reference renderer's convention for a
    receiver on a surface (without it the rays start at the vertex and its own faces are ignored,
    so a crease whose faces rise above the normal's plane does not shadow the vertex, where the
    reference counts them: 16.7 against 2.1 % largest error on the bunny's vertices under a sky).

    ``transfer``: project ``V(ω)·max(0, n·ω)`` instead of V — the vertex's shadowed diffuse
    transfer (Sloan et al. 2002, "Precomputed radiance transfer", Sec. 5), whose inner product
    with n-band radiance is the vertex's irradiance without the truncation of V and of the
    clamped cosine that their SH product carries (:func:`jshadow.scene.combine` takes it in place
    of the clamped cosine at an own vertex, ``self_visibility = "rays"``).

    Cost: V·K·F ray–triangle tests with K = θ·φ directions, memory bounded as in
    :func:`ray_fan_any_hit`. With ``hemisphere`` and concrete inputs (not traced), each vertex's
    fan is cut into groups by azimuth about its normal, and each group is tested against only the
    faces that reach above the vertex's tangent plane and into the group's azimuths, the only ones
    its rays can meet (:func:`jshadow.visibility.hemisphere_fan_any_hit`; the same coefficients):
    the bunny's cast at 12 × 48 took 0.15 s against 1.04 s, the spot cow's 0.29 against 2.25 s
    (``benchmarks/bench_own_rays.py``). Under a trace every face is tested.

    Limitations: binary visibility has no useful derivative with respect to the vertices (autodiff
    gives zero; :mod:`jshadow.scene` refuses to differentiate it).

    Args:
        vertices: (V, 3) mesh vertices, world units; faces: (F, 3) integer indices.
        n: SH bands of the result (n² coefficients).
        grid: (θ nodes, φ cells) of the direction grid, each ≥ 2: over the hemisphere with
            ``hemisphere``, else over the whole sphere.
        hemisphere: cast over each vertex's normal hemisphere only (see above).
        offset: None, or ε ≥ 0 in world units (may be traced): lift the origins (see above).
        transfer: the transfer V·max(0, n·ω) instead of V (see above).

    Returns:
        (V, n²) coefficients, dtype of ``vertices``.
    """
    grid = tuple(int(x) for x in grid)
    vertices = jnp.asarray(vertices)
    traced = any(isinstance(x, jax.core.Tracer) for x in (vertices, faces, offset))
    if not hemisphere or traced:
        return _vertex_visibility_sh(vertices, faces, n, grid, hemisphere, offset, transfer)
    # a concrete mesh: each vertex's fan lies above its normal's plane, so its rays are tested
    # against only the faces that reach above that plane and into their azimuths (the same hits)
    origins, normals, dirs, frame = _hemisphere_fans(vertices, faces, grid, offset)
    hit = hemisphere_fan_any_hit(origins, dirs, vertices, faces, normals, t_min=offset)
    return _hemisphere_sh(hit, frame, n, grid, transfer)


def vertex_transfer_and_lamps(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    n: int,
    grid: tuple[int, int],
    offset: float | Float[ArrayLike, ""],
    directions: Float[ArrayLike, "K 3"],
) -> tuple[Float[Array, "V n2"], Float[Array, "V K"]]:
    """:func:`vertex_visibility_sh`'s shadowed transfer (``transfer=True``, hemisphere ``grid``,
    origins lifted by ``offset``) and each vertex's visibility, 1 or 0, toward K distant
    ``directions`` (0 on or below its tangent plane), from one cast: each vertex's fan holds its
    grid and its lamps, so :func:`jshadow.visibility.hemisphere_fan_any_hit` makes the faces'
    lists once for both. The same values as the two casts apart (the lamps' fan is the one
    ``jshadow.scene`` casts for ``self_visibility = "rays"``: the same origins, ``t_min`` =
    ``offset``); the bunny's 12 × 48 grid and 256 lamps took 232 against 264 ms apart, the spot
    cow's 538 against 614 ms (``benchmarks/bench_own_rays.py``): the lists are made once, but a fan
    of 832 directions is cut into groups of 104 that each span more sectors. Concrete inputs only.

    Returns:
        (V, n²) transfer coefficients and (V, K) visibility, dtype of ``vertices``.
    """
    grid = tuple(int(x) for x in grid)
    vertices = jnp.asarray(vertices)
    directions = jnp.asarray(directions, vertices.dtype)
    if any(isinstance(x, jax.core.Tracer) for x in (vertices, faces, offset, directions)):
        raise ValueError("vertex_transfer_and_lamps needs concrete inputs")
    origins, normals, dirs, frame = _hemisphere_fans(vertices, faces, grid, offset)
    up, lamps = lamp_fans(normals, directions)
    k = dirs.shape[1]
    hit = hemisphere_fan_any_hit(
        origins, jnp.concatenate([dirs, lamps], 1), vertices, faces, normals, t_min=offset
    )
    transfer = _hemisphere_sh(hit[:, :k], frame, n, grid, True)
    return transfer, (up & ~hit[:, k:]).astype(vertices.dtype)


def lamp_fans(normals, directions) -> tuple[Array, Array]:
    """(V, K) whether each of K distant ``directions`` lies above each vertex's tangent plane, and
    the (V, K, 3) fans of them with those on or below it made zero (they never hit, and
    :func:`jshadow.visibility.hemisphere_fan_any_hit` lists them no faces): the own vertices' lamp
    rays, alone (``jshadow.scene._lamp_rays``) or beside the transfer's grid
    (:func:`vertex_transfer_and_lamps`)."""
    up = normals @ directions.T > 0
    return up, jnp.where(up[..., None], directions[None], 0.0)


@jax.jit
def lifted_origins(vertices, faces, offset):
    """(V, 3) origins of the own-vertex rays, each vertex lifted by ``offset`` along its
    area-weighted normal (not lifted for None), and the (V, 3) normals. One compiled function of
    its own, so every cast from the same vertices starts from the same origins to the bit: the
    transfer's fans, the lamps' rays (``jshadow.scene._lamp_rays``) and both at once
    (:func:`vertex_transfer_and_lamps`)."""
    normals = vertex_normals(vertices, jnp.asarray(faces))
    origins = vertices if offset is None else vertices + jnp.asarray(offset, vertices.dtype) * normals
    return origins, normals


@partial(jax.jit, static_argnames=("grid",))
def _grid_fans(normals, grid):
    local, _ = hemisphere_grid(*grid, normals.dtype)  # z >= 0
    e1, e2 = _onb(normals)
    frame = jnp.stack([e1, e2, normals], -1)  # (V, 3, 3): local -> world
    return jnp.einsum("vij,kj->vki", frame, local), frame


def _hemisphere_fans(vertices, faces, grid, offset):
    """Origins (V, 3), normals (V, 3), hemisphere directions (V, K, 3) and local → world frames
    (V, 3, 3) of :func:`vertex_visibility_sh`'s fans (:func:`lifted_origins`)."""
    origins, normals = lifted_origins(vertices, faces, offset)
    return (origins, normals, *_grid_fans(normals, grid))


@partial(jax.jit, static_argnames=("n", "grid", "transfer"))
def _hemisphere_sh(hit, frame, n, grid, transfer):
    local, w = hemisphere_grid(*grid, frame.dtype)
    vis = (~hit).astype(frame.dtype)
    if transfer:
        vis = vis * local[:, 2]
    return rotate(project(vis, local, w, n), frame)


@partial(jax.jit, static_argnames=("n", "grid", "hemisphere", "transfer"))
def _vertex_visibility_sh(vertices, faces, n, grid, hemisphere, offset, transfer):
    if not hemisphere:
        normals = vertex_normals(vertices, jnp.asarray(faces))
        origins = vertices if offset is None else vertices + jnp.asarray(offset, vertices.dtype) * normals
        dirs, w = sphere_grid(*grid, vertices.dtype)
        hit = ray_fan_any_hit(origins, dirs, vertices, faces, t_min=offset)
        vis = (~hit).astype(vertices.dtype)
        if transfer:
            vis = vis * jnp.maximum(normals @ dirs.T, 0.0)
        return project(vis, dirs, w, n)
    origins, _, dirs, frame = _hemisphere_fans(vertices, faces, grid, offset)
    hit = ray_fan_any_hit(origins, dirs, vertices, faces, t_min=offset)
    return _hemisphere_sh(hit, frame, n, grid, transfer)
