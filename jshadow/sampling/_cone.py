"""Uniform cone (solid-angle) sampling of a sphere: the baseline of Peters & Dachsbacher 2019.

Directions are uniform over the spherical cap that a sphere of radius r subtends from a point at
distance |c| > r: ``cos θ = 1 − ξ0 (1 − cos α)``, ``φ = 2π ξ1`` about the axis ``c/|c|``, with
``1 − cos α = r_y²/(1 + √(1 − r_y²))``, ``r_y = r/|c|`` (stable for small caps). The density is
``1/(2π(1 − cos α))`` per steradian.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .._numerics import safe_div, safe_normalize, safe_sqrt
from ._projected_cap import CapSample, _check3, _tangent

__all__ = [
    "sample_sphere_cone",
    "random_sphere_cone",
    "sphere_cone_pdf",
    "stratified_sphere_cone",
    "stratified_cone_components",
]


def _cone(to_center, radius):
    c = _check3("to_center", to_center)
    dtype = c.dtype if jnp.issubdtype(c.dtype, jnp.floating) else jnp.result_type(float)
    c = c.astype(dtype)
    r = jnp.asarray(radius, dtype)
    dist = safe_sqrt(jnp.sum(c * c, axis=-1))
    inside = r >= dist
    ry = jnp.clip(safe_div(r, dist, fill=1.0), 0.0, 1.0)
    one_m_cos = ry * ry / (1.0 + safe_sqrt((1.0 - ry) * (1.0 + ry)))
    return safe_normalize(c), one_m_cos, inside


@jax.jit
def sample_sphere_cone(
    u: Float[ArrayLike, "... 2"],
    to_center: Float[ArrayLike, "... 3"],
    radius: Float[ArrayLike, "..."] | float,
) -> CapSample:
    """Uniform directions in the cone toward a sphere (u (..., 2) uniform in [0, 1); to_center
    (..., 3) receiver → sphere centre; radius (...)). ``valid`` is False inside the sphere.
    ``pdf_proj`` equals ``pdf`` (this sampler knows no normal)."""
    u = jnp.asarray(u)
    if u.ndim < 1 or u.shape[-1] != 2:
        raise ValueError(f"u must have shape (..., 2) of uniform numbers, got {u.shape}")
    axis, omc, inside = _cone(to_center, radius)
    u = u.astype(axis.dtype)
    one_m_ct = u[..., 0] * omc  # 1 − cos θ
    ct = 1.0 - one_m_ct
    st = safe_sqrt(one_m_ct * (2.0 - one_m_ct))
    phi = 2.0 * jnp.pi * u[..., 1]
    t1 = _tangent(axis)
    t2 = jnp.cross(axis, t1)
    d = (st * jnp.cos(phi))[..., None] * t1 + (st * jnp.sin(phi))[..., None] * t2 + ct[..., None] * axis
    valid = jnp.broadcast_to(~inside, ct.shape)
    pdf = jnp.where(valid, safe_div(1.0, 2.0 * jnp.pi * omc), 0.0)
    return CapSample(safe_normalize(d), pdf, pdf, valid)


@partial(jax.jit, static_argnames="num")
def random_sphere_cone(key: PRNGKeyArray, to_center, radius, num: int) -> CapSample:
    """``num`` cone samples per configuration, u drawn from ``key``: shapes (..., num[, 3])."""
    c = jnp.asarray(to_center)
    dtype = c.dtype if jnp.issubdtype(c.dtype, jnp.floating) else jnp.result_type(float)
    batch = jnp.broadcast_shapes(c.shape[:-1], jnp.shape(radius))
    u = jax.random.uniform(key, (*batch, num, 2), dtype)
    return sample_sphere_cone(u, c[..., None, :], jnp.asarray(radius, dtype)[..., None])


@jax.jit
def sphere_cone_pdf(
    direction: Float[ArrayLike, "... 3"],
    to_center: Float[ArrayLike, "... 3"],
    radius: Float[ArrayLike, "..."] | float,
) -> Float[Array, "..."]:
    """Solid-angle density of :func:`sample_sphere_cone` at unit ``direction`` (0 outside the cone)."""
    w = _check3("direction", direction)
    axis, omc, inside = _cone(to_center, radius)
    dd = w.astype(axis.dtype) - axis
    in_cone = jnp.sum(dd * dd, axis=-1) <= 2.0 * omc
    return jnp.where(in_cone & ~inside, safe_div(1.0, 2.0 * jnp.pi * omc), 0.0)


def stratified_cone_components(
    to_center: Float[ArrayLike, "... 3"],
    radius: Float[ArrayLike, "..."] | float,
    strata: tuple[int, int] = (4, 8),
) -> tuple[Float[Array, "... K"], Float[Array, "... K"], Float[Array, "... K"]]:
    """:func:`stratified_sphere_cone` as three (..., K) arrays of x, y and z components (what a
    caller that works component-wise wants: XLA:CPU is slow on (..., K, 3) layouts)."""
    rings, sectors = strata
    if not (isinstance(rings, int) and isinstance(sectors, int) and rings >= 1 and sectors >= 1):
        raise ValueError(f"strata must be two positive ints (rings, sectors), got {strata!r}")
    axis, omc, inside = _cone(to_center, radius)
    omc = jnp.where(inside, 2.0, omc)
    dtype = axis.dtype
    one_m_ct = omc[..., None] * ((jnp.arange(rings, dtype=dtype) + 0.5) / rings)  # (..., R)
    ct = jnp.repeat(1.0 - one_m_ct, sectors, axis=-1)  # (..., K), ring-major
    st = jnp.repeat(safe_sqrt(one_m_ct * (2.0 - one_m_ct)), sectors, axis=-1)
    phi = 2.0 * jnp.pi * (jnp.arange(sectors, dtype=dtype) + 0.5) / sectors
    cp, sp = jnp.tile(jnp.cos(phi), rings), jnp.tile(jnp.sin(phi), rings)  # (K,)
    t1 = _tangent(axis)
    t2 = jnp.cross(axis, t1)
    a, b = st * cp, st * sp
    return tuple(a * t1[..., c, None] + b * t2[..., c, None] + ct * axis[..., c, None] for c in range(3))


def stratified_sphere_cone(
    to_center: Float[ArrayLike, "... 3"],
    radius: Float[ArrayLike, "..."] | float,
    strata: tuple[int, int] = (4, 8),
) -> Float[Array, "... K 3"]:
    """K = rings × sectors directions into the cone toward a sphere, one per stratum.

    Deterministic quadrature nodes, uniform in solid angle: the centre of each of ``strata`` =
    (rings, sectors) equal-area cells in (cos θ, φ) about the axis ``to_center/|to_center|``
    (``1 − cos θ = (i + ½)/rings · (1 − cos α)``, ``φ = 2π(j + ½)/sectors``), so an average over
    them is a midpoint rule for the mean over the cap. Inside the sphere (``|to_center| ≤ r``) the
    cap is the whole sphere (``1 − cos α = 2``). Batches over the leading axes of ``to_center``
    and ``radius``; no NaN for a zero ``to_center`` (any axis then). Unit vectors by construction
    (an orthonormal frame), to rounding.
    """
    return jnp.stack(stratified_cone_components(to_center, radius, strata), axis=-1)
