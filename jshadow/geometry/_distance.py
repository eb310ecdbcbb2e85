"""Distances from points to triangles and to a triangle mesh's surface.

The squared distance from a point p to a triangle (a, b, c) is the squared distance to its plane
where p projects inside the triangle, else the least squared distance to its three edges (each a
segment: the parameter of p's projection on the edge's line clamped to [0, 1]). A degenerate
triangle (zero area) has no inside: its edges give the distance. No square roots are taken;
divisions are guarded (``jshadow._numerics.safe_div``), so the values are finite for any input.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int

from .._numerics import safe_div

__all__ = ["point_triangle_distance2", "point_mesh_distance2"]


def _segment_d2(p, a, b):
    ab = b - a
    t = jnp.clip(safe_div(jnp.sum((p - a) * ab, -1), jnp.sum(ab * ab, -1)), 0.0, 1.0)
    r = p - a - t[..., None] * ab
    return jnp.sum(r * r, -1)


def point_triangle_distance2(
    points: Float[ArrayLike, "*batch 3"], triangles: Float[ArrayLike, "*batch 3 3"]
) -> Float[Array, "*batch"]:
    """Squared Euclidean distance from each point to the closed triangle (corners ``[..., k, :]``),
    batch shapes broadcast against each other. World units squared; exact up to rounding."""
    p = jnp.asarray(points)
    tri = jnp.asarray(triangles)
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    n = jnp.cross(b - a, c - a)
    nn = jnp.sum(n * n, -1)

    def side(u, v):  # p on the inner side of the edge u -> v (seen along n)
        return jnp.sum(jnp.cross(v - u, p - u) * n, -1) >= 0.0

    inside = side(a, b) & side(b, c) & side(c, a) & (nn > 0.0)
    plane = safe_div(jnp.sum((p - a) * n, -1) ** 2, nn)
    edges = jnp.minimum(jnp.minimum(_segment_d2(p, a, b), _segment_d2(p, b, c)), _segment_d2(p, c, a))
    return jnp.where(inside, plane, edges)


def point_mesh_distance2(
    points: Float[ArrayLike, "M 3"], vertices: Float[ArrayLike, "V 3"], faces: Int[ArrayLike, "F 3"]
) -> Float[Array, " M"]:
    """(M,) squared distance from each point to the nearest point of the mesh's faces (its surface,
    not its volume: a point inside a closed mesh is as far as the nearest face). Cost M·F; memory
    M·F (chunk the points for large meshes)."""
    tri = jnp.asarray(vertices)[jnp.asarray(faces)]  # (F, 3, 3)
    return jnp.min(point_triangle_distance2(jnp.asarray(points)[:, None, :], tri[None]), -1)
