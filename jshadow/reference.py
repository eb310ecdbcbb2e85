"""Monte Carlo ground truth: irradiance at every receiver with exact visibility.

``E(x) = ∫ L(ω) V(x, ω) max(0, n·ω) dω`` is estimated independently of the shadow-field code (this
module never imports :mod:`jshadow.scaling`, :mod:`jshadow.scene`, :mod:`jshadow.lights` or the SH
package): visibility is exact any-hit ray casting (:mod:`jshadow.visibility._raycast`) against every
occluder — spheres analytically, meshes triangle by triangle at the frame's deformation.

Estimators, per receiver and per sample (one sample of each strategy):

* Environment ("constant", "sky"): cosine-weighted hemisphere sampling, ``π L(ω) V(ω)``.
  "hdr": one cosine sample and one luminance importance sample of the lat-long map, combined by
  multiple importance sampling (power heuristic, β = 2, by default; Veach 1997).
* Sphere lights: projected-spherical-cap sampling (Peters & Dachsbacher 2019, all three cases),
  ``L_light V(ω) / p⊥(ω)``: zero variance where the light is unoccluded and its cap above the
  horizon. A light ray only counts occluders nearer than the light's surface.

Sphere lights are emitters only, they do **not** occlude: neither the environment nor other lights
are shadowed by them (the shadow-field combination adds each light's shadowed contribution
independently, Zhou et al. 2005 "Precomputed shadow fields", Sec. 5). The environment is infinitely
far: every occluder in a ray's way blocks it.

Receivers are those of :func:`jshadow.entities.receivers_at` (plane receivers, then the deformed
mesh vertices when ``scene.self_shadow``). Self-shadow receivers lie *on* the mesh, so ray origins
are offset along the normal by ``ε = eps(dtype, 100) · scene size`` (about 1.2e-4 of the scene's
extent in float32, 2.2e-13 in float64; :func:`jshadow.entities.surface_offset`, which the shadow
field's own-vertex rays share), and hits closer than ε are ignored. Where the vertex normal
disagrees with an adjacent face (sharp features), rays grazing that face may still be blocked by
it: that is the receiver's own geometry, counted as occlusion.

Randomness: receiver i uses ``fold_in(fold_in(key, i), block)`` for its samples in blocks of 64
(jittered 8×8 strata per strategy by default), so the result depends on ``key`` and ``spp`` but not
on ``chunk``. Mesh visibility is traced only for the rays that can contribute and whose segment
meets the mesh's bounding ball (compacted on the host, power-of-two batches).
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from ._numerics import safe_div, safe_sqrt
from .entities import (
    Environment,
    MeshOccluder,
    Scene,
    SphereOccluder,
    frame_time,
    receivers_at,
    surface_offset,
)
from .sampling import (
    EnvironmentSampler,
    environment_pdf,
    environment_sampler,
    sample_cosine_hemisphere,
    sample_environment,
    sample_projected_cap,
)
from .visibility._raycast import ray_sphere_any_hit, ray_triangle_any_hit

__all__ = ["ReferenceResult", "reference", "reference_irradiance"]

_BLOCK = 64  # samples per receiver per random-number block
_RAYS_PER_CALL = 1 << 16  # default receiver chunk: about this many rays per compiled call


class ReferenceResult(NamedTuple):
    """Output of :func:`reference`; all arrays (N, 3), linear RGB, one row per receiver."""

    points: Float[Array, "N 3"]
    normals: Float[Array, "N 3"]
    irradiance: Float[Array, "N 3"]  # E, W/m² per unit radiance scale
    radiance: Float[Array, "N 3"]  # albedo/π · E (diffuse receivers)
    irradiance_stderr: Float[Array, "N 3"]  # standard error of E from the sample variance


class _Geometry(eqx.Module):
    sphere_centers: Float[Array, "S 3"]
    sphere_radii: Float[Array, " S"]
    meshes: tuple  # ((vertices (V, 3), faces (F, 3)), ...) at the frame's time
    light_centers: Float[Array, "L 3"]
    light_radii: Float[Array, " L"]
    light_radiance: Float[Array, "L 3"]
    environment: Environment | None
    env_sampler: EnvironmentSampler | None
    offset: Float[Array, ""]  # ray-origin offset ε along the normal, and minimum hit distance


def _occluded_spheres(geo: _Geometry, o, d, t_max):
    """Any-hit against the sphere occluders for rays o + t d, ε < t < t_max."""
    hit = jnp.zeros(jnp.broadcast_shapes(o.shape[:-1], d.shape[:-1]), bool)
    for s in range(geo.sphere_radii.shape[0]):
        hit = hit | ray_sphere_any_hit(o, d, geo.sphere_centers[s], geo.sphere_radii[s], geo.offset, t_max)
    return hit


def _occluded(geo: _Geometry, o, d, t_max):
    """Any-hit against all occluders (spheres, then every mesh triangle), inside one jit."""
    hit = _occluded_spheres(geo, o, d, t_max)
    for vertices, faces in geo.meshes:
        hit = hit | ray_triangle_any_hit(o, d, vertices, faces, geo.offset, t_max)
    return hit


def _light_distance(o, d, center, radius):
    """Distance along unit d from o to the near surface of the light (inf if missed)."""
    oc = center - o
    b = jnp.sum(oc * d, axis=-1)
    disc = b * b - (jnp.sum(oc * oc, axis=-1) - radius * radius)
    t = b - safe_sqrt(disc)
    return jnp.where(disc >= 0, jnp.maximum(t, 0.0), jnp.inf)


_SIDE = 8  # _BLOCK = _SIDE² strata of [0, 1)² per strategy
_MIN_BLOCKS = 8  # stratified: estimate the error from the block means when there are this many


def _stratify(keys, u):
    """Jittered strata: in each block, strategy k's 2D numbers cover the _SIDE × _SIDE cells of the
    unit square once each, in an order permuted independently per receiver and strategy (so the
    strategies stay independent of each other). Every u stays uniform on its own: unbiased."""
    n_pairs = u.shape[-1] // 2

    def perms(k):
        ks = jax.random.split(jax.random.fold_in(k, 0x5EED), n_pairs)
        return jax.vmap(lambda kk: jax.random.permutation(kk, _BLOCK))(ks).T  # (B, pairs)

    cell = jax.vmap(perms)(keys)  # (R, B, pairs)
    cx = (cell % _SIDE).astype(u.dtype)
    cy = (cell // _SIDE).astype(u.dtype)
    uu = u[..., : 2 * n_pairs].reshape(*u.shape[:-1], n_pairs, 2)
    out = jnp.stack([(cx + uu[..., 0]) / _SIDE, (cy + uu[..., 1]) / _SIDE], axis=-1)
    return jnp.minimum(out, 1.0 - jnp.finfo(u.dtype).epsneg).reshape(u.shape)


@eqx.filter_jit
def _sample_block(geo: _Geometry, points, normals, ridx, key, block, heuristic_power, stratify):
    """One block of ``_BLOCK`` samples per receiver, every strategy: the rays (origins (R, 1, 3),
    directions (R, B, K, 3), t_max (R, B, K)), the contribution (R, B, K, 3) each ray adds to the
    estimate of E if it is unoccluded, and whether a sphere occluder already blocks it."""
    dtype = points.dtype
    n_lights = geo.light_radii.shape[0]
    env = geo.environment
    use_env = env is not None
    use_mis = geo.env_sampler is not None
    n_u = 2 * n_lights + (2 if use_env else 0) + (2 if use_mis else 0)
    keys = jax.vmap(lambda i: jax.random.fold_in(jax.random.fold_in(key, i), block))(ridx)
    u = jax.vmap(lambda k: jax.random.uniform(k, (_BLOCK, max(n_u, 1)), dtype))(keys)  # (R, B, n_u)
    if stratify and n_u > 0:
        u = _stratify(keys, u)
    p = points[:, None, :]
    n = normals[:, None, :]
    o = p + geo.offset * n  # (R, 1, 3)
    dirs, tmax, contrib = [], [], []
    col = 0
    if use_env:
        cs = sample_cosine_hemisphere(u[..., col : col + 2], n)
        col += 2
        lc = env.radiance_at(cs.direction)
        if use_mis:
            es = sample_environment(geo.env_sampler, u[..., col : col + 2])
            col += 2
            cos_e = jnp.maximum(jnp.sum(es.direction * n, axis=-1), 0.0)
            le = jnp.where(((cos_e > 0) & es.valid)[..., None], env.radiance_at(es.direction), 0.0)
            pc_c, pe_c = cs.pdf, environment_pdf(geo.env_sampler, cs.direction)
            pc_e, pe_e = cos_e / jnp.pi, es.pdf
            b = heuristic_power
            w_c = safe_div(pc_c**b, pc_c**b + pe_c**b)
            w_e = safe_div(pe_e**b, pc_e**b + pe_e**b)
            # cosine strategy: L V cos / p_c = π L V (p_c > 0 on the sampled hemisphere)
            dirs += [cs.direction, es.direction]
            contrib += [(w_c * jnp.pi)[..., None] * lc, (w_e * safe_div(cos_e, pe_e))[..., None] * le]
            tmax += [jnp.full(cs.pdf.shape, jnp.inf, dtype)] * 2
        else:
            dirs.append(cs.direction)
            contrib.append(jnp.pi * lc)
            tmax.append(jnp.full(cs.pdf.shape, jnp.inf, dtype))
    for li in range(n_lights):
        center, radius = geo.light_centers[li], geo.light_radii[li]
        ls = sample_projected_cap(u[..., col : col + 2], n, center - p, radius)
        col += 2
        w = jnp.where(ls.valid, safe_div(1.0, ls.pdf_proj), 0.0)  # L V max(0, n·ω) / p_ω = L V / p⊥
        dirs.append(ls.direction)
        contrib.append(w[..., None] * geo.light_radiance[li])
        tmax.append(_light_distance(o, ls.direction, center, radius))
    if not dirs:
        shape = (points.shape[0], _BLOCK, 0)
        return o, jnp.zeros((*shape, 3), dtype), jnp.zeros(shape, dtype), jnp.zeros((*shape, 3), dtype), None
    dirs = jnp.stack(dirs, axis=2)
    tmax = jnp.stack(tmax, axis=2)
    contrib = jnp.stack(contrib, axis=2)
    blocked = _occluded_spheres(geo, o[:, :, None, :], dirs, tmax)
    return o, dirs, tmax, contrib, blocked


_trace_meshes = jax.jit(ray_triangle_any_hit)


def _bucket(m: int) -> int:
    """Padded ray count: a power of two ≥ 1024 (few distinct shapes, few compilations)."""
    return max(1024, 1 << (m - 1).bit_length())


def _trace_culled(meshes_host, vertices_faces, origins, dirs, tmax, offset, todo):
    """Mesh any-hit for the rays flagged in ``todo`` (numpy bool), after culling by each mesh's
    bounding ball: a ray segment that misses the ball cannot hit the mesh. The candidate rays are
    compacted on the host and traced in power-of-two batches by ``ray_triangle_any_hit``."""
    hit = np.zeros(todo.shape, bool)
    for (center, radius), (vertices, faces) in zip(meshes_host, vertices_faces, strict=True):
        oc = center - origins
        t_closest = np.clip(np.sum(oc * dirs, axis=-1), offset, tmax)
        gap = origins + t_closest[..., None] * dirs - center
        near = np.sum(gap * gap, axis=-1) <= (radius * (1.0 + 1e-4) + offset) ** 2
        idx = np.flatnonzero(todo & ~hit & near)
        if idx.size == 0:
            continue
        m = _bucket(idx.size)
        pad = np.concatenate([idx, np.full(m - idx.size, idx[0])])
        res = _trace_meshes(
            jnp.asarray(origins.reshape(-1, 3)[pad]),
            jnp.asarray(dirs.reshape(-1, 3)[pad]),
            vertices,
            faces,
            jnp.asarray(offset, vertices.dtype),
            jnp.asarray(tmax.reshape(-1)[pad]),
        )
        flat = hit.reshape(-1)
        flat[idx] |= np.asarray(res)[: idx.size]
    return hit


def _visible(geo: _Geometry, meshes_host, origins, dirs, tmax, blocked, contrib):
    """Visibility (numpy bool, shape of ``tmax``) of the rays that can contribute."""
    dtype = np.dtype(dirs.dtype)
    origins = np.broadcast_to(np.asarray(origins), dirs.shape).astype(dtype)
    dirs, tmax = np.asarray(dirs), np.asarray(tmax)
    todo = ~np.asarray(blocked) & np.any(np.asarray(contrib) != 0, axis=-1)
    if geo.meshes:
        todo &= ~_trace_culled(meshes_host, geo.meshes, origins, dirs, tmax, float(geo.offset), todo)
    return todo


def reference(
    scene: Scene,
    spp: int,
    key: PRNGKeyArray,
    frame: int = 0,
    chunk: int | None = None,
    progress: bool = False,
    *,
    heuristic: str = "power",
    stratify: bool = True,
) -> ReferenceResult:
    """Monte Carlo irradiance and radiance at every receiver of ``scene`` at ``frame``.

    Args:
        scene: the scene (any occluders, sphere lights, optional environment).
        spp: samples per receiver and per strategy (≥ 1; the standard error needs ≥ 2).
        key: JAX PRNG key; the result is deterministic for (key, spp), whatever ``chunk``.
        frame: animation frame; mesh occluders are deformed at ``frame_time(frame, n_frames)``.
        chunk: receivers per compiled call (memory bound ~ chunk · 64 · rays · 3 floats); default
            aims at about 65k rays per call.
        progress: show a ``tqdm`` progress bar.
        heuristic: "power" (β = 2) or "balance", for the MIS of "hdr" environments.
        stratify: jittered 8×8 strata per block of 64 samples and per strategy (default). The
            standard error then comes from the spread of the (independent) block means when spp
            is a multiple of 64 and at least 512; otherwise from the per-sample variance, which for
            stratified samples is an upper bound in expectation (conservative).
            ``stratify=False`` draws independent samples (per-sample variance, exact).

    Returns:
        :class:`ReferenceResult` with ``points``, ``normals``, ``irradiance``, ``radiance``
        (albedo/π · E) and ``irradiance_stderr`` (see ``stratify``; 0 if spp = 1), all (N, 3).

    Limitations: not differentiable (binary visibility); cost is brute force, rays × triangles.
    Sphere lights do not occlude (see the module docstring).
    """
    if not (isinstance(spp, int | np.integer) and spp >= 1):
        raise ValueError(f"spp must be a positive integer, got {spp!r}")
    if chunk is not None and not (isinstance(chunk, int | np.integer) and chunk >= 1):
        raise ValueError(f"chunk must be a positive integer or None, got {chunk!r}")
    if not isinstance(stratify, bool):
        raise ValueError(f"stratify must be True or False, got {stratify!r}")
    if heuristic not in ("power", "balance"):
        raise ValueError(f"heuristic must be 'power' or 'balance', got {heuristic!r}")
    dtype = scene.dtype
    t = frame_time(frame, scene.n_frames)
    points, normals = receivers_at(scene, frame)
    points, normals = jnp.asarray(points, dtype), jnp.asarray(normals, dtype)
    spheres = [o for o in scene.occluders if isinstance(o, SphereOccluder)]
    meshes = tuple(
        (jnp.asarray(o.vertices(t), dtype), jnp.asarray(o.faces, jnp.int32))
        for o in scene.occluders
        if isinstance(o, MeshOccluder)
    )
    unknown = [type(o).__name__ for o in scene.occluders if not isinstance(o, SphereOccluder | MeshOccluder)]
    if unknown:
        raise ValueError(f"scene.occluders may hold SphereOccluder and MeshOccluder only, got {unknown}")
    env = scene.environment
    if env is not None:
        env = Environment(
            jnp.asarray(env.radiance, dtype),
            None if env.image is None else jnp.asarray(env.image, dtype),
            env.kind,
        )

    def stack3(xs):
        return jnp.asarray(np.reshape([np.asarray(x) for x in xs], (-1, 3)), dtype)

    geo = _Geometry(
        sphere_centers=stack3(s.center for s in spheres),
        sphere_radii=jnp.asarray([float(s.radius) for s in spheres], dtype).reshape(-1),
        meshes=meshes,
        light_centers=stack3(x.center for x in scene.lights),
        light_radii=jnp.asarray([float(x.radius) for x in scene.lights], dtype).reshape(-1),
        light_radiance=jnp.asarray(
            np.reshape([np.asarray(x.radiance) for x in scene.lights], (-1, 3)), dtype
        ),
        environment=env,
        env_sampler=environment_sampler(env) if env is not None and env.kind == "hdr" else None,
        offset=jnp.asarray(surface_offset(scene, t, points), dtype),
    )
    meshes_host = []
    for vertices, _ in meshes:
        v = np.asarray(vertices, np.float64)
        center = 0.5 * (v.min(axis=0) + v.max(axis=0))
        meshes_host.append((center, float(np.sqrt(np.max(np.sum((v - center) ** 2, axis=-1))))))
    n_recv = points.shape[0]
    n_rays = max(len(scene.lights) + (0 if env is None else 1 + (env.kind == "hdr")), 1)
    if chunk is None:
        chunk = max(1, min(n_recv, _RAYS_PER_CALL // (_BLOCK * n_rays)))
    chunk = min(chunk, max(n_recv, 1))
    n_blocks = -(-spp // _BLOCK)
    n_chunks = -(-n_recv // chunk)
    power = 2.0 if heuristic == "power" else 1.0
    mean = np.zeros((n_recv, 3))
    m2 = np.zeros((n_recv, 3))
    m2_blocks = np.zeros((n_recv, 3))
    by_blocks = stratify and spp % _BLOCK == 0 and n_blocks >= _MIN_BLOCKS
    from tqdm.auto import tqdm

    bar = tqdm(total=n_chunks * n_blocks, disable=not progress, desc="reference", unit="call")
    for c in range(n_chunks):
        lo = c * chunk
        ridx = jnp.minimum(jnp.arange(lo, lo + chunk, dtype=jnp.int32), n_recv - 1)  # pad by repeating
        pts, nrm = points[ridx], normals[ridx]
        m_acc = np.zeros((chunk, 3))
        s_acc = np.zeros((chunk, 3))
        n_acc = 0.0
        bmean = np.zeros((chunk, 3))  # Welford over the block means (stratified error estimate)
        bm2_acc = np.zeros((chunk, 3))
        for b in range(n_blocks):
            o, dirs, tmax, contrib, blocked = _sample_block(
                geo, pts, nrm, ridx, key, jnp.asarray(b, jnp.int32), power, stratify
            )
            if dirs.shape[2] == 0:
                value = np.zeros((chunk, _BLOCK, 3))
            else:
                vis = _visible(geo, meshes_host, o[:, :, None, :], dirs, tmax, blocked, contrib)
                value = np.sum(np.where(vis[..., None], np.asarray(contrib, np.float64), 0.0), axis=2)
            live = (b * _BLOCK + np.arange(_BLOCK)) < spp  # samples beyond spp are masked
            bn = float(np.sum(live))
            bm = np.mean(value[:, live], axis=1)
            bm2 = np.sum((value[:, live] - bm[:, None, :]) ** 2, axis=1)
            # Chan et al.: merge (n_acc, m_acc, s_acc) with the block's (bn, bm, bm2)
            tot = n_acc + bn
            delta = bm - m_acc
            m_acc = m_acc + delta * (bn / tot)
            s_acc = s_acc + bm2 + delta**2 * (n_acc * bn / tot)
            n_acc = tot
            step = bm - bmean
            bmean = bmean + step / (b + 1)
            bm2_acc = bm2_acc + step * (bm - bmean)
            bar.update(1)
        k = min(chunk, n_recv - lo)
        mean[lo : lo + k] = m_acc[:k]
        m2[lo : lo + k] = s_acc[:k]
        m2_blocks[lo : lo + k] = bm2_acc[:k]
    bar.close()
    if by_blocks:  # stratified, whole blocks: the block means are i.i.d.
        stderr = np.sqrt(np.maximum(m2_blocks, 0.0) / (n_blocks - 1) / n_blocks)
    else:  # i.i.d. samples (exact), or stratified samples (conservative)
        var = m2 / (spp - 1) if spp > 1 else np.zeros_like(m2)
        stderr = np.sqrt(np.maximum(var, 0.0) / spp)
    irradiance = jnp.asarray(mean, dtype)
    albedo = jnp.asarray(scene.receivers.albedo, dtype)
    return ReferenceResult(
        points=points,
        normals=normals,
        irradiance=irradiance,
        radiance=albedo / jnp.pi * irradiance,
        irradiance_stderr=jnp.asarray(stderr, dtype),
    )


def reference_irradiance(scene: Scene, spp: int, key: PRNGKeyArray, frame: int = 0) -> Float[Array, "N 3"]:
    """Shortcut: the irradiance (N, 3) of :func:`reference`."""
    return reference(scene, spp, key, frame).irradiance
