"""Visibility of a mesh at its own vertices, by rays (self-shadowing without the field's extrapolation).

A receiver on an occluder's own surface lies inside the occluder's sampling shell, where the shadow
field extrapolates the shell's visibility inward (k = R/d > 1). That model is made for receivers
outside the occluder and limits self-shadowing to about 10 % relative RMSE of irradiance on the
bunny's vertices under a constant sky, whatever the shell radius or band counts
(``experiments/self_shadow.py``, BENCHMARKS.md "Self-shadowing"). Casting each vertex's visibility
of the mesh directly removes that error (9.7 → 1.3 % there) at the price of a ray cast per vertex:
V × K × F ray–triangle tests (the bunny: 1901 vertices × 1152 directions × 3798 faces, seconds on
two CPU cores), affordable once for a mesh whose shape does not change, not per frame.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int

from ..sh import project, sphere_grid
from ._raycast import ray_fan_any_hit

__all__ = ["vertex_visibility_sh"]


@partial(jax.jit, static_argnames=("n", "grid"))
def vertex_visibility_sh(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    n: int,
    grid: tuple[int, int] = (24, 48),
) -> Float[Array, "V n2"]:
    """n-band SH (world frame) of the visibility of the mesh from each of its own vertices.

    ``V_v(ω) = 1`` if the ray ``x_v + t·ω`` (t > 0) hits no face of the mesh, else 0, projected to
    n bands with the Gauss–Legendre × uniform rule of ``grid`` = (θ nodes, φ cells) over the whole
    sphere (:func:`jshadow.sh.sphere_grid`; exact for band-limited functions up to degree
    ``2·θ − n`` in z, so the projection error is that of the binary function's quadrature). The
    faces around a vertex are seen edge-on from it and never hit (:func:`ray_fan_any_hit`), so the
    surface does not shadow itself at the origin; rays into the mesh hit its far side.

    This is the self-shadowing term of Zhou et al. 2005 computed exactly where the deformable-shadow-
    fields paper extrapolates its shell (Sec. 4.2) — a replacement for the field's rows at an
    occluder's own vertices (``[method] self_visibility = "rays"``, :func:`jshadow.scene.render`).

    Limitations: binary visibility has no useful derivative with respect to the vertices (autodiff
    gives zero; :mod:`jshadow.scene` refuses to differentiate it). Cost V·K·F ray–triangle tests
    with K = θ·φ directions; memory bounded as in :func:`ray_fan_any_hit`.

    Args:
        vertices: (V, 3) mesh vertices, world units; faces: (F, 3) integer indices.
        n: SH bands of the result (n² coefficients).
        grid: (θ nodes, φ cells) of the direction grid, each ≥ 2.

    Returns:
        (V, n²) coefficients, dtype of ``vertices``.
    """
    vertices = jnp.asarray(vertices)
    dirs, w = sphere_grid(*grid, vertices.dtype)
    hit = ray_fan_any_hit(vertices, dirs, vertices, faces)
    return project((~hit).astype(vertices.dtype), dirs, w, n)
