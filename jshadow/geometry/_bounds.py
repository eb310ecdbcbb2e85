"""The bounding sphere of a point set (DESIGN.md §3) and normalisation to the unit sphere.

The shadow-field method samples an occluder's visibility on its bounding sphere (Zhou et al. 2005,
"Precomputed shadow fields"; the deformable-shadow-fields paper, Sec. 4). jshadow's bounding sphere
is the cheap, deterministic one: centre = centre of the axis-aligned bounding box, radius = distance
to the farthest vertex from that centre. It is not the minimal enclosing sphere (that one is not a
smooth or even continuous function of the vertices), but it contains every vertex and is
piecewise smooth, so it can be recomputed every frame of a deformation and differentiated.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._numerics import safe_div, safe_norm, select_max, select_min

__all__ = ["bounding_sphere", "normalize_to_unit_sphere"]


def bounding_sphere(
    vertices: Float[ArrayLike, "... V 3"],
) -> tuple[Float[Array, "... 3"], Float[Array, "..."]]:
    """Centre (..., 3) and radius (...) of the AABB-centred bounding sphere of ``vertices``.

    ``center = (min_v x + max_v x) / 2`` per axis; ``radius = max_v |x_v - center|``. Both are
    deterministic (no sampling, no iteration) and in the units of ``vertices``.

    Gradients flow (piecewise-linear / piecewise-smooth): the centre's gradient reaches only the
    vertices attaining the per-axis minimum and maximum; the radius's gradient reaches the farthest
    vertex directly and, through the centre, those extreme vertices. Where several vertices tie for a
    minimum, maximum or the farthest distance, the gradient goes to the first of them
    (:func:`jshadow._numerics.select_max`: finite for any rounding, unlike ``jnp.max``'s rule, which
    divides by a tie count that fused recomputation can make zero). A radius of zero (all
    vertices equal) has a zero, not NaN, gradient.
    """
    v = jnp.asarray(vertices)
    if v.ndim < 2 or v.shape[-1] != 3 or v.shape[-2] == 0:
        raise ValueError(f"bounding_sphere expects vertices of shape (..., V, 3) with V >= 1, got {v.shape}")
    center = 0.5 * (select_min(v, axis=-2) + select_max(v, axis=-2))
    radius = select_max(safe_norm(v - center[..., None, :]), axis=-1)
    return center, radius


def normalize_to_unit_sphere(vertices: Float[ArrayLike, "... V 3"]) -> Float[Array, "... V 3"]:
    """Translate and scale ``vertices`` so that their bounding sphere becomes the unit sphere at 0.

    ``(x - center) / radius`` with :func:`bounding_sphere`; differentiable. The result's bounding
    sphere is centre 0, radius 1 (up to rounding). A point set of zero radius maps to the origin.
    The original placement is ``center + radius · unit`` (the form of ``MeshOccluder``).
    """
    v = jnp.asarray(vertices)
    center, radius = bounding_sphere(v)
    inv_r = safe_div(1.0, radius)  # 0 (not inf) for a single point
    return (v - center[..., None, :]) * inv_r[..., None, None]
