"""Sampling-sphere parametrisation and local frames of the base sphere visibility (BSV).

Convention (shared by every BSV producer and consumer in jshadow; deformable-shadow-fields paper
Sec. 4.1, with the polar axis chosen as world +z so that receivers below an occluder, which see it
from −y, sit at the equator, far from the poles):

* grid point (i, j) of a T×P grid: ``θ_i = π(i + 0.5)/T``, ``φ_j = 2πj/P``;
* direction ``u = (sin θ cos φ, sin θ sin φ, cos θ)``; sample point ``p = c + R·u`` on the shell of
  radius ``R = shell · r`` around the bounding-sphere centre c;
* local frame, defined for any (θ, φ) so that it can be interpolated:
  ``x_loc = e_θ = (cos θ cos φ, cos θ sin φ, −sin θ)``, ``y_loc = −e_φ = (sin φ, −cos φ, 0)``,
  ``z_loc = −u`` (toward the centre); right-handed (``x_loc × y_loc = z_loc``).
  ``frame = [x_loc | y_loc | z_loc]`` as columns, so ``world = frame @ local``.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

__all__ = ["bsv_frames", "bsv_grid_angles"]


def bsv_grid_angles(t: int, p: int, dtype=None) -> tuple[Float[Array, " T"], Float[Array, " P"]]:
    """Angles of the T×P BSV grid: ``θ_i = π(i + 0.5)/T`` (T,), ``φ_j = 2πj/P`` (P,), radians."""
    if not (isinstance(t, int) and isinstance(p, int) and t >= 1 and p >= 1):
        raise ValueError(f"BSV grid must be two positive ints (T, P), got ({t!r}, {p!r})")
    dtype = jnp.result_type(float) if dtype is None else dtype
    theta = (jnp.arange(t, dtype=dtype) + 0.5) * (math.pi / t)
    phi = jnp.arange(p, dtype=dtype) * (2.0 * math.pi / p)
    return theta, phi


def bsv_frames(
    theta: Float[ArrayLike, "..."], phi: Float[ArrayLike, "..."]
) -> tuple[Float[Array, "... 3"], Float[Array, "... 3 3"]]:
    """Outward direction ``u`` (..., 3) and local frame (..., 3, 3) at polar angle θ, azimuth φ.

    θ, φ in radians about world +z, broadcast against each other. ``frame[..., :, k]`` is the k-th
    local axis in world coordinates (x = e_θ, y = −e_φ, z = −u), so ``world = frame @ local`` and
    ``local = frameᵀ @ world``. Smooth in (θ, φ) everywhere, including the poles (where e_θ, e_φ
    still form a valid frame); differentiable.
    """
    theta, phi = jnp.broadcast_arrays(jnp.asarray(theta), jnp.asarray(phi))
    st, ct = jnp.sin(theta), jnp.cos(theta)
    sp, cp = jnp.sin(phi), jnp.cos(phi)
    u = jnp.stack([st * cp, st * sp, ct], axis=-1)
    x = jnp.stack([ct * cp, ct * sp, -st], axis=-1)
    y = jnp.stack([sp, -cp, jnp.zeros_like(sp)], axis=-1)
    frame = jnp.stack([x, y, -u], axis=-1)
    return u, frame
