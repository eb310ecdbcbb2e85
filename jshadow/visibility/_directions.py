"""Direction sets and closed-form hemisphere/cap projections for the BSV.

At each BSV sample point only the local hemisphere facing the occluder's centre (local z > 0) is
cast (Zhou et al. 2005, "Precomputed shadow fields", Sec. 4; deformable-shadow-fields paper
Sec. 4.1): the other half of the sphere of directions points away from the bounding sphere and is
always visible; its SH projection is known in closed form.

Directions: Gauss–Legendre nodes in ``z = cos θ`` on (0, 1) times ``n_phi`` uniform cell centres in
φ (local polar axis +z). With these weights the quadrature integrates every SH of fewer than
``2·n_theta`` bands exactly over the hemisphere, so the unoccluded hemisphere projects exactly and
only the occluded directions carry quadrature error (first order in the angular spacing, since
visibility is an indicator).
"""

from __future__ import annotations

import math
from functools import lru_cache

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

__all__ = ["hemisphere_directions", "cap_sh_projection", "far_hemisphere_sh_projection"]


@lru_cache(maxsize=32)
def _np_hemisphere(n_theta: int, n_phi: int) -> tuple[np.ndarray, np.ndarray]:
    x, w = np.polynomial.legendre.leggauss(n_theta)
    z, wz = 0.5 * (x[::-1] + 1.0), 0.5 * w[::-1]  # θ increasing = z decreasing, z in (0, 1)
    s = np.sqrt(1.0 - z * z)
    phi = (np.arange(n_phi) + 0.5) * (2.0 * math.pi / n_phi)
    dirs = np.stack(
        np.broadcast_arrays(s[:, None] * np.cos(phi), s[:, None] * np.sin(phi), z[:, None]), axis=-1
    ).reshape(-1, 3)
    weights = np.repeat(wz * (2.0 * math.pi / n_phi), n_phi)
    return dirs, weights


def hemisphere_directions(
    n_theta: int = 32, n_phi: int = 32, dtype=None
) -> tuple[Float[Array, "K 3"], Float[Array, " K"]]:
    """Local hemisphere (z > 0) directions (K = n_theta·n_phi, 3), θ-major, and solid-angle weights (K,).

    The weights sum to 2π (steradians). ``Σ_k w_k f(ω_k)`` is exact for polynomials in (x, y, z)
    of degree < 2·n_theta in z and frequency < n_phi in φ.
    """
    if not (isinstance(n_theta, int) and isinstance(n_phi, int) and n_theta >= 1 and n_phi >= 1):
        raise ValueError(
            f"directions must be two positive ints (n_theta, n_phi), got ({n_theta!r}, {n_phi!r})"
        )
    dtype = jnp.result_type(float) if dtype is None else dtype
    dirs, weights = _np_hemisphere(n_theta, n_phi)
    return jnp.asarray(dirs, dtype), jnp.asarray(weights, dtype)


def cap_sh_projection(cos_alpha: Float[ArrayLike, "..."], n: int) -> Float[Array, "... n2"]:
    """SH projection (..., n²) of the indicator of the cap ``z ≥ cos α`` around local +z.

    Zonal: only ``m = 0`` entries are non-zero,
    ``∫_cap Y_l0 dω = 2π K_l (P_{l−1}(cos α) − P_{l+1}(cos α)) / (2l + 1)`` (l ≥ 1) and
    ``2π K_0 (1 − cos α)`` (l = 0), with ``K_l = √((2l+1)/4π)``. Differentiable in cos α.
    A sphere of radius r seen from distance R ≥ r covers the cap ``cos α = √(1 − (r/R)²)``.
    """
    if not (isinstance(n, int) and n >= 1):
        raise ValueError(f"n (number of SH bands) must be a positive int, got {n!r}")
    x = jnp.asarray(cos_alpha)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    p = [jnp.ones_like(x), x]  # Legendre P_l(x) by Bonnet's recurrence, up to l = n
    for l in range(1, n):
        p.append(((2 * l + 1) * x * p[l] - l * p[l - 1]) / (l + 1))
    out = jnp.zeros((*x.shape, n * n), x.dtype)
    for l in range(n):
        k = math.sqrt((2 * l + 1) / (4.0 * math.pi))
        integral = 1.0 - x if l == 0 else (p[l - 1] - p[l + 1]) / (2 * l + 1)
        out = out.at[..., l * l + l].set(2.0 * math.pi * k * integral)
    return out


def far_hemisphere_sh_projection(n: int, dtype=None) -> Float[Array, " n2"]:
    """SH projection (n²,) of the always-visible local hemisphere z < 0 (pointing away from the centre).

    ``∫_{z<0} Y_i dω``: √π on e0 (half of √(4π)), zonal, and zero for even l ≥ 2.
    """
    dtype = jnp.result_type(float) if dtype is None else dtype
    full = jnp.zeros(n * n, dtype).at[0].set(math.sqrt(4.0 * math.pi))
    return full - cap_sh_projection(jnp.asarray(0.0, dtype), n)
