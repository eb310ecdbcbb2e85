"""The bounding sphere of a point set (DESIGN.md §3) and normalisation to the unit sphere.

The shadow-field method samples an occluder's visibility on its bounding sphere (Zhou et al. 2005,
"Precomputed shadow fields"; the deformable-shadow-fields paper, Sec. 4). jshadow's bounding sphere
is the cheap, deterministic one: centre = centre of the axis-aligned bounding box, radius = distance
to the farthest vertex from that centre. It is not the minimal enclosing sphere (that one is not a
smooth or even continuous function of the vertices), but it contains every vertex and is
piecewise smooth, so it can be recomputed every frame of a deformation and differentiated.

A deforming occluder may instead keep a fixed centre (``method.bsv_center = "placed"``): its BSV is
then sampled about the occluder's placed centre c with radius ``max_v |x_v - c|``.
:func:`with_center_anchors` expresses that sphere in the same rule, by appending six points that
no face references, so every sampler (and its derivative) that takes the box-centred sphere of its
input takes the sphere about c instead.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._numerics import eps, safe_div, safe_norm, select_max, select_min

__all__ = [
    "bounding_sphere",
    "normalize_to_unit_sphere",
    "with_center_anchors",
    "cone_may_meet_sphere",
    "fan_may_meet_sphere",
]


def bounding_sphere(
    vertices: Float[ArrayLike, "... V 3"],
) -> tuple[Float[Array, "... 3"], Float[Array, "..."]]:
    """Centre (..., 3) and radius (...) of the AABB-centred bounding sphere of ``vertices``.

    ``center = (min_v x + max_v x) / 2`` per axis; ``radius = max_v |x_v - center|``. Both are
    deterministic (no sampling, no iteration) and in the units of ``vertices``.

    Gradients flow (piecewise-linear / piecewise-smooth): the centre's gradient reaches only the
    vertices attaining the per-axis minimum and maximum; the radius's gradient reaches the farthest
    vertex directly and, through the centre, those extreme vertices. Where several vertices tie for a
    minimum, maximum or the farthest distance (within 2.5 rounding units: mirror-image vertices of a
    symmetric mesh), the gradient is split equally between them, the derivative central differences
    measure (:func:`jshadow._numerics.select_max`: finite for any rounding, unlike ``jnp.max``'s
    rule, which divides by a tie count that fused recomputation can make zero). A radius of zero
    (all vertices equal) has a zero, not NaN, gradient.
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


def with_center_anchors(
    vertices: Float[ArrayLike, "V 3"], center: Float[ArrayLike, "3"]
) -> Float[Array, "V+6 3"]:
    """``vertices`` followed by six anchor points ``c ± h_i e_i``, ``h_i = max_v |x_v,i - c_i|``
    widened by ten rounding units (``eps(dtype) · (|c_i| + h_i)``).

    The anchors make :func:`bounding_sphere` of the result the sphere about ``center``: the box of
    the result spans ``c ± h`` per axis, so its centre is ``c`` (up to one rounding of
    ``((c - h) + (c + h)) / 2``), and its radius is ``max_v |x_v - c|`` (no anchor is farther, up
    to the widening: ``h_i <= max_v |x_v - c|``). Faces index only the first V rows, so the anchors
    change no visibility; a BSV sampler given the result samples on the shell about ``center``.
    Differentiable in both arguments: the centre's derivative comes from ``center`` alone, as
    ``h``'s two contributions cancel. That needs the anchors to be the box's only extremes: a mesh
    normalised about its centre has, at rest, a vertex at ``c_i - h_i`` as well as one at
    ``c_i + h_i``, and a vertex tied with an anchor would share the extreme's derivative
    (:func:`jshadow._numerics.select_min`), so the centre would follow part of each extreme vertex's
    motion. The widening (four times the tie tolerance of ``select_max``) makes the anchors strictly
    outermost. Shapes: vertices (V, 3), center (3,) -> (V + 6, 3).
    """
    v = jnp.asarray(vertices)
    c = jnp.asarray(center, v.dtype)
    if v.ndim != 2 or v.shape[-1] != 3 or v.shape[0] == 0:
        raise ValueError(f"with_center_anchors expects vertices of shape (V, 3) with V >= 1, got {v.shape}")
    if c.shape != (3,):
        raise ValueError(f"with_center_anchors expects a centre of shape (3,), got {c.shape}")
    h = select_max(jnp.abs(v - c), axis=0)  # (3,)
    h = h + eps(v.dtype) * (jnp.abs(c) + h)  # strictly beyond every vertex: no ties with the box
    offsets = jnp.eye(3, dtype=v.dtype) * h  # rows h_i e_i
    return jnp.concatenate([v, c + offsets, c - offsets], axis=0)


_CONE_SLACK = 1e-3  # relative widening of the angular test (rounding of the angles in float32)


def cone_may_meet_sphere(
    points: Float[ArrayLike, "N 3"],
    light_center: Float[ArrayLike, "3"],
    light_radius: Float[ArrayLike, ""],
    center: Float[ArrayLike, "3"],
    radius: Float[ArrayLike, ""],
) -> Array:
    """(N,) bool: whether a ray from ``points`` toward the light sphere may meet the sphere (c, r)
    before the light.

    False only where the cone from x around the light (half-angle asin(r_L / |l − x|)) and the
    cone around the sphere (asin(r / |c − x|)) are apart, γ > (α_L + α_S)(1 + 10⁻³), γ the angle
    between their axes, or where the sphere's centre is not nearer than the light's (the order in
    which the renderer multiplies an occluder in). True for a point inside either sphere. A
    conservative, derivative-free mask (its inputs are held constant): cheap, (N,) work.
    """
    x = jax.lax.stop_gradient(jnp.asarray(points))
    lc, lr = (jax.lax.stop_gradient(jnp.asarray(a, x.dtype)) for a in (light_center, light_radius))
    to_l = lc - x
    d_l = safe_norm(to_l)
    a_l = jnp.arcsin(jnp.clip(safe_div(lr, d_l, 1.0), 0.0, 1.0))
    near, reach, d_s = _sphere_cone(x, to_l, a_l, center, radius)
    return (d_s < d_l) & ((d_l <= lr) | near | reach)


def fan_may_meet_sphere(
    points: Float[ArrayLike, "N 3"],
    axis: Float[ArrayLike, "3"],
    half_angle: Float[ArrayLike, ""],
    center: Float[ArrayLike, "3"],
    radius: Float[ArrayLike, ""],
) -> Array:
    """(N,) bool: whether a ray from ``points`` in a direction within ``half_angle`` (radians) of
    the unit ``axis`` (distant lights) may meet the sphere (c, r): False only where that cone and
    the cone from x around the sphere are apart, as :func:`cone_may_meet_sphere`; True inside the
    sphere. Derivative-free (its inputs are held constant)."""
    x = jax.lax.stop_gradient(jnp.asarray(points))
    ax, half = (jax.lax.stop_gradient(jnp.asarray(a, x.dtype)) for a in (axis, half_angle))
    near, reach, _ = _sphere_cone(x, jnp.broadcast_to(ax, x.shape), half, center, radius)
    return near | reach


def _sphere_cone(x, to_l, a_l, center, radius):
    """(inside the sphere, the cones about ``to_l`` (half-angle a_l) and about the sphere overlap,
    distance to the sphere's centre), each (N,)."""
    c, r = (jax.lax.stop_gradient(jnp.asarray(a, x.dtype)) for a in (center, radius))
    to_s = c - x
    d_s = safe_norm(to_s)
    gamma = jnp.arctan2(safe_norm(jnp.cross(to_l, to_s)), jnp.sum(to_l * to_s, -1))
    a_s = jnp.arcsin(jnp.clip(safe_div(r, d_s, 1.0), 0.0, 1.0))
    return d_s <= r, gamma <= (a_l + a_s) * (1.0 + _CONE_SLACK), d_s
