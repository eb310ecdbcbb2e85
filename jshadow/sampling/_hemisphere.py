"""Cosine-weighted hemisphere sampling: density ``max(0, n·ω)/π`` per steradian."""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .._numerics import safe_normalize, safe_sqrt
from ._projected_cap import CapSample, _check3, _tangent

__all__ = ["sample_cosine_hemisphere", "random_cosine_hemisphere", "cosine_hemisphere_pdf"]


@jax.jit
def sample_cosine_hemisphere(u: Float[ArrayLike, "... 2"], normal: Float[ArrayLike, "... 3"]) -> CapSample:
    """Malley's method: a uniform point of the unit disk (radius √ξ0, angle 2πξ1) lifted to the
    hemisphere around the unit ``normal``. u (..., 2) in [0, 1); leading axes broadcast.
    ``pdf = (n·ω)/π``, ``pdf_proj = 1/π``; always valid."""
    u = jnp.asarray(u)
    if u.ndim < 1 or u.shape[-1] != 2:
        raise ValueError(f"u must have shape (..., 2) of uniform numbers, got {u.shape}")
    n = safe_normalize(_check3("normal", normal))
    u = u.astype(n.dtype)
    rad = safe_sqrt(u[..., 0])
    phi = 2.0 * jnp.pi * u[..., 1]
    z = safe_sqrt(1.0 - u[..., 0])
    t1 = _tangent(n)
    t2 = jnp.cross(n, t1)
    d = (rad * jnp.cos(phi))[..., None] * t1 + (rad * jnp.sin(phi))[..., None] * t2 + z[..., None] * n
    pdf = z / jnp.pi
    return CapSample(safe_normalize(d), pdf, jnp.full_like(pdf, 1.0 / jnp.pi), jnp.ones(pdf.shape, bool))


@partial(jax.jit, static_argnames="num")
def random_cosine_hemisphere(key: PRNGKeyArray, normal: Float[ArrayLike, "... 3"], num: int) -> CapSample:
    """``num`` cosine-weighted samples per normal, u drawn from ``key``: shapes (..., num[, 3])."""
    n = jnp.asarray(normal)
    u = jax.random.uniform(key, (*n.shape[:-1], num, 2), n.dtype)
    return sample_cosine_hemisphere(u, n[..., None, :])


@jax.jit
def cosine_hemisphere_pdf(
    direction: Float[ArrayLike, "... 3"], normal: Float[ArrayLike, "... 3"]
) -> Float[Array, "..."]:
    """``max(0, n·ω)/π`` for unit directions ω and normals n (..., 3)."""
    w = _check3("direction", direction)
    n = safe_normalize(_check3("normal", normal))
    return jnp.maximum(jnp.sum(w * n, axis=-1), 0.0) / jnp.pi
