"""The bright part of a lat-long environment map as a few distant lights (median cut).

An environment's n-band SH cannot hold a studio's small, intense lamps: the studio map of
``configs/bunny_studio.toml`` puts 57 % of its energy into 0.05 % of the sphere and 91 % into 2 %
(``experiments/studio_lamps.py``), and even exact n-band visibility leaves 19 % relative RMSE on
its floor at 4 bands (``experiments/band_limit.py``). :func:`split_environment` therefore splits a map into

* a *rest* — each pixel's radiance clamped to ``τ = threshold × (the map's mean luminance)``,
  colour kept — that stays on the n-band path of every other environment, and
* a *bright part* — the excess over τ — cut into K regions of equal energy by the median-cut
  algorithm (Debevec 2005, "A median cut algorithm for light probe sampling": split the region
  of most extent in two along its longer side, at the energy median, until there are K), each
  region a distant light at its energy centroid.

:func:`jshadow.scene.environment_visible_fraction` shadows the bright part through the BSV's
occlusion images, like the cap directions of a sphere light: the receiver's irradiance from it is
the bright part's exact unoccluded irradiance (tabulated, :func:`jshadow.lights.environment_irradiance_map`)
times the energy- and cosine-weighted visible fraction of the K directions. The split is exact
(rest + bright part = the map, pixel for pixel); what the K directions approximate is only the
*shape* of each region's shadow (a region's penumbra becomes one hard edge), so K should grow with
the bright regions' size, or the lookups widen each edge to its region's penumbra from the
regions' extents (``EnvironmentLights.spread``, ``method.lamp_penumbrae = "region"``).

Limitations: lat-long ("hdr") environments only; the split is decided once from the concrete
image (thresholds and regions are not differentiated: a traced image raises), while the lights'
energies and both parts stay linear — and differentiable — in the image and the radiance.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .entities import Environment, Method
from .lights import IrradianceMap, _np_latlong_dirs, environment_irradiance_map

__all__ = ["EnvironmentLights", "split_environment", "median_cut", "MAX_FAN"]

MAX_FAN = 8  # lights per fan: the occlusion-image lookups choose their four grid points once per fan


class EnvironmentLights(eqx.Module):
    """The bright part of an environment as K distant lights, in fans of nearby directions.

    Attributes:
        directions: (K, 3) unit world directions toward each light (its region's energy centroid).
        energy: (K, 3) radiance × solid angle of each region, summed over its pixels (RGB; the
            region's irradiance on a surface facing it, were it a point).
        axes: (G, 3) unit direction of each fan (the energy centroid of its lights); fan g is
            lights ``g·fan .. (g + 1)·fan − 1``, and the lookups of a fan share their grid points
            (:func:`jshadow.visibility.image_fan_visibility`).
        unoccluded: the bright part's exact unoccluded irradiance over normals.
        fan: lights per fan (static), K = G·fan.
        spread: (K, 3, 3) each region's angular second moment about its light, in its tangent
            plane (radians², energy-weighted over its pixels, each pixel's own width included:
            ``Σ w (δ δᵀ + Δθ²/12 e_θ e_θᵀ + (Δφ sin θ)²/12 e_φ e_φᵀ) / Σ w`` with δ the pixel's
            direction less the light's, projected off it). ``eᵀ spread e`` is the variance along a
            unit tangent e: what the lamp lookups widen a shadow's edge by
            (:func:`jshadow.visibility.lamp_visibility`). Held fixed, like the directions.
    """

    directions: Float[Array, "K 3"]
    energy: Float[Array, "K 3"]
    axes: Float[Array, "G 3"]
    unoccluded: IrradianceMap
    spread: Float[Array, "K 3 3"]
    fan: int = eqx.field(static=True)


def _solid_angles(h: int, w: int) -> np.ndarray:
    """(H,) exact solid angle of one pixel in each row of an H × W lat-long map."""
    edges = np.cos(np.pi * np.arange(h + 1) / h)
    return (edges[:-1] - edges[1:]) * (2.0 * np.pi / w)


def median_cut(weight: np.ndarray, count: int) -> np.ndarray:
    """Median-cut regions of a lat-long weight image: (H, W) int labels 0..count−1.

    ``weight`` (H, W) ≥ 0 is energy per pixel (already times its solid angle); ``count`` a power of
    two. Each level splits every region in two across its longer side — angular extent, the width
    measured at the region's middle latitude — at the cut that best halves its weight; a region
    one pixel wide along that side is cut along the other, and one of a single pixel becomes itself
    and an empty region. Labels follow the tree's depth-first order, so the regions of one subtree
    are consecutive. Deterministic; NumPy, float64.
    """
    count = int(count)
    if count < 1 or count & (count - 1):
        raise ValueError(f"median_cut: count must be a power of two >= 1, got {count}")
    w = np.asarray(weight, np.float64)
    if w.ndim != 2 or np.any(~np.isfinite(w)) or np.any(w < 0):
        raise ValueError("median_cut: weight must be a finite, non-negative (H, W) image")
    h, wd = w.shape
    regions = [(0, h, 0, wd)]
    while len(regions) < count:
        nxt = []
        for r0, r1, c0, c1 in regions:
            nxt.extend(_cut(w, r0, r1, c0, c1))
        regions = nxt
    labels = np.zeros((h, wd), np.int32)
    for k, (r0, r1, c0, c1) in enumerate(regions):
        labels[r0:r1, c0:c1] = k
    return labels


def _cut(w: np.ndarray, r0: int, r1: int, c0: int, c1: int):
    h, wd = w.shape
    rows, cols = r1 - r0, c1 - c0
    if rows * cols <= 1:
        return [(r0, r1, c0, c1), (r1, r1, c1, c1)]  # a pixel (or nothing) and an empty region
    theta_mid = math.pi * 0.5 * (r0 + r1) / h
    height = rows * math.pi / h
    width = cols * 2.0 * math.pi / wd * math.sin(theta_mid)
    along_rows = (height >= width and rows > 1) or cols == 1
    block = w[r0:r1, c0:c1]
    marginal = block.sum(axis=1) if along_rows else block.sum(axis=0)
    n = marginal.shape[0]
    total = marginal.sum()
    if total > 0:
        cum = np.cumsum(marginal)[:-1]  # weight before each possible cut 1..n−1
        s = 1 + int(np.argmin(np.abs(2.0 * cum - total)))
    else:
        s = n // 2
    if along_rows:
        return [(r0, r0 + s, c0, c1), (r0 + s, r1, c0, c1)]
    return [(r0, r1, c0, c0 + s), (r0, r1, c0 + s, c1)]


def _region_spread(dirs, weight, labels, directions, energy) -> np.ndarray:
    """(K, 3, 3) angular second moment of each region about its light (``EnvironmentLights.spread``).

    ``dirs`` (H, W, 3) pixel-centre directions, ``weight`` (H, W) energy per pixel, ``labels``
    (H·W,) region of each pixel, ``directions`` (K, 3) the lights, ``energy`` (K,) the regions'
    weights. A region without energy gets 0 (its light carries none). NumPy, float64."""
    h, wd = weight.shape
    k = directions.shape[0]
    theta = np.pi * (np.arange(h) + 0.5) / h
    phi = 2.0 * np.pi * (np.arange(wd) + 0.5) / wd
    ct, st = np.cos(theta)[:, None], np.sin(theta)[:, None]
    cp, sp = np.cos(phi)[None, :], np.sin(phi)[None, :]
    # unit tangents along θ and φ at each pixel centre, and each pixel's variance along them
    e_t = np.stack(np.broadcast_arrays(ct * cp, -st, -ct * sp), -1).reshape(-1, 3)
    e_p = np.broadcast_to(np.stack([-sp, np.zeros_like(sp), -cp], -1), (h, wd, 3)).reshape(-1, 3)
    var_t = np.full(h * wd, (np.pi / h) ** 2 / 12.0)
    var_p = np.broadcast_to((2.0 * np.pi / wd * st) ** 2 / 12.0, (h, wd)).reshape(-1)
    w = weight.reshape(-1)
    on = w > 0
    d, lab, w = dirs.reshape(-1, 3)[on], labels[on], w[on]
    light = directions[lab]
    delta = d - light
    delta -= np.sum(delta * light, -1, keepdims=True) * light
    second = (
        delta[:, :, None] * delta[:, None, :]
        + var_t[on, None, None] * (e_t[on, :, None] * e_t[on, None, :])
        + var_p[on, None, None] * (e_p[on, :, None] * e_p[on, None, :])
    )
    out = np.zeros((k, 3, 3))
    np.add.at(out, lab, second * w[:, None, None])
    return out / np.maximum(energy, 1e-300)[:, None, None]


def split_environment(
    env: Environment, count: int, threshold: float = Method.environment_threshold
) -> tuple[Environment, EnvironmentLights]:
    """Split a lat-long environment into a clamped rest and ``count`` distant lights (module docstring).

    Args:
        env: an "hdr" :class:`~jshadow.entities.Environment` with a concrete image (its radiance
            may be traced: the parts are linear in it).
        count: K, the number of lights (a power of two); fans of ``min(K, MAX_FAN)`` lights.
        threshold: τ over the map's mean luminance (solid-angle weighted; luminance = the mean of
            the three channels, before ``env.radiance``); the excess of each pixel over τ, with its
            colour, is the bright part. Must be > 0. Default: the scene method's default
            (:attr:`jshadow.entities.Method.environment_threshold`, 2).

    Returns:
        ``(rest, lights)``: the rest as an "hdr" Environment of the same size and radiance, and the
        bright part as :class:`EnvironmentLights`. ``rest`` plus the lights' image is ``env``.
    """
    if env.kind != "hdr":
        raise ValueError(f"split_environment needs a lat-long ('hdr') environment, got {env.kind!r}")
    if not threshold > 0:
        raise ValueError(f"split_environment: threshold must be > 0, got {threshold}")
    try:
        img_np = np.asarray(env.image, np.float64)
    except jax.errors.TracerArrayConversionError:
        raise ValueError(
            "split_environment decides its regions from the concrete map: the environment's image "
            "(or its rotation) cannot be traced with method.environment_lights > 0"
        ) from None
    h, wd = img_np.shape[:2]
    omega = _solid_angles(h, wd)[:, None]
    lum = img_np.mean(-1)
    tau = float(threshold) * float((lum * omega).sum() / (4.0 * math.pi))
    keep = np.where(lum > tau, tau / np.where(lum > tau, lum, 1.0), 1.0)  # rest = img · keep
    labels = median_cut(np.maximum(lum - tau, 0.0) * omega, count)
    k = int(count)
    fan = min(k, MAX_FAN)

    # directions: energy centroids (concrete, from the luminance excess), empty regions their middle
    dirs = _np_latlong_dirs((np.arange(wd) + 0.5) / wd, (np.arange(h) + 0.5) / h)  # (H, W, 3)
    wgt = (np.maximum(lum - tau, 0.0) * omega).reshape(-1)
    flat = labels.reshape(-1)
    sums = np.zeros((k, 3))
    np.add.at(sums, flat, dirs.reshape(-1, 3) * wgt[:, None])
    energy_l = np.bincount(flat, weights=wgt, minlength=k)
    for j in np.nonzero(energy_l <= 0)[0]:
        sums[j] = dirs.reshape(-1, 3)[flat == j].sum(0) if np.any(flat == j) else (0.0, 1.0, 0.0)
    directions = sums / np.maximum(np.linalg.norm(sums, axis=-1, keepdims=True), 1e-300)
    spread = _region_spread(dirs, wgt.reshape(h, wd), flat, directions, energy_l)
    fan_sums = (directions * energy_l[:, None]).reshape(k // fan, fan, 3).sum(1)
    fan_sums = np.where(
        np.linalg.norm(fan_sums, axis=-1, keepdims=True) > 0,
        fan_sums,
        directions.reshape(k // fan, fan, 3)[:, 0],
    )
    axes = fan_sums / np.linalg.norm(fan_sums, axis=-1, keepdims=True)

    image = jnp.asarray(env.image)
    dtype = image.dtype
    keep_j = jnp.asarray(keep[..., None], dtype)
    rest = Environment(radiance=env.radiance, image=image * keep_j, kind="hdr")
    bright_img = image * (1.0 - keep_j)
    bright = Environment(radiance=env.radiance, image=bright_img, kind="hdr")
    per_pixel = (bright_img * jnp.asarray(omega[..., None], dtype)).reshape(-1, 3)
    energy = jax.ops.segment_sum(per_pixel, jnp.asarray(flat), num_segments=k) * jnp.asarray(env.radiance)
    lights = EnvironmentLights(
        directions=jnp.asarray(directions, dtype),
        energy=energy.astype(dtype),
        axes=jnp.asarray(axes, dtype),
        unoccluded=environment_irradiance_map(bright),
        spread=jnp.asarray(spread, dtype),
        fan=fan,
    )
    return rest, lights
