"""Importance sampling of lat-long environment maps, piecewise constant per pixel.

The map's convention is that of :func:`jshadow.entities.latlong_to_dir`: pixel (i, j) of an H×W
image covers ``θ ∈ [π i/H, π (i+1)/H)`` from +y and ``φ ∈ [2π j/W, 2π (j+1)/W)``, and
:meth:`jshadow.entities.Environment.radiance_at` looks radiance up per pixel. Pixels are chosen with
probability proportional to luminance × pixel solid angle (marginal row, then conditional column),
and the direction is uniform in solid angle inside the pixel (``cos θ`` uniform between the
pixel's bounds). Hence the density is constant per pixel, ``p(ω) = P_ij / Ω_ij``, and
``L(ω)/p(ω)`` is constant per pixel (up to colour): zero variance for the unoccluded, un-cosined
integral. Pixels of zero luminance are never sampled; combine with cosine sampling (MIS) to stay
unbiased where that matters.
"""

from __future__ import annotations

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .._numerics import safe_div, safe_sqrt
from ..entities import Environment, dir_to_latlong
from ._projected_cap import CapSample, _check3

__all__ = [
    "EnvironmentSampler",
    "environment_sampler",
    "sample_environment",
    "random_environment",
    "environment_pdf",
]

_LUMA = (0.2126, 0.7152, 0.0722)


class EnvironmentSampler(eqx.Module):
    """Tables for :func:`sample_environment` (build with :func:`environment_sampler`)."""

    pmf: Float[Array, "H W"]  # P_ij: probability of pixel (i, j), sums to 1 (or all 0 for a black map)
    row_cdf: Float[Array, " H1"]  # (H + 1,) cumulative row probabilities, 0 … 1
    col_cdf: Float[Array, "H W1"]  # (H, W + 1) cumulative conditional column probabilities per row
    cos_edges: Float[Array, " H1"]  # (H + 1,) cos θ at the row boundaries, 1 … −1
    pixel_solid_angle: Float[Array, " H"]  # Ω_i of one pixel in row i (steradians)


def environment_sampler(
    environment: Environment | Float[ArrayLike, "H W 3"], radiance: Float[ArrayLike, "3"] | None = None
) -> EnvironmentSampler:
    """Sampling tables of a lat-long image (H, W, 3) (or of an ``Environment`` of kind "hdr",
    whose ``radiance`` multiplier is applied). Weights: luminance (Rec. 709) × pixel solid angle;
    negative or non-finite pixels must not occur (not checked at trace time)."""
    if isinstance(environment, Environment):
        if environment.kind != "hdr" or environment.image is None:
            raise ValueError(
                f"environment importance sampling needs an 'hdr' environment, got {environment.kind!r}"
            )
        image, radiance = environment.image, environment.radiance
    else:
        image = environment
    image = jnp.asarray(image)
    if image.ndim != 3 or image.shape[-1] != 3 or min(image.shape[:2]) < 1:
        raise ValueError(f"environment image must have shape (H, W, 3), got {image.shape}")
    dtype = image.dtype if jnp.issubdtype(image.dtype, jnp.floating) else jnp.result_type(float)
    image = image.astype(dtype)
    if radiance is not None:
        image = image * jnp.asarray(radiance, dtype)
    h, w = image.shape[:2]
    luma = image @ jnp.asarray(_LUMA, dtype)
    cos_edges = jnp.cos(jnp.pi * jnp.arange(h + 1, dtype=dtype) / h)
    omega = (2.0 * jnp.pi / w) * (cos_edges[:-1] - cos_edges[1:])
    weight = jnp.maximum(luma, 0.0) * omega[:, None]
    pmf = safe_div(weight, jnp.sum(weight))
    row_p = jnp.sum(pmf, axis=1)
    zero = jnp.zeros((1,), dtype)
    row_cdf = jnp.concatenate([zero, jnp.cumsum(row_p)])
    row_cdf = row_cdf / jnp.maximum(row_cdf[-1], jnp.finfo(dtype).tiny)
    col = jnp.cumsum(pmf, axis=1)
    col_cdf = jnp.concatenate([jnp.zeros((h, 1), dtype), safe_div(col, row_p[:, None])], axis=1)
    return EnvironmentSampler(pmf, row_cdf, col_cdf, cos_edges, omega)


def _invert_cdf(cdf, x):
    """Index k with cdf[k] ≤ x < cdf[k+1] (skipping empty bins) and the fraction inside it."""
    n = cdf.shape[-1] - 1
    k = jnp.clip(jnp.searchsorted(cdf[1:], x, side="right"), 0, n - 1)
    lo, hi = cdf[k], cdf[k + 1]
    frac = jnp.clip(safe_div(x - lo, hi - lo), 0.0, 1.0)
    return k, frac


@jax.jit
def sample_environment(sampler: EnvironmentSampler, u: Float[ArrayLike, "... 2"]) -> CapSample:
    """Directions from the environment's luminance distribution. u (..., 2) uniform in [0, 1);
    returns :class:`CapSample` with ``pdf`` per steradian (``pdf_proj`` = ``pdf``: no normal
    here); ``valid`` False only for an all-black map."""
    u = jnp.asarray(u)
    if u.ndim < 1 or u.shape[-1] != 2:
        raise ValueError(f"u must have shape (..., 2) of uniform numbers, got {u.shape}")
    dtype = sampler.pmf.dtype
    u = u.astype(dtype)
    h, w = sampler.pmf.shape
    i, fv = _invert_cdf(sampler.row_cdf, u[..., 0])
    j, fu = jax.vmap(_invert_cdf)(sampler.col_cdf[i.reshape(-1)], u[..., 1].reshape(-1))
    j, fu = j.reshape(i.shape), fu.reshape(i.shape)
    c0, c1 = sampler.cos_edges[i], sampler.cos_edges[i + 1]
    ct = jnp.clip(c0 + fv * (c1 - c0), -1.0, 1.0)
    st = safe_sqrt((1.0 - ct) * (1.0 + ct))
    phi = 2.0 * jnp.pi * (j.astype(dtype) + fu) / w
    d = jnp.stack([st * jnp.cos(phi), ct, -st * jnp.sin(phi)], axis=-1)
    pdf = safe_div(sampler.pmf[i, j], sampler.pixel_solid_angle[i])
    return CapSample(d, pdf, pdf, pdf > 0)


@partial(jax.jit, static_argnames="shape")
def random_environment(sampler: EnvironmentSampler, key: PRNGKeyArray, shape: tuple[int, ...]) -> CapSample:
    """Samples of shape ``shape`` (+ (3,) for directions), u drawn from ``key``."""
    return sample_environment(sampler, jax.random.uniform(key, (*shape, 2), sampler.pmf.dtype))


@jax.jit
def environment_pdf(sampler: EnvironmentSampler, direction: Float[ArrayLike, "... 3"]) -> Float[Array, "..."]:
    """Solid-angle density of :func:`sample_environment` at unit directions (..., 3); the pixel is
    found exactly as :meth:`Environment.radiance_at` finds it."""
    d = _check3("direction", direction).astype(sampler.pmf.dtype)
    h, w = sampler.pmf.shape
    uu, vv = dir_to_latlong(d)
    i = jnp.clip(jnp.floor(vv * h).astype(jnp.int32), 0, h - 1)
    j = jnp.clip(jnp.floor(uu * w).astype(jnp.int32), 0, w - 1)
    return safe_div(sampler.pmf[i, j], sampler.pixel_solid_angle[i])
