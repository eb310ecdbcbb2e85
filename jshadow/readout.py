"""Shading read out of the field's table: frames whose geometry does not move.

With one BSV occluder, the irradiance at a receiver is a fixed function of a few *linear*
functionals of its world-frame visibility ``v``: ``⟨v, w_c⟩`` for the environment's three colour
channels (``w_c = M_env[c] T``, :func:`jshadow.scene.combine`) and ``⟨v, T ⊛ cap_j⟩`` for each
sphere light j, each then finished by the shading (ratio or product) and the light's colour. The
field itself is linear too (:func:`jshadow.field.bsv_visibility_and_distance`): ``v = R · s`` with
``s`` the trilinear interpolation of the frame's node table (:func:`jshadow.field.field_nodes`) and
``R`` the rotation from the receiver's local frame to the world. So

    ⟨v, w⟩ = ⟨R s, w⟩ = ⟨s, Rᵀ w⟩ = Σ_corners weight · ⟨node_row, Rᵀ w⟩.

Everything but the node table depends on the geometry alone: the angular cell and its weights (the
receiver's direction from the occluder's centre), its distance, the rotation, and the functionals
``w`` (the receiver's normal, the lights' positions, the environment). When those do not change
between frames — receivers that do not move, an occluder that deforms about a fixed bounding-sphere
centre, lights that stay where they are, the deformable-shadow-fields paper's setting (Sec. 4.3) —
they are computed once (:func:`prepare_readout`), and a frame is the node table's GEMM, the bracket
of k = R/d (a deforming occluder's shell radius R changes from pose to pose), four gathered rows
per receiver and ``C`` dot products of n² (:func:`shade_readout`), instead of the angles, the
per-receiver SH rotation and the combination's products. The numbers are those of the
general path up to float rounding (the rotation is applied to the functionals instead of the
visibility; ``tests/test_readout.py``), and the saving is measured in BENCHMARKS.md ("Rendering").

Scope (:func:`readout_unsupported` names what rules it out): exactly one occluder, with a BSV (a
mesh, or a sphere on the "bsv" path); no ray-cast own-vertex rows, occlusion images or environment
lights; lights fixed (the scene's positions cannot be animated); a bounding-sphere centre that stays
where it is (``method.bsv_center = "placed"``, the default, keeps a deforming mesh's; with "box" a
deformation that is not symmetric about the centre moves it, as the airplane's bend does). Only
receivers that do not move are read out: a deforming mesh's own vertices (``self_shadow``) move, and
:class:`jshadow.Renderer` shades them by the general path in the same call. Several occluders
multiply their visibilities (an SH product), which is not linear in each.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from . import sh
from ._numerics import safe_norm
from .entities import Scene
from .field import (
    cell_corners,
    field_bracket,
    field_cells,
    field_nodes,
    read_nodes,
)
from .lights import environment_irradiance, sphere_light_irradiance, sphere_light_sh
from .scaling import MkTable
from .scene import Lighting, _shadow_ratio
from .visibility import BSV

__all__ = ["Readout", "readout_unsupported", "prepare_readout", "shade_readout"]


class Readout(eqx.Module):
    """What a frame of a fixed-geometry scene reads from the field's table (module docstring).

    N receivers, C functionals: the environment's three channels (if any) first, then one per
    sphere light.

    Attributes:
        rows: (4, N) int32 points ``i·P + j`` of the BSV's θ×φ grid at the corners of each
            receiver's cell (:func:`jshadow.field.cell_corners`); the field's pair table holds
            point r's bracket [k_t, k_{t+1}] in row ``r·(K − 1) + t`` (:func:`jshadow.field.field_nodes`).
        weights: (4, N) their bilinear weights.
        inv_d: (N,) 1 / the receiver's distance to the centre (0 at the centre): a deforming
            occluder's shell radius R changes from pose to pose, and with it k = R/d, so the
            bracket in k is found per frame (:func:`jshadow.field.field_bracket`).
        vectors: (C, n², N) the functionals in each receiver's local frame, ``Rᵀ w``.
        near: (C, N) whether the occluder is nearer than the functional's light (always, for the
            environment): where it is not, the occluder does not shadow that light, as in ``combine``.
        unit: (C, N) the functional's value for visibility 1 (where ``near`` is False, and at
            receivers beyond the table's range).
        unoccluded: (C, N) the n-band unoccluded value (the ratio's denominator).
        exact: (C, N) the exact unoccluded irradiance (ratio shading; the unoccluded otherwise).
        colours: (C, 3) the colour each functional's finished value is multiplied by: the unit
            vectors of the three channels, then each light's radiance.
        center: the BSV's bounding-sphere centre (3,) that the rows were computed for.
        ratio: (static) ratio shading (else Zhou et al.'s products, as in ``combine``).
        offset: (N, 3) irradiance added to every frame, or None: the terms of a static scene's
            lights shadowed through the occlusion images, which do not change from frame to frame
            (:class:`jshadow.Renderer` sets it; :func:`prepare_readout` leaves it None).
    """

    rows: Int[Array, "4 N"]
    weights: Float[Array, "4 N"]
    inv_d: Float[Array, " N"]
    vectors: Float[Array, "C n2 N"]
    near: Bool[Array, "C N"]
    unit: Float[Array, "C N"]
    unoccluded: Float[Array, "C N"]
    exact: Float[Array, "C N"]
    colours: Float[Array, "C 3"]
    center: Float[Array, "3"]
    ratio: bool = eqx.field(static=True)
    offset: Float[Array, "N 3"] | None = None


def readout_unsupported(scene: Scene, bsvs, own=None, images=None, env_lights=None) -> str | None:
    """Why a frame of ``scene`` cannot be read out (module docstring), or None if it can.

    ``bsvs`` are the frame's BSVs (None for an analytic sphere), ``own``/``images``/``env_lights``
    the renderer's ray-cast own-vertex rows, occlusion images and environment lights (None when
    unused). The caller compares each frame's BSV centre with the readout's, and reads out only
    receivers that do not move (a deforming mesh's own vertices do)."""
    if len(scene.occluders) != 1:
        return f"{len(scene.occluders)} occluders (the readout takes exactly one)"
    if bsvs[0] is None:
        return "an analytic sphere occluder (no BSV)"
    if own is not None:
        return "ray-cast own-vertex visibility"
    if images is not None or env_lights is not None:
        return "occlusion images or environment lights"
    if scene.method.shading not in ("ratio", "product"):
        return f"shading {scene.method.shading!r}"
    if scene.environment is None and not scene.lights:
        return "no light (the frame is black)"
    return None


def prepare_readout(
    scene: Scene,
    bsv: BSV,
    lighting: Lighting,
    table: MkTable,
    points: Float[Array, "N 3"],
    normals: Float[Array, "N 3"],
    shared: int = 0,
) -> Readout:
    """The :class:`Readout` of receivers ``points``/``normals`` (fixed) for the scene's one occluder,
    whose BSV at any pose has ``bsv``'s centre and grid (its coefficients and shell radius are not
    read). ``lighting`` is :func:`jshadow.scene.scene_lighting`'s, ``table`` the scene's occlusion
    table. The functionals are those :func:`jshadow.scene.combine` forms, per receiver:
    ``M_env[c] T`` for the environment and ``T ⊛ cap_j`` for sphere light j (``T`` the clamped
    cosine about the normal, ``cap_j`` the light's unit-radiance SH). A light counts the occluder
    only at receivers nearer to the occluder's centre than to the light's, as ``combine`` does.
    ``shared`` (static): the first ``shared`` receivers have receiver 0's normal
    (:func:`jshadow.scene.shared_normal_count`), whose product matrix ``P(T)`` is then formed once.
    The products are ``P(T) cap`` (a GEMM with a constant table, :func:`jshadow.sh.product_matrix`),
    not the unrolled triple product, which took 1.4 s of this function's 3.2 s compilation."""
    n = scene.method.sh_bands
    dtype = points.dtype
    ratio = scene.method.shading == "ratio"
    cell, (cp, sp, ct, st), d, inv_d = field_cells(bsv, points)
    rows, weights = cell_corners(cell, bsv.coeffs.shape[0], bsv.coeffs.shape[1])
    t = sh.clamped_cosine(normals, n)  # (N, n²)
    funcs, unocc, exact, colours, dist_l = [], [], [], [], []
    if scene.environment is not None:
        l_env = lighting.env_sh.astype(dtype)  # (n², 3)
        m_env = sh.product_matrix(l_env.T)  # (3, n², n²)
        funcs += list(jnp.einsum("cik,rk->cri", m_env, t))  # 3 × (N, n²)
        u_env = t @ l_env  # n-band unoccluded (N, 3)
        unocc += list(u_env.T)
        ex = environment_irradiance(lighting.env_map, normals).astype(dtype) if ratio else u_env
        exact += list(ex.T)
        colours += list(jnp.eye(3, dtype=dtype))
        dist_l += [jnp.full(d.shape, jnp.inf, dtype)] * 3
    one = jnp.ones((1,), dtype)
    for light in scene.lights:
        cap = sphere_light_sh(light.center, light.radius, one, points, n)[..., 0]  # (N, n²)
        funcs.append(_times_transfer(t, cap, shared))
        u = jnp.sum(t * cap, -1)  # n-band unoccluded
        unocc.append(u)
        if ratio:
            u = sphere_light_irradiance(light.center, light.radius, one, points, normals)[:, 0]
        exact.append(u)
        colours.append(jnp.asarray(light.radiance, dtype))
        dist_l.append(safe_norm(points - light.center))
    if not funcs:
        raise ValueError("prepare_readout: the scene has no light")
    w = jnp.stack(funcs)  # (C, N, n²) world-frame functionals
    light_distance = jnp.stack(dist_l)  # (C, N)

    def rotate(s):
        return sh.rotate_zyz_cs(s, (cp, sp), (ct, st), prepared=True)

    _, pull = jax.vjp(rotate, jnp.zeros_like(t))
    local = jax.vmap(lambda wc: pull(wc)[0])(w)  # Rᵀ w: (C, N, n²), one trace of the transpose
    unit = math.sqrt(4.0 * math.pi)
    return Readout(
        rows=jnp.stack(rows).astype(jnp.int32),
        weights=jnp.stack(weights).astype(bsv.coeffs.dtype),
        inv_d=inv_d,
        vectors=jnp.transpose(local, (0, 2, 1)),
        near=d < light_distance,
        unit=unit * w[..., 0],
        unoccluded=jnp.stack(unocc),
        exact=jnp.stack(exact).astype(dtype),
        colours=jnp.stack(colours),
        center=bsv.center,
        ratio=ratio,
    )


def _times_transfer(t: Float[Array, "N n2"], cap: Float[Array, "N n2"], shared: int) -> Float[Array, "N n2"]:
    """``T ⊛ cap`` per receiver as ``P(T) cap``; one ``P(T₀)`` for the first ``shared`` rows."""
    if not shared:
        return jnp.einsum("rik,rk->ri", sh.product_matrix(t), cap)
    head = cap[:shared] @ sh.product_matrix(t[0]).T
    if shared == t.shape[0]:
        return head
    return jnp.concatenate([head, jnp.einsum("rik,rk->ri", sh.product_matrix(t[shared:]), cap[shared:])])


def shade_readout(
    readout: Readout, bsv: BSV, table: MkTable, n: int, albedo: Float[Array, "3"]
) -> tuple[Float[Array, "N 3"], Float[Array, "N 3"]]:
    """Irradiance and outgoing radiance (N, 3) of the readout's receivers for a pose's ``bsv``
    (same centre and grid as at :func:`prepare_readout`, not checked here; any shell radius), with
    the scene's occlusion ``table`` and ``n`` (static) lighting bands."""
    pairs = field_nodes(bsv, table, n)
    t0, wk, in_range = field_bracket(table, bsv.shell_radius, readout.inv_d)
    rows = [r * (table.ks.shape[0] - 1) + t0 for r in readout.rows]
    s = read_nodes(pairs, rows, readout.weights, wk.astype(pairs.dtype), n)
    q = _dots(s.T, readout.vectors)
    return _finish(readout, jnp.where(in_range & readout.near, q, readout.unit), albedo)


def _dots(s: Float[Array, "n2 N"], vectors: Float[Array, "C n2 N"]) -> Float[Array, "C N"]:
    """``Σ_i s[i] · vectors[:, i]``: C dot products of n² per receiver, unrolled over n²
    (an einsum of (N, n²)·(N, n², C) was 2.5× slower on XLA:CPU in a throwaway timing)."""
    q = s[0] * vectors[:, 0]
    for i in range(1, s.shape[0]):
        q = q + s[i] * vectors[:, i]
    return q


def _finish(
    readout: Readout, q: Float[Array, "C N"], albedo
) -> tuple[Float[Array, "N 3"], Float[Array, "N 3"]]:
    """The functionals' values → irradiance and radiance (N, 3), shaded as :func:`jshadow.scene.combine`."""
    q = _shadow_ratio(q, readout.unoccluded, readout.exact) if readout.ratio else q
    e = q.T @ readout.colours  # (N, 3)
    if readout.offset is not None:
        e = e + readout.offset
    return e, e * (albedo / math.pi)
