"""Quadrature grids on the sphere and hemisphere, and projection onto real SH.

The grids are Gauss–Legendre in ``z = cos θ`` times uniform cell centres in ``φ`` (polar axis +z,
φ from +x toward +y, as in :mod:`jshadow.sh._basis`). A product ``p(z) · e^{imφ}`` is integrated
exactly when ``deg p < 2·n_theta`` and ``|m| < n_phi``; a product of real SH of bands ``l1, l2`` is
a polynomial of degree ``l1 + l2`` in (x, y, z), so ``n_theta > (l1 + l2) / 2`` and
``n_phi > l1 + l2`` make the Gram matrix exact (to rounding). Functions with discontinuities
(binary visibility) converge only at first order in the grid spacing.

Besides the JAX API, this module keeps two small float64 numpy helpers (``_np_sphere_grid``,
``_np_sh_basis``) that other SH modules use to build constant tables (Gaunt coefficients, rotation
fitting matrices) at trace time, outside any JAX trace. ``_np_sh_basis`` is an independent
evaluation of the same basis from (θ, φ) and associated Legendre functions; the tests check it
against :func:`jshadow.sh.sh_basis`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import lru_cache

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ._basis import sh_basis

__all__ = ["sphere_grid", "hemisphere_grid", "project", "project_fn"]

# full float32 accuracy on accelerators too (no TF32/bf16 passes in these small products)
_HIGHEST = jax.lax.Precision.HIGHEST

# Default "high-accuracy" grid of project_fn: exact for band-limited integrands up to degree 255
# in z and 255 in φ; first-order accurate (about 1e-3 relative) for indicator functions.
_FN_N_THETA = 128
_FN_N_PHI = 256


def _check_grid_size(n_theta: int, n_phi: int) -> None:
    if int(n_theta) != n_theta or int(n_phi) != n_phi or n_theta < 1 or n_phi < 1:
        raise ValueError(f"grid sizes must be positive integers, got n_theta={n_theta}, n_phi={n_phi}")


@lru_cache(maxsize=64)
def _np_sphere_grid(n_theta: int, n_phi: int, hemisphere: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """float64 (dirs (n_theta·n_phi, 3), weights (n_theta·n_phi,)); θ-major, θ increasing."""
    _check_grid_size(n_theta, n_phi)
    x, w = np.polynomial.legendre.leggauss(int(n_theta))  # nodes ascending in [-1, 1]
    if hemisphere:
        x, w = 0.5 * (x + 1.0), 0.5 * w  # affine map of [-1, 1] onto [0, 1]
    z, wz = x[::-1].copy(), w[::-1].copy()  # θ increasing = z decreasing
    s = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    phi = (np.arange(n_phi) + 0.5) * (2.0 * np.pi / n_phi)
    dirs = np.stack(
        [s[:, None] * np.cos(phi)[None, :], s[:, None] * np.sin(phi)[None, :], z[:, None] + 0.0 * phi], -1
    ).reshape(-1, 3)
    weights = (wz[:, None] * np.full(n_phi, 2.0 * np.pi / n_phi)[None, :]).reshape(-1)
    dirs.setflags(write=False)
    weights.setflags(write=False)
    return dirs, weights


def _np_sh_basis(dirs: np.ndarray, n: int) -> np.ndarray:
    """float64 real SH basis (N, n²) from θ, φ and associated Legendre functions (numpy only).

    Same convention as :func:`jshadow.sh.sh_basis` (no Condon–Shortley phase), computed by a
    different route: P_m^m = (2m-1)!! sin^m θ, P_{m+1}^m = (2m+1) z P_m^m, then the three-term
    recurrence in l; ``cos(mφ)``, ``sin(mφ)`` from ``φ = atan2(y, x)``.
    """
    d = np.asarray(dirs, dtype=np.float64)
    z = d[:, 2]
    st = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    phi = np.arctan2(d[:, 1], d[:, 0])
    out = np.zeros((d.shape[0], n * n))
    for m in range(n):
        p = {m: math.prod(range(2 * m - 1, 0, -2)) * st**m}
        if m + 1 < n:
            p[m + 1] = (2 * m + 1) * z * p[m]
        for l in range(m + 2, n):
            p[l] = ((2 * l - 1) * z * p[l - 1] - (l + m - 1) * p[l - 2]) / (l - m)
        for l in range(m, n):
            k = math.sqrt((2 * l + 1) / (4 * math.pi) * math.factorial(l - m) / math.factorial(l + m))
            if m == 0:
                out[:, l * l + l] = k * p[l]
            else:
                out[:, l * l + l + m] = math.sqrt(2.0) * k * p[l] * np.cos(m * phi)
                out[:, l * l + l - m] = math.sqrt(2.0) * k * p[l] * np.sin(m * phi)
    return out


def _as_dtype(dtype):
    return jnp.result_type(float) if dtype is None else jnp.dtype(dtype)


def sphere_grid(n_theta: int, n_phi: int, dtype=None) -> tuple[Float[Array, "N 3"], Float[Array, " N"]]:
    """Gauss–Legendre (in cos θ) × uniform (in φ) quadrature on the unit sphere.

    Args:
        n_theta: number of Gauss–Legendre nodes in ``z = cos θ`` (>= 1).
        n_phi: number of φ cell centres ``φ_j = (j + ½)·2π/n_phi`` (>= 1).
        dtype: floating dtype of the result (default: JAX's default float).

    Returns:
        ``dirs`` (n_theta·n_phi, 3) unit vectors, θ-major with θ increasing (row ``i·n_phi + j``),
        and ``weights`` (n_theta·n_phi,) solid angles in steradians summing to 4π. The rule is exact
        for ``p(cos θ)·e^{imφ}`` with ``deg p < 2·n_theta`` and ``|m| < n_phi``.
    """
    dirs, w = _np_sphere_grid(int(n_theta), int(n_phi), False)
    dt = _as_dtype(dtype)
    return jnp.asarray(dirs, dtype=dt), jnp.asarray(w, dtype=dt)


def hemisphere_grid(n_theta: int, n_phi: int, dtype=None) -> tuple[Float[Array, "N 3"], Float[Array, " N"]]:
    """The same rule as :func:`sphere_grid` on the upper hemisphere ``z >= 0``.

    Gauss–Legendre nodes are mapped onto ``z ∈ [0, 1]``; weights sum to 2π sr. Exact for
    ``p(z)·e^{imφ}`` over the hemisphere with ``deg p < 2·n_theta`` and ``|m| < n_phi``.
    Returns ``dirs`` (n_theta·n_phi, 3) and ``weights`` (n_theta·n_phi,).
    """
    dirs, w = _np_sphere_grid(int(n_theta), int(n_phi), True)
    dt = _as_dtype(dtype)
    return jnp.asarray(dirs, dtype=dt), jnp.asarray(w, dtype=dt)


def project(
    values: Float[ArrayLike, "... N"],
    dirs: Float[ArrayLike, "N 3"],
    weights: Float[ArrayLike, " N"],
    n: int,
) -> Float[Array, "... n2"]:
    """SH coefficients ``c_i = ∫ f Y_i dω`` by the quadrature ``Σ_k w_k f(ω_k) Y_i(ω_k)``.

    Args:
        values: (..., N) samples of f at ``dirs``; leading axes are batch axes.
        dirs: (N, 3) unit quadrature directions (e.g. from :func:`sphere_grid`).
        weights: (N,) quadrature weights in steradians.
        n: number of SH bands of the result.

    Returns:
        (..., n²) coefficients. Exact for band-limited f when the rule is exact for the product
        (see :func:`sphere_grid`); for a hemisphere grid, f is taken as zero on ``z < 0``.
    """
    if int(n) != n or n < 1:
        raise ValueError(f"n (number of SH bands) must be a positive integer, got {n}")
    values, dirs, weights = jnp.asarray(values), jnp.asarray(dirs), jnp.asarray(weights)
    if dirs.ndim != 2 or dirs.shape[-1] != 3:
        raise ValueError(f"dirs must have shape (N, 3), got {dirs.shape}")
    n_dirs = dirs.shape[0]
    if weights.shape != (n_dirs,):
        raise ValueError(f"weights must have shape ({n_dirs},) to match dirs, got {weights.shape}")
    if values.ndim < 1 or values.shape[-1] != n_dirs:
        raise ValueError(f"values must have shape (..., {n_dirs}) to match dirs, got {values.shape}")
    basis_w = sh_basis(dirs, int(n)) * weights[:, None]  # (N, n²): w_k Y_i(ω_k)
    return jnp.matmul(values, basis_w, precision=_HIGHEST)


def project_fn(
    f: Callable[[Float[Array, "N 3"]], Float[Array, "N ..."]],
    n: int,
    n_theta: int | None = None,
    n_phi: int | None = None,
    dtype=None,
) -> Float[Array, "... n2"]:
    """Project a callable ``f(dirs) -> values`` onto n SH bands with a fine sphere grid.

    Args:
        f: maps (N, 3) unit directions to (N,) or (N, ...) values (direction axis first).
        n: number of SH bands.
        n_theta, n_phi: grid size; default 128 × 256 (the "high-accuracy grid": exact for
            band-limited f of degree < 256, about 1e-3 relative error for an indicator function).
        dtype: dtype of the directions passed to f (default: JAX's default float).

    Returns:
        (..., n²) coefficients, where ``...`` are f's trailing value axes.
    """
    dirs, w = sphere_grid(n_theta or _FN_N_THETA, n_phi or _FN_N_PHI, dtype)
    vals = jnp.asarray(f(dirs))
    if vals.ndim < 1 or vals.shape[0] != dirs.shape[0]:
        raise ValueError(f"f must return values of shape ({dirs.shape[0]}, ...), got {vals.shape}")
    return project(jnp.moveaxis(vals, 0, -1), dirs, w, n)
