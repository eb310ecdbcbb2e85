"""Visibility SH of a mesh from points it lies wholly above: the rays of the upper half only.

A receiver on a floor under a mesh (every vertex on or above the receiver's tangent plane) sees
nothing below that plane: a ray into the lower half-space cannot reach a mesh whose faces, convex
combinations of its vertices, all lie in the upper one. So of a sphere grid's rays only the upper
half need be cast, the lower half counting as free. Here the grid's pole is a tangent of the plane,
so the plane splits every ring of the Gauss–Legendre × uniform rule (:func:`jshadow.sh.sphere_grid`)
between its φ cells: the quadrature is the whole grid's, turned, at half the rays. (A hemisphere
rule about the normal, :func:`jshadow.sh.hemisphere_grid`, has its rings about the normal instead:
under a sphere the cap's edge is one of its rings, and its 12 × 48 rule missed the solid angle of
the cap of an icosphere 0.05 above the receiver, 0.1 of its radius, by 0.26 sr, where the whole
24 × 48 grid missed it by 0.085 sr and this one by 0.02 sr: ``tests/test_contact.py``'s scene.)

Used by :func:`jshadow.scene.contact_rows_at_time` for the receivers next to a mesh, where the
caller has checked that the mesh lies above them.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ..sh import rotate, sh_basis, sphere_grid
from ._raycast import _onb, ray_fan_any_hit

__all__ = ["halfspace_visibility_sh"]


def halfspace_visibility_sh(
    origins: Float[ArrayLike, "M 3"],
    normals: Float[ArrayLike, "M 3"],
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    n: int,
    grid: tuple[int, int],
) -> Float[Array, "M n2"]:
    """(M, n²) world-frame SH of the mesh's visibility ``V(ω)`` (1 where the ray from the origin
    along ω meets no face) from origins that the mesh lies wholly above, casting half the rays.

    The sphere ``grid`` (θ nodes, φ cells; φ cells even) is laid with its pole along a tangent
    ``e1`` of each origin's plane and its φ = π/2 meridian along the unit normal: local
    (x, y, z) = (e2, normal, e1) in world, so the cells with φ in (0, π) are exactly those above the
    plane. Those are cast (:func:`ray_fan_any_hit`), the others taken as V = 1, projected in the
    local frame and rotated to world (:func:`jshadow.sh.rotate`).

    Exact, that is equal to the whole grid's rays, only where every vertex of the mesh lies on or
    above each origin's tangent plane (not checked here: the caller's, e.g.
    ``jshadow.scene._contact_above``); elsewhere the faces below are missed.

    Args:
        origins: (M, 3) points, world units; normals: (M, 3) unit normals of their planes.
        vertices: (V, 3); faces: (F, 3) int.
        n: SH bands of the result.
        grid: (θ nodes ≥ 1, φ cells, even ≥ 2) of :func:`jshadow.sh.sphere_grid`.

    Returns:
        (M, n²) coefficients in the origins' dtype; no derivative (binary visibility).
    """
    n_theta, n_phi = (int(g) for g in grid)
    if n_phi < 2 or n_phi % 2:
        raise ValueError(f"halfspace_visibility_sh: the grid's φ cells must be even and >= 2, got {grid}")
    origins, normals = jnp.asarray(origins), jnp.asarray(normals)
    dtype = origins.dtype
    d, w = sphere_grid(n_theta, n_phi, dtype)
    basis = sh_basis(d, n) * w[:, None]  # (K, n²): the quadrature weights folded in
    upper = np.arange(n_theta * n_phi) % n_phi < n_phi // 2  # φ in (0, π): local y > 0
    above, below = np.nonzero(upper)[0], np.nonzero(~upper)[0]
    e1, e2 = _onb(normals)
    frame = jnp.stack([e2, normals, e1], -1)  # (M, 3, 3): local -> world, a rotation
    dirs = jnp.einsum("mij,kj->mki", frame, d[above])
    vis = 1.0 - ray_fan_any_hit(origins, dirs, vertices, faces).astype(dtype)
    coeffs = vis @ basis[above] + jnp.sum(basis[below], 0)
    return rotate(coeffs, frame)
