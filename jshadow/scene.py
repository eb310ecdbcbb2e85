"""Combination of shadow fields at receivers (Zhou et al. 2005, Sec. 5; DESIGN.md §1.5).

At every receiver x with normal n and albedo ρ:

* every occluder j contributes a visibility function V_j (SH, world frame, :mod:`jshadow.field`);
* the environment lies behind every occluder: ``E_env = ∫ L_env · Π_j V_j · max(0, n·ω) dω``;
* a sphere light l is shadowed only by the occluders whose centres are nearer to x than the light's
  centre: ``E_l = ∫ L_l · Π_{j: d_j < d_l} V_j · max(0, n·ω) dω`` (sorting the entities by distance
  and multiplying front to back is equivalent to this mask; the mask keeps shapes static);
* ``E = E_env + Σ_l E_l`` and the outgoing radiance of the diffuse receiver is ``ρ/π · E``.

Products of SH functions are SH triple products truncated to n bands; the final integral
``∫ V · (L·T)`` is a double product of V with the n-band projection of L·T, which is exact for an
n-band V (so one occluder under the environment costs one product L·T per receiver and one dot).
What a scene does not need is skipped at trace time: no environment, no lights, no occluders,
a single occluder (no visibility products); and at run time a BSV occluder that no receiver is
within range of (visibility 1 everywhere: its field, and in the renderer's chain its product, are
not evaluated; :func:`_reaches`). Receivers out of range of an occluder that reaches others get
visibility 1 from the field's range test; skipping them one by one cost more than it saved on
XLA:CPU (BENCHMARKS.md, "Many occluders").

Sphere lights do not occlude (they are emitters only), matching :mod:`jshadow.reference`.
"""

from __future__ import annotations

import functools
import hashlib
import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from . import sh
from ._active import over_active
from ._numerics import safe_norm, safe_normalize, safe_sqrt
from .entities import (
    MeshOccluder,
    Scene,
    SphereOccluder,
    frame_time,
    receivers_at_time,
    remembered_rest_shape,
    surface_offset,
)
from .envlights import EnvironmentLights, split_environment
from .field import bsv_visibility_and_distance, sphere_light_blocked, sphere_visibility_sh, unit_visibility
from .geometry import (
    bounding_sphere,
    cone_may_meet_sphere,
    fan_may_meet_sphere,
    point_mesh_distance2,
    with_center_anchors,
)
from .lights import (
    IrradianceMap,
    environment_irradiance,
    environment_irradiance_map,
    environment_sh,
    sphere_light_dot,
    sphere_light_irradiance,
    sphere_light_sh,
)
from .sampling import stratified_cone_components
from .scaling import MkTable, mk_table
from .visibility import (
    BSV,
    LampImages,
    OcclusionImages,
    _own_exact,
    bsv_and_coverage_edgescan_diff,
    bsv_mesh,
    bsv_mesh_diff,
    bsv_mesh_edgescan,
    bsv_mesh_edgescan_diff,
    bsv_mesh_edgescan_of,
    bsv_mesh_edgescan_scan_diff,
    bsv_silhouette_counts,
    bsv_sphere,
    bsv_with_occlusion_images,
    coverage_sh,
    edgescan_grad_slots,
    edgescan_scan_slots,
    edgescan_slots,
    halfspace_visibility_sh,
    hemisphere_fan_any_hit,
    image_fan_visibility_components,
    image_reach,
    is_closed_manifold,
    lamp_images,
    lamp_visibility,
    occlusion_images,
    ray_fan_any_hit,
    ray_sphere_any_hit,
    ring_faces,
    scan_coverage,
    vertex_lamp_visibility,
    vertex_transfer_and_lamps,
    vertex_transfer_maps,
    vertex_visibility_sh,
)
from .visibility._edgescan import _traced_default_slots, always, staged
from .visibility._own import lamp_fans, lifted_origins

__all__ = [
    "RenderResult",
    "grow_slots",
    "occlusion_table",
    "scene_bsvs",
    "occluder_bsv",
    "mesh_bsv",
    "occluder_visibilities",
    "uses_visibility_chain",
    "visibility_chain",
    "uses_self_rays",
    "casts_own_sh",
    "self_visibility_owners",
    "uses_contact",
    "contact_rows_at_time",
    "contact_ray_tests",
    "CONTACT_REACH",
    "CONTACT_GRID",
    "CONTACT_GRID_DIM",
    "CONTACT_SH_SHARE",
    "contact_grid",
    "CONTACT_LARGE_FACE",
    "CONTACT_NO_DERIVATIVE",
    "occluder_own_visibility",
    "clear_pose_caches",
    "self_visibility_rows",
    "occluder_own_casts",
    "occluder_own_light_visibility",
    "self_light_rows",
    "own_rows_at_time",
    "assemble_own_rows",
    "uses_environment_lights",
    "uses_light_images",
    "occluder_images",
    "occluder_bsv_and_images",
    "scene_images",
    "scene_bsvs_and_images",
    "light_visible_fractions",
    "environment_visible_fraction",
    "image_fractions",
    "Lighting",
    "scene_lighting",
    "combine",
    "shared_normal_count",
    "render",
    "render_at",
]


class RenderResult(eqx.Module):
    """Per-receiver output of one frame: all arrays (N, 3)."""

    points: Float[Array, "N 3"]
    normals: Float[Array, "N 3"]
    irradiance: Float[Array, "N 3"]  # E, W/m² per unit radiance scale (linear RGB)
    radiance: Float[Array, "N 3"]  # outgoing radiance of the diffuse receiver: albedo/π · E


@functools.lru_cache(maxsize=16)
def _table(n, num, d_min, d_max, model, dtype) -> MkTable:
    with jax.ensure_compile_time_eval():  # concrete arrays even when first called under a trace
        return mk_table(n=n, num=num, d_min=d_min, d_max=d_max, kind="occlusion", model=model, dtype=dtype)


def occlusion_table(scene: Scene) -> MkTable:
    """The occlusion M_k table of the scene's method (built once per method, then cached)."""
    m = scene.method
    return _table(m.field_bands, m.radial_samples, m.d_range[0], m.d_range[1], m.model, scene.dtype)


def scene_bsvs(scene: Scene, t, sphere_path: str = "analytic") -> tuple[BSV | None, ...]:
    """BSV of every occluder at animation time t (None for spheres on the analytic path).

    ``sphere_path="bsv"`` sends sphere occluders through the BSV + M_k path as well (for comparing
    the two); meshes always use it.
    """
    return tuple(occluder_bsv(occ, t, scene, sphere_path) for occ in scene.occluders)


def occluder_bsv(
    occ, t, scene: Scene, sphere_path: str = "analytic", differentiable: bool = True
) -> BSV | None:
    """BSV of one occluder at time t (see :func:`scene_bsvs`; ``differentiable`` see :func:`mesh_bsv`)."""
    m = scene.method
    if isinstance(occ, SphereOccluder):
        if sphere_path == "analytic":
            return None
        if sphere_path != "bsv":
            raise ValueError(f"sphere_path must be 'analytic' or 'bsv', got {sphere_path!r}")
        return bsv_sphere(occ.center, occ.radius, n=m.field_bands, grid=m.bsv_grid, shell=m.shell)
    if isinstance(occ, MeshOccluder):
        return mesh_bsv(occ, t, scene, differentiable)
    raise TypeError(f"unknown occluder type {type(occ).__name__}")


@eqx.filter_jit
def _vertices_at(occ: MeshOccluder, t) -> Float[Array, "V 3"]:
    """World vertices at time t as one compiled call (eagerly, a deformation is many small dispatches)."""
    return occ.vertices(t)


def mesh_bsv(occ: MeshOccluder, t, scene: Scene, differentiable: bool = True) -> BSV:
    """BSV of one mesh occluder at time t (deformed vertices, per-frame bounding sphere).

    With ``differentiable`` (and concrete faces, the usual case) the coefficients carry the
    silhouette-edge derivative of :func:`jshadow.visibility.bsv_mesh_diff`, so ``jax.grad`` /
    ``jax.jvp`` with respect to vertices and deformation parameters are visibility-correct; the
    forward value is exactly that of :func:`jshadow.visibility.bsv_mesh` with the method's options.
    The centre and radius of the bounding sphere are differentiable either way. Pass
    ``differentiable=False`` when no derivative is wanted: the sampler then runs directly, outside
    the custom-derivative wrapper (which traces its primal and so loses the edge-scan's staging), and
    for a concrete occluder sampled by the edge-scan the deformation and the BSV are one compiled call
    (:func:`jshadow.visibility.bsv_mesh_edgescan_of`; instead of several dispatches and eager
    operations: on two CPU cores the BSV stage took 0.88–0.96× the time, whole frames 0.91–0.95×:
    airplane, egg, animated bunny, in-process A/B, alternating frames; BENCHMARKS.md).
    """
    m = scene.method
    t = jnp.asarray(t, occ.unit_vertices.dtype)  # an array: one compile for all t
    if m.bsv_images == "coverage":
        v = _sampler_vertices(occ, t, m)
        return _coverage_bsv(occ, v, _coverage(occ, v, m), m)
    kw = dict(n=m.field_bands, grid=m.bsv_grid, directions=m.directions, shell=m.shell)
    faces = _concrete(occ.faces)
    traced = any(isinstance(x, jax.core.Tracer) for x in (occ.unit_vertices, t))
    if not differentiable and faces is not None and not traced and _uses_edgescan(m, faces):
        anchored = _placed(occ, m)
        shape = occ.unit_vertices.shape[0] + (6 if anchored else 0), occ.unit_vertices.dtype
        return bsv_mesh_edgescan_of(
            _deformed_anchored if anchored else _deformed, (occ, t), faces, *shape, **kw
        )
    v = _sampler_vertices(occ, t, m)
    if not differentiable:
        return _with_center_motion(occ, bsv_mesh(v, occ.faces, method=m.bsv_method, **kw))
    center, radius = _bsv_sphere(occ, v, m)
    coeffs = _differentiable_coeffs(occ, v, faces, m, kw)
    return BSV(coeffs=coeffs, center=center, radius=radius, shell_radius=m.shell * radius)


def _bsv_sphere(occ: MeshOccluder, v, m):
    """The bounding sphere (centre, radius) of the sampler's input vertices ``v``
    (:func:`_sampler_vertices`), the centre carrying the occluder centre's derivative. Where it is
    placed (:func:`_placed`) the centre is ``occ.center`` itself: the same centre (up to one
    rounding), but with no dependence on the vertices — the box centre of the anchored vertices has
    an identically zero vertex derivative that reverse mode would still carry through every
    receiver's direction and SH rotation."""
    center, radius = bounding_sphere(v)
    if _placed(occ, m):
        return jnp.asarray(occ.center, v.dtype), radius
    return center + _center_motion(occ, v.dtype), radius


def _placed(occ: MeshOccluder, m) -> bool:
    """Whether this occluder's BSV is sampled about its placed centre (a deforming mesh with
    ``method.bsv_center = "placed"``)."""
    return m.bsv_center == "placed" and occ.deforms


def bsv_input_vertices(occ: MeshOccluder, v: Float[Array, "V 3"], m) -> Float[Array, "W 3"]:
    """The vertices a BSV sampler is given for the occluder's world vertices ``v`` (V, 3).

    ``v`` itself (W = V), whose box-centred sphere the samplers take, except for a deforming mesh
    with ``method.bsv_center = "placed"``: then ``v`` and six anchors (W = V + 6,
    :func:`jshadow.geometry.with_center_anchors`), which centre that sphere on ``occ.center``.
    The bounding sphere of the result (:func:`jshadow.geometry.bounding_sphere`) is the BSV's.
    """
    return with_center_anchors(v, occ.center) if _placed(occ, m) else v


def _deformed(occ: MeshOccluder, t) -> Float[Array, "V 3"]:
    """World vertices at time t (the function :func:`mesh_bsv` compiles together with the BSV)."""
    return occ.vertices(t)


def _deformed_anchored(occ: MeshOccluder, t) -> Float[Array, "V+6 3"]:
    """:func:`_deformed` with the anchors of the placed centre (:func:`bsv_input_vertices`)."""
    return with_center_anchors(occ.vertices(t), occ.center)


def _sampler_vertices(occ: MeshOccluder, t, m) -> Float[Array, "W 3"]:
    """What the BSV's samplers (coefficients, occlusion and coverage images) are given at time t:
    :func:`bsv_input_vertices` of the world vertices, with the occluder's centre held constant for
    differentiation (``lax.stop_gradient``; W = V or V + 6).

    The samplers' outputs do not change under a translation (they sample on a shell about the
    input's own sphere), so the centre's derivative (moving the occluder) would reach their
    derivative machinery — the silhouette terms of the BSV's — only to give zero; held constant, it
    does not enter them at all, and the values are bitwise those of the world vertices. The
    sphere's centre gets its derivative back in :func:`_bsv_sphere` and :func:`_with_center_motion`
    (BENCHMARKS.md, "Every parameter's frame gradient, and moving an occluder": the position's
    frame gradient 2.5–7× cheaper)."""
    c = jax.lax.stop_gradient(occ.center)
    v = c + occ.radius * occ.unit_pose(t)  # occ.vertices(t), bitwise
    return with_center_anchors(v, c) if _placed(occ, m) else v


def _center_motion(occ: MeshOccluder, dtype) -> Float[Array, "3"]:
    """``occ.center - stop_gradient(occ.center)``: zero, with the centre's derivative, which a
    sphere found from :func:`_sampler_vertices` adds back to its centre."""
    c = jnp.asarray(occ.center, dtype)
    return c - jax.lax.stop_gradient(c)


def _with_center_motion(occ: MeshOccluder, obj):
    """A sampler's BSV or occlusion images of :func:`_sampler_vertices`, its centre carrying the
    occluder centre's derivative again (the values are unchanged)."""
    return eqx.tree_at(lambda o: o.center, obj, obj.center + _center_motion(occ, obj.center.dtype))


def _differentiable_coeffs(occ: MeshOccluder, v, faces: np.ndarray | None, m, kw):
    """BSV coefficients of ``v`` carrying the silhouette derivative that ``m.bsv_gradient`` selects."""
    if faces is None:  # the forward pass works; a derivative would silently miss the silhouette term
        return _no_derivative_guard(lambda x: bsv_mesh(x, occ.faces, method=m.bsv_method, **kw).coeffs, v)
    mode = bsv_gradient_mode(m, faces)
    if mode in ("image", "scanline"):
        if not is_closed_manifold(faces):
            raise ValueError(
                f"method.bsv_gradient = {mode!r} needs the edge-scan sampler, i.e. a closed, consistently "
                "wound manifold mesh; this occluder's mesh is not (use bsv_gradient = 'raycast')"
            )
        # the derivative's sizes are measured when a derivative is traced, not by a forward pass
        es = _edgescan_slots(occ, faces, m)
        if mode == "scanline":
            scan_slots = _scan_grad_slots(occ, faces, m, lazy=True)
            return bsv_mesh_edgescan_scan_diff(v, faces, slots=es, scan_slots=scan_slots, **kw)
        grad_slots = _image_grad_slots(occ, faces, m, lazy=True)
        return bsv_mesh_edgescan_diff(v, faces, slots=es, grad_slots=grad_slots, **kw)

    if _uses_edgescan(m, faces):
        # the edge-scan, as the eager call and the Renderer compute it: bsv_mesh would cast rays
        # under a trace (another quadrature: 0.6 % apart; the bunny's jitted frame 190 ms instead of
        # 6 ms, BENCHMARKS.md). Slots measured on concrete poses; if a traced pose overflows them,
        # that call falls back to the rays instead of raising.
        es = _edgescan_slots(occ, faces, m)

        def forward(x):
            return bsv_mesh_edgescan(x, faces, slots=es, on_overflow="brute", **kw).coeffs

    else:

        def forward(x):
            return bsv_mesh(x, faces, method=m.bsv_method, **kw).coeffs

    return bsv_mesh_diff(v, faces, forward=forward, slots=_slots(occ, faces, m), nodes=8, **kw)


def bsv_gradient_mode(m, faces: np.ndarray) -> str:
    """The silhouette visibility ``m.bsv_gradient`` selects for these faces: "auto" is "image"
    (exact winding number in the edge-scan's image plane, 11–31× faster on whole frames) when the
    forward pass is the edge-scan (shell > 1, closed manifold mesh, ``bsv_method`` not "brute"),
    else "raycast"."""
    if m.bsv_gradient != "auto":
        return m.bsv_gradient
    return "image" if _uses_edgescan(m, faces) else "raycast"


def _uses_edgescan(m, faces: np.ndarray) -> bool:
    """Whether ``bsv_mesh(..., method=m.bsv_method)`` samples these faces with the edge-scan."""
    auto = m.bsv_method == "auto" and m.shell > 1.0 and is_closed_manifold(faces)
    return auto or m.bsv_method == "edgescan"


TRACED_FACES = (
    "mesh faces are traced (the scene was built inside jax.jit/vmap or passed to it as an argument), "
    "so the BSV's silhouette derivative cannot be formed: build the scene outside the transformation "
    "and close over it, keeping only the parameters being differentiated as arguments"
)


def _no_derivative_guard(forward, v, message: str = TRACED_FACES):
    """``forward(v)``, raising ``message`` (default :data:`TRACED_FACES`) if it is differentiated
    with respect to ``v`` (instead of a zero derivative through binary visibility)."""

    @jax.custom_jvp
    def guarded(x):
        return forward(x)

    @guarded.defjvp
    def _jvp(primals, tangents):
        raise ValueError(message)

    return guarded(v)


def _concrete(x):
    """``x`` as a numpy array if it is concrete (not a tracer), else None."""
    try:
        return np.asarray(x)
    except jax.errors.TracerArrayConversionError:
        return None


_SLOTS: dict = {}
_PENDING: dict = {}  # topology -> the lazy measurement of a concrete shape seen with it, not yet run
_REMEASURE: list = []  # non-empty while grow_slots runs: measure again and keep the largest


def _cached_slots(kind: str, occ: MeshOccluder, faces: np.ndarray, m, measure, merge, none, *, lazy=False):
    """Slot sizes measured by ``measure(poses)`` on the occluder's concrete poses (:func:`_poses`),
    cached per rest shape.

    Each topology and configuration also keeps ``merge`` (the largest) of every shape measured with
    it, which a call whose rest pose is traced (fitting per-vertex offsets) reuses. A traced rest
    pose of a topology not measured yet is measured on the last concrete occluder constructed with
    the same faces (:func:`jshadow.entities.remembered_rest_shape`, e.g. ``build_scene``'s), so a
    user's first ``jax.grad`` with respect to the vertices needs no render before it; ``none`` when
    there is none. With ``lazy``, a shape not measured yet gives a zero-argument function that
    measures (eagerly, outside any trace) when called, for sizes that only a derivative needs; a
    traced rest pose of a topology whose concrete shape was seen but not measured gets that shape's
    function.
    """
    topo = (kind, faces.shape, hash(faces.tobytes()), m.bsv_grid, m.directions, m.shell)
    unit = _concrete(occ.unit_vertices)
    if unit is None:
        if lazy and topo not in _SLOTS and topo in _PENDING:
            return _PENDING[topo]
        if topo not in _SLOTS:  # measure on the concrete shape built last with these faces, if any
            seen = remembered_rest_shape(faces)
            if seen is not None and _concrete(seen.unit_vertices) is not None:
                return _cached_slots(kind, seen, faces, m, measure, merge, none, lazy=lazy)
        return _SLOTS.get(topo, none)
    key = (*topo, hash(unit.tobytes()))
    if _REMEASURE:  # grow_slots: measured again on these poses and merged in, if in use
        if key not in _SLOTS and topo not in _SLOTS:
            return none  # not in use for this topology: left to its first use
        with jax.core.eval_context():
            fresh = measure(_poses(occ, unit, m))
        old = _SLOTS.get(key)
        _SLOTS[key] = fresh if old is None else merge(old, fresh)
        _SLOTS[topo] = merge(_SLOTS.get(topo, _SLOTS[key]), _SLOTS[key])
        if _SLOTS[key] != old:
            _REMEASURE.append(kind)
        return _SLOTS[key]
    if key in _SLOTS:
        return _SLOTS[key]
    poses = _poses(occ, unit, m)

    def run():
        if key not in _SLOTS:
            with jax.core.eval_context():
                _SLOTS[key] = measure(poses)
            _SLOTS[topo] = _SLOTS[key] if topo not in _SLOTS else merge(_SLOTS[topo], _SLOTS[key])
        return _SLOTS[key]

    if lazy:
        _PENDING.setdefault(topo, run)
        return run
    return run()


def grow_slots(scene: Scene) -> bool:
    """Measure the static sizes in use for ``scene``'s mesh occluders again, on its poses as they
    are now, and keep the largest of the old and new sizes; True if any grew.

    Sizes are measured on concrete poses (the rest pose and five of the animation). A pose reached
    under a trace (a fitted deformation amount, per-vertex offsets) may need more, and the traced
    call then raises an overflow; :func:`jshadow.optim.fit_params` calls this with the scene at the
    current parameters and traces its step again (with the grown sizes) when that happens.
    ``scene`` must be concrete. Sizes never measured for a topology are left to their first use.
    """
    m = scene.method
    _REMEASURE[:] = [None]  # non-empty: _cached_slots measures again
    try:
        for occ in scene.occluders:
            faces = _concrete(occ.faces) if isinstance(occ, MeshOccluder) else None
            if faces is None or _concrete(occ.unit_vertices) is None:
                continue
            _slots(occ, faces, m)
            _edgescan_slots(occ, faces, m)
            _image_grad_slots(occ, faces, m)
            _scan_grad_slots(occ, faces, m)
        return len(_REMEASURE) > 1
    finally:
        _REMEASURE.clear()


def _poses(occ: MeshOccluder, unit: np.ndarray, m) -> list[np.ndarray]:
    """The rest pose ``unit`` and, if the deformation is concrete (no traced parameter), five poses
    of its animation (t = 0 … 1), as numpy arrays, each as the BSV's sampler is given it
    (:func:`bsv_input_vertices`) but in the unit frame: the sampled images, hence the sizes, do not
    change under a translation or a scale, so a traced centre or radius (moving the occluder) still
    has its animation measured."""
    poses = [unit]
    if occ.deform is None or any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(occ.deform)):
        return poses
    with jax.core.eval_context():  # concrete also while a caller is being traced
        zero = jnp.zeros(3, unit.dtype)
        anchored = _placed(occ, m)  # as the BSV sees them: anchored about the placed centre
        if anchored:
            poses = [np.asarray(with_center_anchors(unit, zero))]
        for t in np.linspace(0.0, 1.0, 5):
            x = occ.deform(jnp.asarray(unit), jnp.asarray(t, unit.dtype))
            poses.append(np.asarray(with_center_anchors(x, zero) if anchored else x))
    return poses


def _slots(occ: MeshOccluder, faces: np.ndarray, m) -> int | None:
    """Silhouette slots per viewpoint for ``bsv_gradient = "raycast"``: 1.5 × the largest count over
    the rest pose and five poses of the animation (:func:`_cached_slots`; an overflow raises when the
    derivative runs); None (every edge: never overflows, slower) if unknown."""

    def measure(poses):
        most = max(
            int(np.asarray(bsv_silhouette_counts(v, faces, grid=m.bsv_grid, shell=m.shell)).max())
            for v in poses
        )
        return int(min(int(1.5 * most) + 8, 3 * faces.shape[0] // 2))

    return _cached_slots("raycast", occ, faces, m, measure, max, None)


def _merge_max(a, b):
    return tuple(max(x, y) for x, y in zip(a, b, strict=True))


def _edgescan_slots(occ: MeshOccluder, faces: np.ndarray, m):
    """Edge-scan slots ``(S, S2, S3, K)`` of the BSV forward pass (1.5 margin): the largest over the
    rest pose and five poses of the animation (:func:`_cached_slots`); None (generous defaults,
    slower under a trace) if no concrete pose of this topology is known. An overflow repairs itself
    on concrete vertices; under a trace the raycast forward falls back to rays
    (:func:`_differentiable_coeffs`) and the image-mode one reruns with 4× the slots."""

    def measure(poses):
        es = [edgescan_slots(v, faces, m.bsv_grid, m.directions, m.shell) for v in poses]
        return tuple(max(x) for x in zip(*es, strict=True))

    return _cached_slots("edgescan", occ, faces, m, measure, _merge_max, None)


def _image_grad_slots(occ: MeshOccluder, faces: np.ndarray, m, lazy: bool = False):
    """Derivative sizes for ``bsv_gradient = "image"`` (:func:`jshadow.visibility.edgescan_grad_slots`,
    1.5 margin): the largest over the rest pose and five poses of the animation where they are
    concrete (the images are scale- and translation-invariant; under a trace an overflow raises),
    see :func:`_cached_slots`; None — generous defaults, slower — if unknown. With ``lazy``, sizes
    not measured yet come as a function that measures them, which the derivative rule calls: a
    forward pass (``jax.jit(render)``) then never compiles the counting passes."""

    def measure(poses):
        grid, shell, directions = m.bsv_grid, m.shell, m.directions
        es = _edgescan_slots(occ, faces, m)  # the largest over the same poses: one compile for all
        gs = [edgescan_grad_slots(v, faces, grid, shell, directions=directions, slots=es) for v in poses]
        return tuple(max(x) for x in zip(*gs, strict=True))

    return _cached_slots("image", occ, faces, m, measure, _merge_max, None, lazy=lazy)


def _scan_grad_slots(occ: MeshOccluder, faces: np.ndarray, m, lazy: bool = False):
    """Derivative sizes for ``bsv_gradient = "scanline"`` (:func:`jshadow.visibility.edgescan_scan_slots`,
    1.5 margin): the largest over the rest pose and five poses of the animation, measured as
    :func:`_image_grad_slots` measures its own (lazily, when a derivative is first traced); None —
    the column slots for the rows and no compaction, slower — if unknown."""

    def measure(poses):
        grid, shell, directions = m.bsv_grid, m.shell, m.directions
        es = _edgescan_slots(occ, faces, m)
        ss = [edgescan_scan_slots(v, faces, grid, directions, shell, slots=es) for v in poses]
        return tuple(max(x) for x in zip(*ss, strict=True))

    return _cached_slots("scanline", occ, faces, m, measure, _merge_max, None, lazy=lazy)


SELF_RAYS_NO_DERIVATIVE = (
    "method.self_visibility = 'rays' (or 'light_rays') casts binary visibility from the occluders' own "
    "vertices, which "
    "has no derivative with respect to those vertices: differentiate with self_visibility = 'field' "
    "(or without self_shadow)"
)


def uses_self_rays(scene: Scene) -> bool:
    """Whether rays are cast from the occluders' own vertices (``self_shadow`` and at least one
    mesh occluder, with ``method.self_visibility = "rays"``, or "light_rays" and
    :func:`uses_environment_lights`): :func:`own_rows_at_time` is then not None."""
    m = scene.method.self_visibility
    return (
        scene.self_shadow
        and any(isinstance(o, MeshOccluder) for o in scene.occluders)
        and (m in ("rays", "maps") or (m == "light_rays" and uses_environment_lights(scene)))
    )


def casts_own_sh(scene: Scene) -> bool:
    """Whether the own vertices' visibility SH is cast (``self_visibility = "rays"``) rather than
    the field's (with "light_rays" only their visibility toward the environment lights is)."""
    return uses_self_rays(scene) and scene.method.self_visibility in ("rays", "maps")


def self_visibility_owners(scene: Scene) -> np.ndarray:
    """(N,) int32 over the receivers of :func:`jshadow.entities.receivers_at_time` (``self_shadow``
    order: the plane's rows, then each mesh occluder's vertices): the index in ``scene.occluders``
    of the occluder whose own vertex the receiver is, −1 for the plane's receivers."""
    rows = [np.full(scene.receivers.points.shape[0], -1, np.int32)]
    for i, occ in enumerate(scene.occluders):
        if isinstance(occ, MeshOccluder):
            rows.append(np.full(occ.unit_vertices.shape[0], i, np.int32))
    return np.concatenate(rows)


_surface_offset = eqx.filter_jit(surface_offset)  # one compiled call (eagerly, many small dispatches)


def _concrete_lift(scene: Scene, t) -> float | None:
    """The scene's :func:`jshadow.entities.surface_offset` at t as a float, or None when it is
    traced (receivers, occluders or lights being differentiated or traced under ``jit``)."""
    with jax.ensure_compile_time_eval():
        lift = _concrete(_surface_offset(scene, t))
    return None if lift is None else float(lift)


# self_visibility = "maps" (jshadow.visibility._own_maps; the transfer's sphere grid and image pixels
# are method.self_maps_grid and method.self_maps_resolution): the lamps' image pixels where
# method.lamp_images is 0
MAPS_LAMP_RESOLUTION = 128
MAPS_RINGS = 2  # rings of faces about each vertex tested by exact rays
MAPS_MARGIN = 3.0  # pixels: entries in the images closer ahead of a vertex are the local rays' to find
# the lamps' (vertex, lamp) pairs whose four pixel centres disagree, or that pass a sliver, tested
# exactly (jshadow.visibility.settle_ambiguous): the animated bunny 1.03 -> 0.94 % (map split at 4 x
# its mean, the four centres alone) for 20 ms per frame (benchmarks/bench_own_maps.py); the slivers
# took its vertices' largest error 9.0 -> 6.5 % (map split at 2) for 7 ms more a frame (170.1 ->
# 177.4 ms in bench_own_maps.py; 4 ms of the settling alone)
MAPS_EXACT_AMBIGUOUS = True
# pixels of the transfer's images (the bending spot cow under a sky: 1.5 -> 0.5 took it 3.04 -> 2.07 %)
MAPS_TRANSFER_MARGIN = 0.5
SELF_MAPS_CLOSED = (
    "method.self_visibility = 'maps' images a mesh's entry faces, which cover its silhouette only for a "
    "closed, consistently oriented mesh: use self_visibility = 'rays' for this one"
)


@functools.lru_cache(maxsize=8)
def _ring_faces_of(faces_bytes: bytes, n_faces: int, n_vertices: int, rings: int) -> np.ndarray:
    faces = np.frombuffer(faces_bytes, np.int64).reshape(n_faces, 3)
    return ring_faces(faces, n_vertices, rings)


def _ring_faces(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """:func:`jshadow.visibility.ring_faces` (two rings) of a topology, kept for the next pose."""
    f = np.ascontiguousarray(faces, np.int64)
    return _ring_faces_of(f.tobytes(), f.shape[0], int(n_vertices), MAPS_RINGS)


_OWN: list = []  # [(key, own visibility)] of concrete poses, most recent last (at most 8)


def _maps_constants() -> tuple:
    """The module constants the "maps" casts read, as they are now: part of the own-vertex caches'
    keys, so that a pose cast before one of them changed is cast anew."""
    return (
        MAPS_MARGIN,
        MAPS_TRANSFER_MARGIN,
        MAPS_RINGS,
        MAPS_LAMP_RESOLUTION,
        MAPS_EXACT_AMBIGUOUS,
        _own_exact.REACH,
        _own_exact.AHEAD,
        _own_exact.TILE,
    )


def occluder_own_visibility(occ: MeshOccluder, t, scene: Scene, cache: bool = True) -> Float[Array, "V n2"]:
    """(V, n²) shadowed diffuse transfer of a mesh occluder at its own vertices at time t, by rays
    (:func:`jshadow.visibility.vertex_visibility_sh` with ``transfer=True``, the scene's
    :func:`jshadow.entities.surface_offset` and ``method.self_visibility_grid``): the SH of
    ``V(ω)·max(0, n·ω)``, which :func:`combine` takes in place of the clamped cosine at these
    vertices (their own field visibility is then 1).

    A concrete pose (vertices and faces not traced) is cast once and kept: :func:`render` called
    again on a shape it has seen (another frame of a rigid mesh, another light position) reuses
    the cast, as :class:`jshadow.Renderer` does (the last 8 poses are kept; ``cache=False`` casts
    anew and keeps nothing, for a caller with its own reuse). Differentiating it
    with respect to the vertices (their deformation, offsets, position) raises
    :data:`SELF_RAYS_NO_DERIVATIVE`: binary visibility has no derivative to give.

    With ``self_visibility = "maps"`` a concrete pose's transfer comes from depth images and local
    rays instead (:func:`jshadow.visibility.vertex_transfer_maps`, ``method.self_maps_grid`` at
    ``method.self_maps_resolution`` pixels), cached or not the same way; a traced pose is cast by
    rays.
    """
    m = scene.method
    t = jnp.asarray(t, occ.unit_vertices.dtype)
    v = _vertices_at(occ, t)
    faces = occ.faces
    grid = tuple(m.self_visibility_grid)
    v_np, f_np, lift = _concrete(v), _concrete(faces), _concrete_lift(scene, t)
    concrete = v_np is not None and f_np is not None and lift is not None
    if concrete and (cache or m.self_visibility == "maps"):  # "maps" needs a concrete pose
        key = _own_key(m, v_np, f_np, lift)
        hit = [own for k, own in _OWN if k == key] if cache else []
        if not hit:
            with jax.ensure_compile_time_eval():
                if m.self_visibility == "maps":
                    if not is_closed_manifold(f_np):
                        raise ValueError(SELF_MAPS_CLOSED)
                    local = _ring_faces(f_np, v_np.shape[0])
                    n = m.sh_bands
                    own = vertex_transfer_maps(
                        v_np,
                        f_np,
                        n,
                        local,
                        lift,
                        tuple(m.self_maps_grid),
                        m.self_maps_resolution,
                        MAPS_TRANSFER_MARGIN,
                    )
                else:
                    own = vertex_visibility_sh(v_np, f_np, m.sh_bands, grid, offset=lift, transfer=True)
                hit = [np.asarray(own)]
            if cache:
                _OWN.append((key, hit[0]))
                del _OWN[:-8]
        return jnp.asarray(hit[0])
    lift = jax.lax.stop_gradient(_surface_offset(scene, t))

    def forward(x):
        return vertex_visibility_sh(x, faces, m.sh_bands, grid, offset=lift, transfer=True)

    return _no_derivative_guard(forward, v, SELF_RAYS_NO_DERIVATIVE)


_OWN_LIGHTS: list = []  # [(key, (V, K) visibility)] like _OWN


def occluder_own_light_visibility(
    occ: MeshOccluder, t, scene: Scene, directions: Float[Array, "K 3"], cache: bool = True
) -> Float[Array, "V K"]:
    """(V, K) visibility, 0 or 1, of a mesh occluder's own vertices at time t toward K distant
    ``directions`` (the environment lights of :mod:`jshadow.envlights`), by exact rays against
    the mesh (:func:`jshadow.visibility.ray_fan_any_hit`) from each vertex lifted by the scene's
    :func:`jshadow.entities.surface_offset` along its normal, hits closer than that ignored (the
    reference renderer's convention for a receiver on a surface); 0 toward a direction on or below
    the vertex's tangent plane, which the shading weighs by zero (:func:`_lamp_rays`). Cached per
    concrete pose like :func:`occluder_own_visibility`, and likewise raising
    :data:`SELF_RAYS_NO_DERIVATIVE` if differentiated with respect to the vertices. With
    ``self_visibility = "maps"`` a concrete pose's visibility comes from entry-face images along
    the directions (``method.lamp_images`` pixels, :data:`MAPS_LAMP_RESOLUTION` if 0) and rays
    against each vertex's two rings of faces, the pairs next to a silhouette in the images tested
    exactly (:func:`jshadow.visibility.vertex_lamp_visibility` with ``exact_ambiguous``); a traced
    pose is cast by rays."""
    m = scene.method
    t = jnp.asarray(t, occ.unit_vertices.dtype)
    v = _vertices_at(occ, t)
    faces = occ.faces
    v_np, f_np, d_np = _concrete(v), _concrete(faces), _concrete(directions)
    lift = _concrete_lift(scene, t)
    concrete = v_np is not None and f_np is not None and d_np is not None and lift is not None
    if concrete and (cache or m.self_visibility == "maps"):  # "maps" needs a concrete pose
        key = _own_light_key(m, v_np, f_np, d_np, lift)
        hit = [vis for k, vis in _OWN_LIGHTS if k == key] if cache else []
        if not hit:
            with jax.ensure_compile_time_eval():
                if m.self_visibility == "maps":
                    if not is_closed_manifold(f_np):
                        raise ValueError(SELF_MAPS_CLOSED)
                    res = m.lamp_images or MAPS_LAMP_RESOLUTION
                    images = _lamp_images_of(v_np, f_np, d_np.astype(v_np.dtype), res)
                    local = _ring_faces(f_np, v_np.shape[0])
                    vis = vertex_lamp_visibility(
                        images, v_np, f_np, local, lift, MAPS_MARGIN, exact_ambiguous=MAPS_EXACT_AMBIGUOUS
                    )
                else:
                    vis = _lamp_rays(v_np, f_np, d_np.astype(v_np.dtype), lift)
                hit = [np.asarray(vis)]
            if cache:
                _OWN_LIGHTS.append((key, hit[0]))
                del _OWN_LIGHTS[:-8]
        return jnp.asarray(hit[0])
    lift = jax.lax.stop_gradient(_surface_offset(scene, t))

    def forward(x):
        return _lamp_rays(x, faces, jax.lax.stop_gradient(directions).astype(x.dtype), lift)

    return _no_derivative_guard(forward, v, SELF_RAYS_NO_DERIVATIVE)


def _own_key(m, v_np, f_np, lift) -> tuple:
    """What :func:`occluder_own_visibility` keeps a pose's transfer under."""
    key = (v_np.shape, str(v_np.dtype), v_np.tobytes(), f_np.shape, f_np.tobytes(), m.sh_bands)
    key = (*key, tuple(m.self_visibility_grid), lift, m.self_visibility)
    return (*key, tuple(m.self_maps_grid), m.self_maps_resolution, *_maps_constants())


def _own_light_key(m, v_np, f_np, d_np, lift) -> tuple:
    """What :func:`occluder_own_light_visibility` keeps a pose's lamp visibility under."""
    key = (v_np.shape, str(v_np.dtype), v_np.tobytes(), f_np.tobytes(), d_np.tobytes(), lift)
    return (*key, m.self_visibility, m.lamp_images, *_maps_constants())


def occluder_own_casts(
    occ: MeshOccluder, t, scene: Scene, directions: Float[Array, "K 3"], cache: bool = True
) -> tuple[Float[Array, "V n2"], Float[Array, "V K"]]:
    """:func:`occluder_own_visibility` and :func:`occluder_own_light_visibility` of one pose.
    With ``self_visibility = "rays"`` and a concrete pose both come from one cast
    (:func:`jshadow.visibility.vertex_transfer_and_lamps`: each vertex's grid and lamps in one fan,
    the faces' lists made once; the same values), kept as those functions keep theirs; otherwise
    from the two functions."""
    m = scene.method
    if m.self_visibility == "rays":
        t = jnp.asarray(t, occ.unit_vertices.dtype)
        v_np, f_np = _concrete(_vertices_at(occ, t)), _concrete(occ.faces)
        d_np, lift = _concrete(directions), _concrete_lift(scene, t)
        if all(x is not None for x in (v_np, f_np, d_np, lift)):
            keys = _own_key(m, v_np, f_np, lift), _own_light_key(m, v_np, f_np, d_np, lift)
            own = [x for k, x in _OWN if k == keys[0]] if cache else []
            lamps = [x for k, x in _OWN_LIGHTS if k == keys[1]] if cache else []
            if not (own and lamps):
                with jax.ensure_compile_time_eval():
                    transfer, vis = vertex_transfer_and_lamps(
                        v_np, f_np, m.sh_bands, tuple(m.self_visibility_grid), lift, d_np.astype(v_np.dtype)
                    )
                own, lamps = [np.asarray(transfer)], [np.asarray(vis)]
                if cache:
                    for store, key, value in ((_OWN, keys[0], own[0]), (_OWN_LIGHTS, keys[1], lamps[0])):
                        store.append((key, value))
                        del store[:-8]
            return jnp.asarray(own[0]), jnp.asarray(lamps[0])
    return (
        occluder_own_visibility(occ, t, scene, cache),
        occluder_own_light_visibility(occ, t, scene, directions, cache),
    )


def _lamp_rays(v, faces, directions, lift) -> Float[Array, "V K"]:
    """1 where the ray from vertex v lifted by ``lift`` along its normal toward a direction above
    the vertex's tangent plane is free; 0 toward a direction on or below that plane, which the
    shading weighs by zero (the cosine of :func:`environment_visible_fraction`). A concrete mesh
    tests each vertex's rays against only the faces above its plane within their azimuths
    (:func:`jshadow.visibility.hemisphere_fan_any_hit`: the same hits; the bunny's 256 lamps took
    144 against 575 ms, ``benchmarks/bench_own_rays.py``); a traced one against every face."""
    origins, normals = lifted_origins(v, faces, jnp.asarray(lift, v.dtype))  # the transfer's origins
    up, fans = lamp_fans(normals, directions)  # (V, K), (V, K, 3)
    if any(isinstance(x, jax.core.Tracer) for x in (v, faces, directions, lift)):
        hit = ray_fan_any_hit(origins, directions, v, faces, t_min=lift)
    else:
        hit = hemisphere_fan_any_hit(origins, fans, v, faces, normals, t_min=lift)
    return (up & ~hit).astype(v.dtype)


def self_light_rows(scene: Scene, own: list, k: int) -> Float[Array, "N K"]:
    """(N, K) rows over all receivers: each mesh occluder's :func:`occluder_own_light_visibility`
    at its vertices' rows (in the order of the mesh occluders), ones at the plane's."""
    plane = jnp.ones((scene.receivers.points.shape[0], k), scene.dtype)
    return jnp.concatenate([plane, *(o.astype(scene.dtype) for o in own)], 0)


def self_visibility_rows(scene: Scene, own: list) -> Float[Array, "N n2"]:
    """(N, n²) rows over all receivers: each mesh occluder's ``own`` visibility (in the order of
    the mesh occluders) at its vertices' rows, zeros at the plane's (see :func:`self_visibility_owners`)."""
    n2 = scene.method.sh_bands**2
    plane = jnp.zeros((scene.receivers.points.shape[0], n2), scene.dtype)
    return jnp.concatenate([plane, *(o.astype(scene.dtype) for o in own)], 0)


def own_rows_at_time(scene: Scene, t) -> tuple[Array, ...] | None:
    """``(rows, owners)`` of the scene's ray-cast own-vertex visibility at time t
    (:func:`self_visibility_rows`, :func:`self_visibility_owners`), or None when the scene does
    not use them (:func:`uses_self_rays`); ``rows`` is None with ``self_visibility = "light_rays"``
    (the field's visibility is kept). With :func:`uses_environment_lights` a third item, the
    (N, K) own-vertex visibility toward the environment lights (:func:`self_light_rows`)."""
    if not uses_self_rays(scene):
        return None
    meshes = [o for o in scene.occluders if isinstance(o, MeshOccluder)]
    if not uses_environment_lights(scene):
        own = [occluder_own_visibility(o, t, scene) for o in meshes] if casts_own_sh(scene) else None
        return assemble_own_rows(scene, own)
    d = scene_lighting(scene).env_lights.directions
    if casts_own_sh(scene):  # both: from one cast each where they can be ("rays")
        both = [occluder_own_casts(o, t, scene, d) for o in meshes]
        return assemble_own_rows(scene, [b[0] for b in both], [b[1] for b in both], d)
    return assemble_own_rows(scene, None, [occluder_own_light_visibility(o, t, scene, d) for o in meshes], d)


def assemble_own_rows(
    scene: Scene,
    own: Sequence[Array],
    own_lights: Sequence[Array] | None = None,
    light_directions: Float[Array, "K 3"] | None = None,
    owners: Int[Array, " N"] | None = None,
) -> tuple[Array, ...]:
    """The tuple :func:`own_rows_at_time` returns, from each mesh occluder's cast visibility.

    ``own``: per mesh occluder (in scene order) its :func:`occluder_own_visibility`, or None
    (``self_visibility = "light_rays"``: the tuple's rows are None);
    ``own_lights`` (with ``light_directions``, the (K, 3) environment-light directions): its
    :func:`occluder_own_light_visibility`, or None without environment lights; ``owners``: the
    precomputed :func:`self_visibility_owners` as an array (computed here when None).
    """
    if owners is None:
        owners = jnp.asarray(self_visibility_owners(scene))
    out = (None if own is None else self_visibility_rows(scene, own), owners)
    if own_lights is None:
        return out
    return (*out, self_light_rows(scene, own_lights, light_directions.shape[0]))


LIGHT_IMAGES_NO_DERIVATIVE = (
    "method.light_visibility = 'images' tests the rays to the sphere lights (and to the environment's "
    "bright part, with environment_lights) against sphere occluders exactly, a binary test with no "
    "derivative with respect to those spheres' centres and radii: differentiate them with "
    "light_visibility = 'sh' (mesh occluders, lights and receivers have derivatives with both)"
)


def uses_environment_lights(scene: Scene) -> bool:
    """Whether the environment's bright part is split off as distant lights shadowed through the
    occlusion images (``method.environment_lights`` > 0 — which needs ``light_visibility =
    "images"`` —, a lat-long environment and a mesh occluder; :mod:`jshadow.envlights`)."""
    return (
        scene.method.environment_lights > 0
        and scene.environment is not None
        and scene.environment.kind == "hdr"
        and any(isinstance(o, MeshOccluder) for o in scene.occluders)
    )


def uses_light_images(scene: Scene) -> bool:
    """Whether lights are shadowed through the occlusion images (``method.light_visibility =
    "images"``, a mesh occluder, and sphere lights or :func:`uses_environment_lights`: with sphere
    occluders only, the analytic path's exact lens of two caps is used as it is)."""
    return (
        scene.method.light_visibility == "images"
        and (bool(scene.lights) or uses_environment_lights(scene))
        and any(isinstance(o, MeshOccluder) for o in scene.occluders)
    )


def occluder_images(occ, t, scene: Scene, differentiable: bool = True) -> OcclusionImages | None:
    """The occlusion images (:func:`jshadow.visibility.occlusion_images`) of a mesh occluder at time
    t on the method's shell, grid and directions; None for a sphere occluder (an exact ray test is
    used instead).

    With ``differentiable`` the images are 0.0 / 1.0 *coverage* floats, so that lookups carry the
    derivative of the read point's motion (lights, receivers, the occluder's placement), and for
    traced vertices also the silhouette boundary term of
    :func:`jshadow.visibility.bsv_and_coverage_edgescan_diff` (which needs the edge-scan: concrete
    closed manifold faces; a mesh without it raises :data:`TRACED_FACES` when differentiated).
    ``differentiable=False`` gives the boolean images (the :class:`jshadow.runner.Renderer`'s, no
    derivative at all). With ``method.light_images = "coverage"`` both give the scan lines'
    coverage images (:func:`jshadow.visibility.scan_coverage`), read bilinearly, whose derivative
    is JAX's own and exact.
    """
    if not isinstance(occ, MeshOccluder):
        return None
    m = scene.method
    v = _sampler_vertices(occ, jnp.asarray(t, occ.unit_vertices.dtype), m)
    faces = occ.faces
    if m.light_images == "coverage":
        return _coverage_images(occ, v, m)

    def forward(x):
        return occlusion_images(x, faces, tuple(m.bsv_grid), tuple(m.directions), float(m.shell))

    if not differentiable:
        return _with_center_motion(occ, _no_derivative_guard(forward, v, LIGHT_IMAGES_NO_DERIVATIVE))
    faces_np = _concrete(faces)
    if isinstance(v, jax.core.Tracer) and faces_np is not None and _uses_edgescan(m, faces_np):
        return _mesh_bsv_and_images(occ, v, faces_np, m)[1]
    img = _with_center_motion(occ, _no_derivative_guard(forward, v))
    return OcclusionImages(
        occluded=img.occluded.astype(v.dtype), center=img.center, radius=img.radius, shell=img.shell
    )


def _coverage(occ: MeshOccluder, v, m) -> Float[Array, "T P Ny Nx"]:
    """The scan lines' coverage images of the sampler's input vertices ``v``
    (:func:`jshadow.visibility.scan_coverage`), differentiable by JAX itself (exact), for
    ``light_images`` or ``bsv_images = "coverage"``. Sizes as the scanline derivative's (measured on
    concrete poses)."""
    faces = _concrete(occ.faces)
    if faces is None or not _uses_edgescan(m, faces):
        raise ValueError(
            "method.light_images / bsv_images = 'coverage' needs the edge-scan: concrete, closed, "
            "consistently wound manifold mesh faces and shell > 1 (build the scene outside jax "
            "transformations)"
        )
    es = _edgescan_slots(occ, faces, m)
    ss = _scan_grad_slots(occ, faces, m)
    if es is None:  # a traced pose of faces no concrete pose was seen with: no sizes measured, and
        # no fallback under a trace (an overflow raises), so 4x the edge-scan's generous defaults
        es = tuple(4 * x for x in _traced_default_slots(faces.shape[0], m.bsv_grid, m.directions))
    # the BSV's: each crossing weighted by its edge's share of its scan, whose derivative is the
    # converged one's within 0.5-2.3 % (the plain mean's 13-39 %, BENCHMARKS.md "BSV from coverage
    # images"); the light images alone keep the mean their figures were measured with
    scans = "split" if m.bsv_images == "coverage" else "both"
    return scan_coverage(v, faces, m.bsv_grid, m.directions, m.shell, scans=scans, slots=es, scan_slots=ss)


def _coverage_images(occ: MeshOccluder, v, m, cov=None) -> OcclusionImages:
    """``method.light_images = "coverage"``: the coverage images (:func:`_coverage`, or ``cov``
    where they are made already) read bilinearly."""
    cov = _coverage(occ, v, m) if cov is None else cov
    center, radius = _bsv_sphere(occ, v, m)
    return OcclusionImages(occluded=cov, center=center, radius=radius, shell=float(m.shell), reads="bilinear")


def _coverage_bsv(occ: MeshOccluder, v, cov, m) -> BSV:
    """``method.bsv_images = "coverage"``: the BSV projected from the coverage images ``cov`` of the
    sampler's input vertices ``v`` (:func:`jshadow.visibility.coverage_sh`); its derivative is
    JAX's own."""
    center, radius = _bsv_sphere(occ, v, m)
    coeffs = coverage_sh(cov, m.field_bands, tuple(m.directions), float(m.shell))
    return BSV(coeffs=coeffs, center=center, radius=radius, shell_radius=m.shell * radius)


def _mesh_bsv_and_images(occ: MeshOccluder, v, faces: np.ndarray, m) -> tuple[BSV, OcclusionImages]:
    """The differentiable BSV (``bsv_gradient = "image"``'s derivative) and coverage images of the
    sampler's input vertices ``v`` from one edge-scan and one set of silhouette derivative terms
    (:func:`jshadow.visibility.bsv_and_coverage_edgescan_diff`)."""
    es = _edgescan_slots(occ, faces, m)
    grad_slots = _image_grad_slots(occ, faces, m, lazy=True)
    coeffs, cov = bsv_and_coverage_edgescan_diff(
        v, faces, m.field_bands, m.bsv_grid, m.directions, m.shell, slots=es, grad_slots=grad_slots
    )
    center, radius = _bsv_sphere(occ, v, m)
    bsv = BSV(coeffs=coeffs, center=center, radius=radius, shell_radius=m.shell * radius)
    return bsv, OcclusionImages(occluded=cov, center=center, radius=radius, shell=float(m.shell))


def occluder_bsv_and_images(occ: MeshOccluder, t, scene: Scene) -> tuple[BSV, OcclusionImages] | None:
    """The BSV (without derivative machinery, as ``occluder_bsv(..., differentiable=False)``) and
    the occlusion images of a mesh occluder at a concrete time from one edge-scan
    (:func:`jshadow.visibility.bsv_with_occlusion_images`), or None where the method does not
    sample this mesh with the edge-scan (then the two are computed apart)."""
    m = scene.method
    faces = _concrete(occ.faces)
    if m.bsv_images == "coverage" and m.light_images == "coverage":  # one coverage for both
        v = _sampler_vertices(occ, jnp.asarray(t, occ.unit_vertices.dtype), m)
        cov = _coverage(occ, v, m)
        return _coverage_bsv(occ, v, cov, m), _coverage_images(occ, v, m, cov)
    if faces is None or not _uses_edgescan(m, faces) or "coverage" in (m.light_images, m.bsv_images):
        return None
    v = _sampler_vertices(occ, jnp.asarray(t, occ.unit_vertices.dtype), m)
    if _concrete(v) is None:
        return None
    bsv, img = bsv_with_occlusion_images(v, faces, m.field_bands, m.bsv_grid, m.directions, m.shell)
    return _with_center_motion(occ, bsv), _with_center_motion(occ, img)


def occluder_lamp_images(occ, t, scene: Scene, img: OcclusionImages | None) -> OcclusionImages | None:
    """``img`` with the occluder's orthographic images along the environment lights' directions
    attached (:func:`jshadow.visibility.lamp_images` at ``method.lamp_images`` pixels per side, of
    its world vertices at time t), where the scene splits its map into lights and asks for them;
    else ``img`` as it is. Concrete vertices only: traced ones (a deformation or placement being
    differentiated or traced under ``jit``) keep the shell's images for those lights."""
    m = scene.method
    if img is None or img.lamps is not None or m.lamp_images <= 0 or not isinstance(occ, MeshOccluder):
        return img
    if not uses_environment_lights(scene):
        return img
    v = _concrete(_vertices_at(occ, jnp.asarray(t, occ.unit_vertices.dtype)))
    faces = _concrete(occ.faces)
    d = _concrete(scene_lighting(scene).env_lights.directions)
    if v is None or faces is None or d is None:
        return img
    lamps = _lamp_images_of(v, faces, d, m.lamp_images)
    return eqx.tree_at(lambda x: x.lamps, img, lamps, is_leaf=lambda x: x is None)


_LAMP_IMAGES: list = []  # [(key, LampImages)] of concrete poses, most recent last (at most 2)


def clear_pose_caches() -> None:
    """Forget the casts and images kept per concrete pose (:func:`occluder_own_visibility`,
    :func:`occluder_own_light_visibility`, :func:`occluder_lamp_images`, :func:`render_at`'s
    contact rows): what a benchmark of
    fresh frames of one pose calls between them, so that each makes everything again."""
    _OWN.clear()
    _OWN_LIGHTS.clear()
    _LAMP_IMAGES.clear()
    _CONTACT.clear()


def _lamp_images_of(v: np.ndarray, faces: np.ndarray, directions: np.ndarray, resolution: int) -> LampImages:
    """:func:`jshadow.visibility.lamp_images` of a concrete pose, of the entry faces for a closed
    mesh (the same coverage, and the depth its own vertices are tested against with
    ``self_visibility = "maps"``); the last two poses are kept, so a frame's plane and own
    vertices share one set."""
    closed = is_closed_manifold(faces)
    key = (v.shape, str(v.dtype), v.tobytes(), faces.tobytes(), directions.tobytes(), int(resolution), closed)
    hit = [img for k, img in _LAMP_IMAGES if k == key]
    if not hit:
        with jax.ensure_compile_time_eval():
            hit = [lamp_images(v, faces, directions, resolution, entry_only=closed)]
        _LAMP_IMAGES.append((key, hit[0]))
        del _LAMP_IMAGES[:-2]
    return hit[0]


def with_lamp_images(scene: Scene, t, images):
    """:func:`occluder_lamp_images` of every occluder's images (None stays None)."""
    if images is None:
        return None
    pairs = zip(scene.occluders, images, strict=True)
    return tuple(occluder_lamp_images(o, t, scene, img) for o, img in pairs)


def scene_images(scene: Scene, t) -> tuple[OcclusionImages | None, ...] | None:
    """:func:`occluder_images` of every occluder at time t, or None unless :func:`uses_light_images`."""
    if not uses_light_images(scene):
        return None
    return tuple(occluder_images(o, t, scene) for o in scene.occluders)


def scene_bsvs_and_images(
    scene: Scene, t, sphere_path: str = "analytic"
) -> tuple[tuple[BSV | None, ...], tuple[OcclusionImages | None, ...] | None]:
    """:func:`scene_bsvs` and :func:`scene_images` at time t, a mesh occluder's two from one
    edge-scan (and one set of derivative terms) where both carry the ``"image"`` silhouette
    derivative (:func:`_mesh_bsv_and_images`); else each as those functions make it."""
    if not uses_light_images(scene):
        return scene_bsvs(scene, t, sphere_path), None
    m = scene.method
    bsvs, images = [], []
    for occ in scene.occluders:
        if isinstance(occ, MeshOccluder) and m.bsv_images == m.light_images == "coverage":
            bsv, img = occluder_bsv_and_images(occ, t, scene)  # one coverage for both
            bsvs.append(bsv)
            images.append(img)
            continue
        faces = _concrete(occ.faces) if isinstance(occ, MeshOccluder) else None
        one_pass = faces is not None and m.light_images == "samples"  # coverage: its own scan pass
        one_pass = one_pass and m.bsv_images == "samples"
        if one_pass and _uses_edgescan(m, faces) and bsv_gradient_mode(m, faces) == "image":
            v = _sampler_vertices(occ, jnp.asarray(t, occ.unit_vertices.dtype), m)
            if isinstance(v, jax.core.Tracer):
                bsv, img = _mesh_bsv_and_images(occ, v, faces, m)
                bsvs.append(bsv)
                images.append(img)
                continue
        bsvs.append(occluder_bsv(occ, t, scene, sphere_path))
        images.append(occluder_images(occ, t, scene))
    return tuple(bsvs), tuple(images)


def light_visible_fractions(
    scene: Scene,
    images: tuple[OcclusionImages | None, ...],
    points: Float[Array, "N 3"],
    normals: Float[Array, "N 3"],
    cull: bool = True,
) -> list[Float[Array, " N"]]:
    """Per sphere light, the cosine-weighted visible fraction (N,) of the light at each receiver.

    ``F = Σ_k V(x, ω_k) cos⁺_k / Σ_k cos⁺_k`` over the ``method.light_cap`` stratified directions
    ω_k of the light's cap (:func:`jshadow.sampling.stratified_sphere_cone`). ``V`` multiplies, per
    direction, every occluder whose centre is nearer than the light's: a mesh occluder looked up in
    its ``images`` (:func:`jshadow.visibility.image_fan_visibility`, grid points chosen around the
    ray to the light's centre), a sphere occluder by an exact ray test. A receiver that sees none
    of the cap above its horizon gets F = 1 (its exact unoccluded irradiance is 0 anyway).

    Derivatives: with coverage images (:func:`occluder_images`) the lookups carry the silhouette
    term of the mesh's vertices and the motion of the read points (receivers, lights, the
    occluder's placement; :func:`jshadow.visibility.bsv_and_coverage_edgescan_diff`), i.e. the
    derivative of the pixel-box-filtered images, sampled at the cap directions: an estimate whose
    noise falls as the cap's directions and the receivers grow (``tests/test_image_lookup_grad.py``
    measures it against the closed-form lens). Differentiating a sphere occluder's centre or
    radius raises :data:`LIGHT_IMAGES_NO_DERIVATIVE` (its ray test is binary).

    Work skipped: with ``cull`` (the default), a receiver whose cone toward the light misses every
    occluder's bounding sphere (:func:`jshadow.geometry.cone_may_meet_sphere`, with the images'
    :func:`jshadow.visibility.image_reach`) has F = 1 exactly and no derivative; the cap directions
    and lookups run only on chunks of receivers that hold another (:func:`jshadow._active.over_active`).
    ``cull=False`` computes every receiver (the same values and derivatives).
    """
    strata = tuple(scene.method.light_cap)
    geometry = (
        points,
        normals,
        [(light.center, light.radius) for light in scene.lights],
        _sphere_blockers(scene),
    )

    def forward(geo):
        pts, nrm, lights, spheres = geo
        it = iter(spheres)
        blockers = [(img, None) if img is not None else (None, next(it)) for img in images]
        out = []
        for lc, lr in lights:

            def fraction(pts, nrm, lc=lc, lr=lr):
                # component-wise (N, K) arrays throughout: XLA:CPU is slow on (N, K, 3) layouts
                dx, dy, dz = stratified_cone_components(lc - pts, lr, strata)
                axis = safe_normalize(lc - pts)
                d_l = safe_norm(pts - lc)
                vis = jnp.ones(dx.shape, pts.dtype)
                dirs = jnp.stack([dx, dy, dz], -1) if len(spheres) else None  # the sphere ray tests
                for img, sphere in blockers:
                    if img is None:
                        c, r = sphere
                        v = 1.0 - ray_sphere_any_hit(pts[:, None, :], dirs, c, r).astype(pts.dtype)
                    else:
                        c = img.center
                        v = image_fan_visibility_components(img, pts, (dx, dy, dz), axis)
                    vis = vis * jnp.where((safe_norm(pts - c) < d_l)[:, None], v, 1.0)
                cos = jnp.maximum(nrm[:, 0:1] * dx + nrm[:, 1:2] * dy + nrm[:, 2:3] * dz, 0.0)
                den = jnp.sum(cos, -1)
                return jnp.where(den > 0, jnp.sum(vis * cos, -1) / jnp.where(den > 0, den, 1.0), 1.0)

            if not cull:
                out.append(fraction(pts, nrm))
                continue
            # receivers whose cone toward the light misses every blocker's sphere see all of it (F = 1,
            # no derivative): the lookups run on the others only
            active = jnp.zeros(pts.shape[:1], bool)
            for c, r in _reach_spheres(blockers):
                active = active | cone_may_meet_sphere(pts, lc, lr, c, r)
            out.append(over_active(fraction, active, (pts, nrm), 1.0))
        return out

    return forward(geometry)


def _reach_spheres(blockers) -> list[tuple[Array, Array]]:
    """(centre, radius) per blocker beyond which its rays are free: a sphere occluder itself, a
    mesh's bounding sphere widened by its images' derivative ramp (:func:`image_reach`)."""
    return [sphere if img is None else (img.center, image_reach(img)) for img, sphere in blockers]


def _sphere_blockers(scene: Scene) -> list[tuple[Array, Array]]:
    """The (centre, radius) of each sphere occluder, for the exact ray tests of the image lookups'
    path; differentiating them raises :data:`LIGHT_IMAGES_NO_DERIVATIVE` (a binary test)."""
    spheres = [(o.center, o.radius) for o in scene.occluders if not isinstance(o, MeshOccluder)]
    return _no_derivative_guard(lambda x: x, spheres, LIGHT_IMAGES_NO_DERIVATIVE) if spheres else spheres


_INSIDE = 1.0 + 1e-4  # receivers within this × a mesh's bounding radius fall back to the n-band path


def environment_visible_fraction(
    scene: Scene,
    images: tuple[OcclusionImages | None, ...],
    lights: EnvironmentLights,
    points: Float[Array, "N 3"],
    normals: Float[Array, "N 3"],
    own: tuple[Array, ...] | None = None,
    cull: bool = True,
) -> tuple[Float[Array, "N 3"], Bool[Array, " N"]]:
    """The visible fraction (N, 3) of the environment's bright part (:mod:`jshadow.envlights`).

    ``F_c = Σ_k E_kc cos⁺_k V(x, ω_k) / Σ_k E_kc cos⁺_k`` over the K distant lights (energies E,
    directions ω); ``V`` multiplies every occluder (all are nearer than the environment): a mesh
    occluder looked up in its ``images`` (:func:`jshadow.visibility.image_fan_visibility`, the
    grid points chosen once per fan of lights about the fan's axis), a sphere occluder by an exact
    ray test. A receiver facing none of the lights gets F = 1 (its unoccluded irradiance from them
    is 0). Differentiable in the lights' energies and, with coverage images, in the geometry as
    :func:`light_visible_fractions` is (the lights' directions are the map's: held fixed);
    differentiating a sphere occluder raises :data:`LIGHT_IMAGES_NO_DERIVATIVE`.

    Returns ``(F, inside)``: ``inside`` (N,) bool marks receivers within a mesh occluder's bounding
    sphere whose rays its images cannot resolve: for the shell's images every such receiver (the
    line through it meets the mesh behind it too); for lamp images, whose depth settles any
    receiver off the mesh (:func:`jshadow.visibility.lamp_visibility`), only its own vertices with
    ``self_shadow`` where they have no rows in ``own`` (before 2026-12-07 every receiver within
    the sphere, so a plane under a low mesh took the n-band path there). :func:`combine` shades
    their bright part through the n-band path instead (in a throwaway trial on the bunny's own
    vertices under the studio map, not kept: 55 % relative RMSE through the shell's lookups, 24 %
    through the n-band path). With ``self_visibility = "rays"`` or "light_rays", ``own`` (from
    :func:`own_rows_at_time`, or a piece of it) holds the own vertices' exact visibility toward
    the lights in its third item: it replaces their own occluder's lookup, and they are not
    ``inside`` for it.

    Work skipped: with ``cull`` (the default), the lookups of a fan run only on chunks of receivers
    that hold one from which a direction of the fan may meet a blocker's sphere
    (:func:`jshadow.geometry.fan_may_meet_sphere`; as :func:`light_visible_fractions`) and that is
    not ``inside``; elsewhere the fraction is 1 (at ``inside`` receivers, whose fraction
    :func:`combine` does not use, ``cull=False`` gives the lookups' value instead; the other
    receivers' values and derivatives are the same either way). Where every mesh has lamp images
    (:func:`occluder_lamp_images`) a lookup is one pixel: all lamps are looked up at every receiver
    in one pass, without that choice (cheaper than making it).
    """
    fan = lights.fan
    geometry = (points, normals, _sphere_blockers(scene))
    dirs = jax.lax.stop_gradient(lights.directions)
    axes = jax.lax.stop_gradient(lights.axes)
    # lamp_penumbrae = "region": the regions' extents widen the lamp lookups
    spread = jax.lax.stop_gradient(lights.spread) if scene.method.lamp_penumbrae == "region" else None

    owners, own_vis = (own[1], own[2]) if own is not None and len(own) > 2 else (None, None)

    def forward(geo, inside):
        pts, nrm, spheres = geo
        it = iter(spheres)
        blockers = [(img, None) if img is not None else (None, next(it)) for img in images]
        # every mesh looked up in its lamp images: one pixel per receiver and lamp, cheaper than
        # choosing the receivers that need it, and all lamps in one pass (the animated bunny's 160²
        # plane, its vertices and 64 lamps: 26.8 -> 9.0 ms)
        direct = all(img is None or img.lamps is not None for img in images)
        k = dirs.shape[0]
        spans = [(0, k)] if direct else [(g * fan, (g + 1) * fan) for g in range(axes.shape[0])]
        vis_all, cos_all = [], []
        for g, (lo, hi) in enumerate(spans):
            d = dirs[lo:hi].astype(pts.dtype)  # (fan, 3), or (K, 3) when direct
            ax = axes[g].astype(pts.dtype)

            def fan_visibility(pts, *own_rows, d=d, ax=ax, lo=lo, hi=hi):
                comps = tuple(d[None, :, c] for c in range(3))  # (1, fan) each: shared by all receivers
                axis = jnp.broadcast_to(ax, pts.shape)
                vis = jnp.ones((pts.shape[0], hi - lo), pts.dtype)
                for i, (img, sphere) in enumerate(blockers):
                    if img is None:
                        c, r = sphere
                        hit = ray_sphere_any_hit(pts[:, None, :], d[None], c, r)
                        vis = vis * (1.0 - hit.astype(pts.dtype))
                        continue
                    if img.lamps is not None:  # the lamps' own orthographic images

                        def look(p, img=img, lo=lo, hi=hi):
                            return lamp_visibility(img.lamps, p, slice(lo, hi), spread)

                        # this mesh's own vertices take their own rows below: the chunks of
                        # receivers that are all its vertices skip the lookup
                        v = over_active(look, own_rows[0] != i, (pts,), 1.0) if own_rows else look(pts)
                    else:
                        v = image_fan_visibility_components(img, pts, comps, axis)
                    if own_rows:  # own vertices: their exact rays instead of the lookup
                        own_owner, own_fan = own_rows
                        v = jnp.where((own_owner == i)[:, None], own_fan.astype(v.dtype), v)
                    vis = vis * v
                return vis

            rows = (pts,) if owners is None else (pts, owners, own_vis[:, lo:hi])
            if not cull or direct:
                vis_all.append(fan_visibility(*rows))
            else:
                # receivers from which no direction of the fan meets a blocker's sphere see the whole fan
                half = jnp.arccos(jnp.clip(jnp.min(d @ ax), -1.0, 1.0))
                active = jnp.zeros(pts.shape[:1], bool)
                for c, r in _reach_spheres(blockers):
                    active = active | fan_may_meet_sphere(pts, ax, half, c, r)
                # nor for those inside a mesh's bounding sphere: combine shades them by the n-band path
                vis_all.append(over_active(fan_visibility, active & ~inside, rows, 1.0))
            cos_all.append(jnp.maximum(nrm @ d.T, 0.0))
        return jnp.concatenate(vis_all, -1), jnp.concatenate(cos_all, -1)  # (N, K) each

    inside = jnp.zeros(points.shape[:1], bool)
    for i, img in enumerate(images):
        if img is None:
            continue
        if img.lamps is not None and (owners is not None or not scene.self_shadow):
            continue  # its lamp images resolve any receiver off its surface, its own have their rows
        c, r = jax.lax.stop_gradient((img.center, img.radius))
        near = jnp.sum((jax.lax.stop_gradient(points) - c) ** 2, -1) < (r * _INSIDE) ** 2
        inside = inside | (near if owners is None else near & (owners != i))
    vis, cos = forward(geometry, inside)
    energy = lights.energy.astype(points.dtype)  # (K, 3)
    den = cos @ energy
    num = (cos * vis) @ energy
    ok = den > 0
    fraction = jnp.where(ok, num / jnp.where(ok, den, 1.0), 1.0)
    return fraction, inside


# ---- contact receivers (method.contact_visibility = "rays") ----------------------------------------
# the fixed receivers (scene.receivers) closer than this many bounding radii to a vertex of a mesh
# occluder: its field, extrapolated inward from the shell, fails there (the spot cow 0.05 above its
# floor: 12.2 % RMS error at the receivers 0.1-0.2 radii from it, 0.66 % at 0.5-1 radii); exact rays
# were better there but not at 0.3-0.5 radii under a lamp-split map (spot_sunset 2.99 -> 3.26 %,
# max 4.1 -> 5.3 %; BENCHMARKS.md "The default against the paper", eighth run)
CONTACT_REACH = 0.3
# faces with an edge longer than this fraction of the reach are also measured to (_large_faces)
CONTACT_LARGE_FACE = 0.5
CONTACT_GRID = (24, 48)  # θ × φ sphere grid of their visibility rays (48 × 96 gave nothing more)
# the grid where the n-band path carries at most CONTACT_SH_SHARE of the light that the rows shadow
# (a lat-long map's rest once its bright part is split into lamps, which the rays find exactly):
# a quarter of the rays, whose larger quadrature error is scaled by that share (the five scenes
# under the studio map, whose rest holds 11.9 % of its energy: every error the same to the digit
# as with CONTACT_GRID, BENCHMARKS.md "The default against the paper", tenth run)
CONTACT_GRID_DIM = (12, 24)
CONTACT_SH_SHARE = 0.25
# receivers per chunk of their rays (jshadow._active.over_active): of the powers of two from 8 to
# 128 and the multiples of 32 from 64 to 128, the size with the least chunks × (size +
# _CONTACT_CHUNK_COST) for the near count (each chunk costs about as much as 32 receivers' rays
# more: 2 near receivers 31 ms in chunks of 8, 92 ms in chunks of 64; 42 near 90 ms in one chunk of
# 64, 107 ms in two of 32; 91 near 94 ms in two chunks of 64, 78 ms in one of 128; 172 near 181 ms
# in three of 64, 203 ms in two of 128; 366 near 273 ms in six of 64, 210 ms in three of 128. With
# chunks of 96: the low bunny's 91 near on the coarser grid 36 ms against 48 ms in one of 128, the
# low cow's 172 near 159 ms in two of 96, 188 ms in three of 64, 217 ms in two of 128; the low
# bunny's 366 near 147 ms in four of 96, 143 ms in three of 128); 32 where the count is traced
_CONTACT_ROWS = (8, 128)
_CONTACT_CHUNK_COST = 32
CONTACT_NO_DERIVATIVE = (
    "method.contact_visibility = 'rays' casts binary visibility from the receivers next to a mesh "
    "occluder, which has no derivative with respect to the mesh, the receivers or the lights: "
    "differentiate with contact_visibility = 'field'"
)


def uses_contact(scene: Scene) -> bool:
    """Whether ``method.contact_visibility = "rays"`` applies: the scene has a mesh occluder."""
    return scene.method.contact_visibility == "rays" and any(
        isinstance(o, MeshOccluder) for o in scene.occluders
    )


def _nearest_vertex_d2(points: Float[Array, "M 3"], v: Float[Array, "V 3"]) -> Float[Array, " M"]:
    """Squared distance from each point to its nearest vertex (one GEMM)."""
    d2 = jnp.sum(points * points, -1)[:, None] - 2.0 * points @ v.T + jnp.sum(v * v, -1)[None]
    return jnp.maximum(jnp.min(d2, -1), 0.0)


def _near_mesh(
    points: Float[Array, "P 3"], v: Float[Array, "V 3"], large: Int[Array, "B 3"] | None = None
) -> Bool[Array, " P"]:
    """Which ``points`` lie within :data:`CONTACT_REACH` × the bounding radius of ``v`` from one of
    its vertices or from one of its ``large`` faces (:func:`_large_faces`; exact point–triangle
    distances), the tests only where the point is within reach of the bounding sphere."""
    c, r = bounding_sphere(v)
    reach = CONTACT_REACH * r
    maybe = jnp.sum((points - c) ** 2, -1) < (r + reach) ** 2
    d2 = over_active(lambda p: _nearest_vertex_d2(p, v), maybe, (points,), jnp.inf)
    if large is not None and large.shape[0]:
        # a point within reach of a face lies within reach + L/√3 of one of its corners (L its
        # longest edge): the faces are measured to only where the vertices leave it open
        tri = v[large]
        longest = jnp.sqrt(jnp.max(jnp.sum((tri - jnp.roll(tri, 1, axis=1)) ** 2, -1)))
        open_ = maybe & (d2 >= reach * reach) & (d2 <= (reach + longest / math.sqrt(3.0)) ** 2)
        faces_d2 = over_active(lambda p: point_mesh_distance2(p, v, large), open_, (points,), jnp.inf)
        d2 = jnp.minimum(d2, faces_d2)
    return maybe & (d2 < reach * reach)


def _large_faces(occ: MeshOccluder) -> np.ndarray | None:
    """(B, 3) the faces of a mesh occluder whose longest edge in its rest pose exceeds
    :data:`CONTACT_LARGE_FACE` × :data:`CONTACT_REACH` bounding radii, for the near test
    (:func:`_near_mesh`); None where there are none or the rest pose is traced.

    Any point of a triangle lies within L/√3 of its nearest corner (L its longest edge): the
    nearest-vertex test alone misses a receiver near the middle of a face larger than the reach (a
    box's side); of the faces left to it, whose longest edge is at most half the reach, it finds
    every receiver within 0.71 reaches of the face (a vertex then lies within 0.71 + 0.5/√3 < 1),
    so it misses only some in the outer 0.29 of the reach. Chosen on the rest pose: a deformation that
    stretches a small face is not followed (the bunny: 215 of its 3798 faces, mostly its base; the
    spot cow none; a cube all).

    Kept for the rest pose's arrays (JAX arrays are immutable: the same objects, the same faces),
    so a renderer's frames of one occluder copy and measure them once, not every frame (0.2–0.7 ms
    a call on the scenes of ``experiments/defaults.py``)."""
    limit = CONTACT_LARGE_FACE * CONTACT_REACH  # the rest pose's bounding radius is 1
    for u, f, lim, big in _LARGE:
        if u is occ.unit_vertices and f is occ.faces and lim == limit:
            return big
    u, f = _concrete(occ.unit_vertices), _concrete(occ.faces)
    if u is None or f is None:
        return None
    u = np.asarray(u, np.float64)
    f = np.asarray(f, np.int64)
    longest = np.max([np.linalg.norm(u[f[:, k]] - u[f[:, (k + 1) % 3]], axis=1) for k in range(3)], axis=0)
    big = f[longest > limit]
    big = big.astype(np.int32) if big.shape[0] else None
    if isinstance(occ.unit_vertices, jax.Array) and isinstance(occ.faces, jax.Array):
        _LARGE.append((occ.unit_vertices, occ.faces, limit, big))
        del _LARGE[:-8]
    return big


_LARGE: list = []  # [(rest pose, faces, limit, large faces)] of the last 8 occluders measured


_near_mesh_jit = jax.jit(_near_mesh)


def _contact_above(scene: Scene, t, near: Bool[Array, "N m"]) -> Bool[Array, ""]:
    """Whether every mesh occluder lies on or above the tangent plane of each fixed receiver near
    it (``near`` of :func:`_contact_near`): its lowest vertex's height over the plane ≥ 0 (the
    faces are the vertices' convex combinations), so no ray below that plane can hit it."""
    points = jax.lax.stop_gradient(scene.receivers.points)
    normals = jax.lax.stop_gradient(scene.receivers.normals)
    ok = jnp.asarray(True)
    for i, occ in enumerate(scene.occluders):
        if isinstance(occ, MeshOccluder):
            v = jax.lax.stop_gradient(occ.vertices(t))

            def lowest(p, q, v=v):  # (M,) the lowest vertex's height over each receiver's plane
                return jnp.min(q @ v.T, -1) - jnp.sum(p * q, -1)

            low = over_active(lowest, near[: points.shape[0], i], (points, normals), jnp.inf)
            ok = ok & jnp.all(low >= 0.0)
    return ok


def _contact_near(scene: Scene, t, large: tuple = ()) -> Bool[Array, "N m"]:
    """``near`` of :func:`contact_rows_at_time` (a mask: no derivative): tested at the fixed
    receivers, False at the own vertices that follow them. ``large``: per occluder its
    :func:`_large_faces` (or None), or empty for none."""
    points = jax.lax.stop_gradient(scene.receivers.points)
    own = receivers_at_time(scene, t)[0].shape[0] - points.shape[0]  # static
    cols = []
    for i, occ in enumerate(scene.occluders):
        if isinstance(occ, MeshOccluder):
            big = large[i] if large else None
            cols.append(_near_mesh(points, jax.lax.stop_gradient(occ.vertices(t)), big))
        else:
            cols.append(jnp.zeros(points.shape[0], bool))
    near = jnp.stack(cols, -1)
    return jnp.concatenate([near, jnp.zeros((own, near.shape[1]), bool)]) if own else near


def _contact_chunk(count: int | None) -> int:
    """Receivers per chunk of the contact rays for ``count`` near receivers (None: unknown)."""
    lo, hi = _CONTACT_ROWS
    if count is None:
        return 32
    sizes = sorted({1 << k for k in range(lo.bit_length() - 1, hi.bit_length())} | set(range(64, hi + 1, 32)))
    return min(sizes, key=lambda c: (-(-max(count, 1) // c) * (c + _CONTACT_CHUNK_COST), -c))


def contact_grid(scene: Scene, lighting: Lighting | None = None) -> tuple[int, int]:
    """The (θ, φ) sphere grid of the contact visibility rays (:func:`contact_rows_at_time`).

    Their rows shadow the n-band part of the light only: the environment's SH, which is the rest
    of a lat-long map once its bright part is split into lamps (the lamps, and sphere lights,
    which a split map's ``light_visibility = "images"`` shadows through the images, get exact
    rays of their own there). :data:`CONTACT_GRID_DIM` (a quarter of the rays) where the map is
    split and its rest carries at most :data:`CONTACT_SH_SHARE` of its energy (the rest's SH
    constant term against the bright part's, luminance = mean of RGB); else
    :data:`CONTACT_GRID`, also where the lighting is traced."""
    if lighting is None:
        lighting = scene_lighting(scene)
    if lighting.env_lights is None or lighting.env_bright_sh is None:
        return tuple(CONTACT_GRID)
    rest, bright = _concrete(lighting.env_sh), _concrete(lighting.env_bright_sh)
    if rest is None or bright is None:
        return tuple(CONTACT_GRID)
    rest_dc, bright_dc = float(np.mean(rest[0])), float(np.mean(bright[0]))
    total = rest_dc + bright_dc
    if total > 0 and rest_dc >= 0 and rest_dc <= CONTACT_SH_SHARE * total:
        return tuple(CONTACT_GRID_DIM)
    return tuple(CONTACT_GRID)


def _contact_rows(
    scene: Scene,
    t,
    lighting: Lighting,
    near: Bool[Array, "N m"],
    chunk: int = 32,
    above: bool | None = None,
    grid: tuple[int, int] = CONTACT_GRID,
):
    """The arrays of :func:`contact_rows_at_time` for the mask ``near`` of :func:`_contact_near`,
    the rays in chunks of ``chunk`` receivers (static). ``above`` (static): :func:`_contact_above`
    as known on the host, the visibility rays then over the half of the grid above each receiver's
    plane only (:func:`jshadow.visibility.halfspace_visibility_sh`) or over all of it; None
    (traced): decided in the trace (``lax.cond``). ``grid`` (static): the rays' (θ, φ) sphere
    grid, :func:`contact_grid`."""
    grid = tuple(int(g) for g in grid)
    m = scene.method
    n = m.sh_bands
    # the fixed receivers only (the own vertices that follow them are never near: padded below)
    points, normals = scene.receivers.points, scene.receivers.normals
    n_rec = points.shape[0]
    own = near.shape[0] - n_rec
    near_all, near = near, near[:n_rec]
    dtype = points.dtype
    meshes = [
        (i, occ.vertices(t), occ.faces)
        for i, occ in enumerate(scene.occluders)
        if isinstance(occ, MeshOccluder)
    ]
    spheres = [(occ.center, occ.radius) for occ in scene.occluders if isinstance(occ, SphereOccluder)]
    env = lighting.env_lights
    light_params = tuple((light.center, light.radius) for light in scene.lights)
    chunks = max(1, -(-n_rec // chunk))

    def forward(x):
        pts, nrm, verts, lights, balls = x
        rows = [jnp.zeros((n_rec, n * n), dtype)] * len(scene.occluders)
        flag = _contact_above(scene, t, near_all) if above is None else None
        d, w = sh.sphere_grid(*grid, dtype)
        basis = sh.sh_basis(d, n) * w[:, None]  # (K, n²) quadrature weights folded in
        centres = []
        for (i, _, faces), v in zip(meshes, verts, strict=True):
            centres.append(bounding_sphere(v)[0])

            def half(p, q, v=v, faces=faces):  # the mesh above every near receiver's plane
                return halfspace_visibility_sh(p, q, v, faces, n, grid)

            def whole(p, q, v=v, faces=faces):
                return (1.0 - ray_fan_any_hit(p, d, v, faces).astype(dtype)) @ basis

            def cast_rows(cast, i=i):
                return over_active(cast, near[:, i], (pts, nrm), 0.0, chunks=chunks)

            if above is None:  # traced: decided in the trace
                rows[i] = jax.lax.cond(flag, lambda: cast_rows(half), lambda: cast_rows(whole))
            else:
                rows[i] = cast_rows(half if above else whole)
        any_near = jnp.any(near, -1)

        def blocked(p, dirs, gates=None):
            """(M, K) 1 where the ray from p along dirs (K, 3) or (M, K, 3) is free of every occluder."""
            vis = jnp.ones(p.shape[:1] + dirs.shape[-2:-1], dtype)
            shared = dirs.ndim == 2
            for k, ((_, _, faces), v) in enumerate(zip(meshes, verts, strict=True)):
                free = 1.0 - ray_fan_any_hit(p, dirs, v, faces).astype(dtype)
                vis = vis * (free if gates is None else jnp.where(gates(centres[k])[:, None], free, 1.0))
            for c, r in balls:
                dd = dirs[None] if shared else dirs
                free = 1.0 - ray_sphere_any_hit(p[:, None, :], dd, c, r).astype(dtype)
                vis = vis * (free if gates is None else jnp.where(gates(c)[:, None], free, 1.0))
            return vis

        light_f = None
        if lights and m.light_visibility == "images":  # else the lights are shadowed by the SH
            strata = tuple(m.light_cap)

            def fractions(p, q):
                out = []
                for lc, lr in lights:
                    dx, dy, dz = stratified_cone_components(lc - p, lr, strata)
                    d_l = safe_norm(p - lc)
                    # an occluder counts where its centre is nearer than the light's, as the lookups'
                    vis = blocked(
                        p, jnp.stack([dx, dy, dz], -1), lambda c, p=p, d_l=d_l: safe_norm(p - c) < d_l
                    )
                    cos = jnp.maximum(q[:, 0:1] * dx + q[:, 1:2] * dy + q[:, 2:3] * dz, 0.0)
                    den = jnp.sum(cos, -1)
                    out.append(jnp.where(den > 0, jnp.sum(vis * cos, -1) / jnp.where(den > 0, den, 1.0), 1.0))
                return jnp.stack(out, -1)

            light_f = over_active(fractions, any_near, (pts, nrm), 1.0, chunks=chunks)
        env_f = None
        if env is not None:
            dirs = jax.lax.stop_gradient(env.directions).astype(dtype)
            energy = env.energy.astype(dtype)

            def env_fraction(p, q):
                cos = jnp.maximum(q @ dirs.T, 0.0)
                den = cos @ energy
                num = (cos * blocked(p, dirs)) @ energy
                return jnp.where(den > 0, num / jnp.where(den > 0, den, 1.0), 1.0)

            env_f = over_active(env_fraction, any_near, (pts, nrm), 1.0, chunks=chunks)
        return jnp.stack(rows, 1), light_f, env_f

    x = (points, normals, tuple(v for _, v, _ in meshes), light_params, tuple(spheres))
    rows, light_f, env_f = _no_derivative_guard(forward, x, CONTACT_NO_DERIVATIVE)

    def pad(a, fill):
        if a is None or not own:
            return a
        return jnp.concatenate([a, jnp.full((own, *a.shape[1:]), fill, a.dtype)])

    return near_all, pad(rows, 0.0), pad(light_f, 1.0), pad(env_f, 1.0)


_contact_near_jit = eqx.filter_jit(_contact_near)
_contact_above_jit = eqx.filter_jit(_contact_above)
_contact_rows_jit = eqx.filter_jit(_contact_rows)


def contact_ray_tests(
    occluders: Sequence,
    points: Float[Array, "N 3"],
    rays: int,
    times: Sequence[float] = (0.0, 1 / 3, 2 / 3, 1.0),
) -> float:
    """Ray–triangle tests a frame's contact rows take (:func:`contact_rows_at_time`): per mesh
    occluder, its receivers among ``points`` near it (:data:`CONTACT_REACH`), rounded up to the
    chunks of rows the rays run on, times ``rays`` per receiver times its faces; summed over the
    meshes, the most over ``times`` of the animation. inf where a mesh or ``points`` is traced."""
    if _concrete(points) is None:
        return math.inf
    worst = 0.0
    for t in times:
        total = 0.0
        for occ in occluders:
            if not isinstance(occ, MeshOccluder):
                continue
            v, f = _vertices_at(occ, jnp.float32(t)), _concrete(occ.faces)
            if _concrete(v) is None or f is None:
                return math.inf
            near = int(jnp.sum(_near_mesh_jit(jnp.asarray(points, v.dtype), v, _large_faces(occ))))
            chunk = _contact_chunk(near)
            total += -(-near // chunk) * chunk * rays * f.shape[0]
        worst = max(worst, total)
    return worst


def contact_rows_at_time(scene: Scene, t, lighting: Lighting | None = None) -> tuple | None:
    """``(near, rows, lights, env)`` of the receivers next to a mesh occluder at time t, or None
    where the scene does not use them (:func:`uses_contact`) or, at a concrete pose, no receiver is
    that near.

    A fixed receiver (``scene.receivers``; not an occluder's own vertex) is *near* mesh occluder i
    when one of the mesh's vertices, or one of its faces larger than about the reach
    (:func:`_large_faces`), lies within :data:`CONTACT_REACH` × its bounding radius. The
    field extrapolates a mesh's visibility inward from its shell (1.5 radii by default), which fails
    at a contact: a mesh just above its floor. There, instead:

    * ``rows`` (N, m, n²): mesh i's visibility SH cast by rays along a sphere grid
      (Gauss–Legendre × uniform quadrature; :data:`CONTACT_GRID`, or :data:`CONTACT_GRID_DIM` where
      the n-band path carries little of the light, :func:`contact_grid`), in place of its field's
      (:func:`occluder_visibilities`, with ``near`` (N, m) bool saying where);
    * ``lights`` (N, L): each sphere light's cosine-weighted visible fraction over the same
      ``method.light_cap`` cap directions as :func:`light_visible_fractions`, by exact rays against
      every occluder (None without sphere lights or with ``light_visibility = "sh"``, where the
      visibility SH shadows them);
    * ``env`` (N, 3): the environment lights' visible fraction as
      :func:`environment_visible_fraction` forms it, by exact rays (None without them);

    both in place of the images' lookups (:func:`image_fractions`) at receivers near any mesh.
    Rows of other receivers are 0 (``rows``) or 1 and are not read. The nearest-vertex test, the
    rays and the fractions run only on chunks holding a receiver that needs them
    (:func:`jshadow._active.over_active`). Where every mesh lies on or above the tangent plane of
    each near receiver (a floor under them), the visibility rays are cast over the half of the grid
    above that plane only, the rest free (:func:`jshadow.visibility.halfspace_visibility_sh`: the
    same rule, turned, at half the rays). Binary visibility: differentiating with
    respect to the meshes, the receivers or the lights raises :data:`CONTACT_NO_DERIVATIVE`.
    """
    if not uses_contact(scene):
        return None
    if lighting is None:
        lighting = scene_lighting(scene)
    t = jnp.asarray(t, scene.receivers.points.dtype)
    large = tuple(_large_faces(o) if isinstance(o, MeshOccluder) else None for o in scene.occluders)
    near = _contact_near_jit(scene, t, large)
    concrete = _concrete(near)
    if concrete is not None and not concrete.any():
        return None  # no ray stage at all
    count = None if concrete is None else int(concrete.any(-1).sum())
    above = None
    if concrete is not None:  # else decided in the trace
        above = _concrete(_contact_above_jit(scene, t, near))
        above = None if above is None else bool(above)
    grid = contact_grid(scene, lighting)
    return _contact_rows_jit(scene, t, lighting, near, _contact_chunk(count), above, grid)


# BSV occluders of one coefficient shape up to this many are traced one by one; more share one
# lax.map body (compile time that does not grow with their number)
_UNROLLED_FIELDS = 16


def occluder_visibilities(
    scene: Scene,
    bsvs: tuple[BSV | None, ...],
    points: Float[Array, "N 3"],
    own: tuple[Float[Array, "N n2"], Array] | None = None,
    plane_first: bool = False,
    contact: tuple | None = None,
) -> tuple[list, list]:
    """Visibility SH (N, n²) and distance (N,) from each receiver to each occluder's centre.

    BSV occluders are traced one by one up to ``_UNROLLED_FIELDS`` (16) of one coefficient shape;
    more are evaluated together under one ``lax.map`` (one compiled body however many there are:
    compile time bounded, run time about 1.3x).

    ``plane_first``: ``points`` are :func:`jshadow.entities.receivers_at_time`'s, the plane's
    receivers (``scene.receivers.points``) first. When own vertices follow them, the BSV fields of
    the plane (read from ``scene.receivers.points`` itself) and of the vertices are evaluated as two
    calls (same values): the plane's points do not move, and neither does a placed BSV centre, so
    reverse mode finds no derivative for the plane's interpolation cells and frame rotations and
    skips their transposes (in one call, or sliced from ``points``, every receiver carries the moving
    vertices' derivative). The animated bunny's frame value_and_grad: BENCHMARKS.md, "BSV gradients".

    ``own``: None, or ``(rows, owners)`` — (N, n²) and (N,) int — from :func:`own_rows_at_time`
    (or a piece of them, sliced like ``points``): receiver r's visibility of occluder
    ``owners[r]`` is 1 instead of the field's, its cast transfer ``rows[r]`` standing for its
    clamped cosine in :func:`combine` (``self_visibility = "rays"``; rows None: the field's
    throughout).

    ``contact``: None, or :func:`contact_rows_at_time`'s tuple (or a piece of it, sliced like
    ``points``): where ``near[r, i]``, receiver r's visibility of mesh occluder i is the cast
    ``rows[r, i]`` instead of the field's.
    """
    n = scene.method.sh_bands
    table = occlusion_table(scene) if any(b is not None for b in bsvs) else None
    vis: list = [None] * len(bsvs)
    dist: list = [None] * len(bsvs)
    groups: dict = {}
    for i, (occ, b) in enumerate(zip(scene.occluders, bsvs, strict=True)):
        if b is None:
            vis[i] = sphere_visibility_sh(occ.center, occ.radius, points, n)
            dist[i] = safe_norm(points - occ.center)
        else:
            groups.setdefault(b.coeffs.shape, []).append(i)
    fixed = scene.receivers.points.shape[0] if plane_first else 0
    if fixed > points.shape[0]:
        raise ValueError(
            f"plane_first: points ({points.shape[0]}) must begin with the scene's {fixed} plane receivers"
        )
    if 0 < fixed < points.shape[0]:
        pieces = [jnp.asarray(scene.receivers.points, points.dtype), points[fixed:]]
    else:
        pieces = [points]

    def field(b):
        out = [_field_or_unit(b, table, p, n) for p in pieces]
        return tuple(jnp.concatenate(x, 0) if len(x) > 1 else x[0] for x in zip(*out))

    for idx in groups.values():
        if len(idx) <= _UNROLLED_FIELDS:
            # one traced field per occluder: 0.72x (4 occluders) and 0.79x (16) the time of the
            # lax.map below, field and product chain, on XLA:CPU (BENCHMARKS.md, "Many occluders")
            for i in idx:
                vis[i], dist[i] = field(bsvs[i])
            continue
        stacked = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *[bsvs[i] for i in idx])
        # lax.map, not vmap: batching the field's gathers and small matmuls over occluders was slower
        # on XLA:CPU than one occluder after another (bench_render.py, 16 occluders: field 88 -> 65 ms)
        vs, ds = jax.lax.map(field, stacked)
        for j, i in enumerate(idx):
            vis[i], dist[i] = vs[j], ds[j]
    if own is not None and own[0] is not None:
        # the own vertices' cast rows are their transfer (combine takes them for the clamped
        # cosine): their own occluder's visibility there is 1
        owners = own[1]
        for i, occ in enumerate(scene.occluders):
            if isinstance(occ, MeshOccluder):
                unit = unit_visibility((1,), n, vis[i].dtype)
                vis[i] = jnp.where((owners == i)[:, None], unit, vis[i])
    if contact is not None:
        near, rows = contact[0], contact[1]
        for i, occ in enumerate(scene.occluders):
            if isinstance(occ, MeshOccluder):
                vis[i] = jnp.where(near[:, i, None], rows[:, i].astype(vis[i].dtype), vis[i])
    return vis, dist


def _reaches(b: BSV, table: MkTable, points: Float[Array, "N 3"]) -> Bool[Array, ""]:
    """Whether any receiver is within a BSV occluder's range (the table's largest distance: the
    field's ``mk_in_range``, here generous by a relative 1e-4); where none is, its visibility is 1
    at every receiver and its field is not evaluated (a ``lax.cond``: a far occluder costs one pass
    over the receivers' distances)."""
    rel = points - b.center
    d2 = rel[:, 0] * rel[:, 0] + rel[:, 1] * rel[:, 1] + rel[:, 2] * rel[:, 2]
    reach = b.shell_radius * (1.0 + 1e-4) / table.ks[0].astype(d2.dtype)
    return jnp.any(d2 <= reach * reach)


def _field_or_unit(b: BSV, table: MkTable, p: Float[Array, "N 3"], n: int) -> tuple[Array, Array]:
    """:func:`bsv_visibility_and_distance`, or visibility 1 and the distances (computed as the field
    computes them) where no receiver is within the occluder's range (:func:`_reaches`)."""

    def far(b, p):
        rel = p - b.center
        x, y, z = rel[:, 0], rel[:, 1], rel[:, 2]
        return unit_visibility((p.shape[0],), n, p.dtype), safe_sqrt(x * x + y * y + z * z)

    return jax.lax.cond(
        _reaches(b, table, p), lambda b, p: bsv_visibility_and_distance(b, table, p, n), far, b, p
    )


def _product(vs: list) -> Float[Array, "N n2"] | None:
    """SH product of several visibilities, truncated to n bands after every factor.

    Computed with the coefficient axis first (:func:`jshadow.sh.sh_product_t`). Each product is a
    stage (:func:`jshadow.visibility._edgescan.staged`): its operands are buffers. Without that,
    XLA:CPU fused the producers of a product (the fields' gathers and rotations) into it and
    recomputed them for every term: 4 sphere occluders with the last product split off
    (:func:`combine`) took 12.1 ms with the other three multiplied inline, 7.6 ms staged
    (BENCHMARKS.md, "Many occluders"). Up to ``_UNROLLED_FIELDS`` factors
    are multiplied one after another (no stacked copy of all of them); more go through one
    ``lax.scan`` (compiled once, however many there are).
    """
    if not vs:
        return None
    if len(vs) == 1:
        return vs[0]
    live = always(vs[0])
    if len(vs) > _UNROLLED_FIELDS:

        def chain(first, rest):
            return jax.lax.scan(lambda a, v: (sh.sh_product_t(a, v), None), first.T, rest)[0].T

        return staged(live, chain, vs[0], jnp.swapaxes(jnp.stack(vs[1:]), 1, 2))
    acc = vs[0].T
    for v in vs[1:]:
        acc = staged(live, sh.sh_product_t, acc, v.T)
    return acc.T


def uses_visibility_chain(
    scene: Scene, own=None, images=None, lighting: Lighting | None = None, contact=None
) -> bool:
    """Whether :func:`visibility_chain` can stand for :func:`occluder_visibilities` in a frame's
    combination: an environment, no sphere lights, no own-vertex or contact rows, occlusion images
    or environment lights (only the product of all visibilities is needed then), and 2 to
    ``_UNROLLED_FIELDS`` occluders."""
    env_lights = None if lighting is None else lighting.env_lights
    return (
        scene.environment is not None
        and not scene.lights
        and own is None
        and contact is None
        and images is None
        and env_lights is None
        and 2 <= len(scene.occluders) <= _UNROLLED_FIELDS
    )


def visibility_chain(
    scene: Scene, bsvs: tuple[BSV | None, ...], points: Float[Array, "N 3"]
) -> tuple[Float[Array, "N n2"], Float[Array, "N n2"]]:
    """``(rest, last)``: the product of all but the last occluder's visibility (as :func:`_product`)
    and the last one's, each visibility made just before it is multiplied in (one stage per
    occluder: field and product). :func:`combine` takes them as ``env_visibility``
    (:func:`uses_visibility_chain` says when). The numbers are those of :func:`occluder_visibilities`
    and :func:`_product`; only the order differs: made all at once, 16 occluders' visibilities over
    25600 receivers (26 MB) left the caches, and the fields took 2.1 instead of 1.2 ms each
    (BENCHMARKS.md, "Many occluders")."""
    n = scene.method.sh_bands
    table = occlusion_table(scene) if any(b is not None for b in bsvs) else None

    def visibility(occ, b, p):
        if b is None:
            return sphere_visibility_sh(occ.center, occ.radius, p, n)
        return bsv_visibility_and_distance(b, table, p, n)[0]

    def field(acc, occ, b, p):
        # acc passes through (the other branch of the stage gives zeros, so XLA cannot forward
        # it): the field waits for the product before it, and its result is a buffer, not fused
        # into the product and recomputed per term
        return visibility(occ, b, p), acc

    def step(acc, occ, b, p):
        v, acc = staged(live, field, acc, occ, b, p)
        return staged(live, sh.sh_product_t, acc, v.T)

    def unit(acc, occ, b, p):
        return unit_visibility((p.shape[0],), n, p.dtype), acc

    def skip(acc, occ, b, p):
        return acc

    # a BSV occluder with no receiver in range is skipped (visibility 1, no field, no product)
    live = always(points)
    occs = scene.occluders
    reaches = [live if b is None else _reaches(b, table, points) for b in bsvs]
    acc = jax.lax.cond(reaches[0], field, unit, None, occs[0], bsvs[0], points)[0].T
    for occ, b, r in zip(occs[1:-1], bsvs[1:-1], reaches[1:-1], strict=True):
        acc = jax.lax.cond(r, step, skip, acc, occ, b, points)
    v, acc = jax.lax.cond(reaches[-1], field, unit, acc, occs[-1], bsvs[-1], points)
    return acc.T, v


class Lighting(eqx.Module):
    """Per-scene lighting constants of :func:`combine` (computed once, reused for every frame).

    ``env_sh``: the environment's n-band SH (n², 3); ``env_map``: its unoccluded irradiance over
    normals (only for ``shading="ratio"``). Both None without an environment. ``env_lights``: with
    :func:`uses_environment_lights`, the map's bright part as distant lights
    (:func:`jshadow.envlights.split_environment`) and ``env_bright_sh`` its n-band SH (for the
    receivers the images cannot serve); then ``env_sh`` and ``env_map`` are those of the rest.
    Else both None.
    """

    env_sh: Float[Array, "n2 3"] | None
    env_map: IrradianceMap | None
    env_lights: EnvironmentLights | None = None
    env_bright_sh: Float[Array, "n2 3"] | None = None


_LIGHTING: list = []  # [(environment leaves, options, numpy Lighting)], most recent last


def scene_lighting(scene: Scene) -> Lighting:
    """The lighting constants of the scene's environment (see :class:`Lighting`).

    When the environment is concrete (also when a traced function closes over the scene), they are
    computed eagerly once per environment object and enter a trace as constants: tabulating the
    irradiance map inside a trace left XLA to constant-fold a 2112 × 8192 product on every compile
    (2–3 s). A traced environment (differentiating with respect to its radiance or image) is
    computed in the trace.
    """
    env = scene.environment
    if env is None:
        return Lighting(env_sh=None, env_map=None)
    n, ratio = scene.method.sh_bands, scene.method.shading == "ratio"
    split = uses_environment_lights(scene)
    m = scene.method

    def compute():
        rest, lights = (
            split_environment(env, m.environment_lights, m.environment_threshold) if split else (env, None)
        )
        env_sh = environment_sh(rest, n).astype(scene.dtype)
        env_map = environment_irradiance_map(rest) if ratio else None
        if lights is None:
            return Lighting(env_sh=env_sh, env_map=env_map)
        bright = environment_sh(env, n).astype(scene.dtype) - env_sh  # linear: the bright part's SH
        return Lighting(env_sh=env_sh, env_map=env_map, env_lights=lights, env_bright_sh=bright)

    leaves = jax.tree.leaves(env)
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        return compute()
    options = (
        n,
        ratio,
        str(np.dtype(scene.dtype)),
        split and (m.environment_lights, m.environment_threshold),
    )
    hits = [
        value
        for cached, opts, value in _LIGHTING
        if opts == options and len(cached) == len(leaves) and all(a is b for a, b in zip(cached, leaves))
    ]
    if not hits:
        with jax.ensure_compile_time_eval():
            hits = [jax.tree.map(np.asarray, compute())]
        _LIGHTING.append((leaves, options, hits[0]))
        del _LIGHTING[:-8]
    return jax.tree.map(jnp.asarray, hits[0])


def _shadow_ratio(occluded, unoccluded, exact):
    """Exact unoccluded irradiance times the SH estimate's occluded/unoccluded ratio, in [0, 1].

    Where the n-band unoccluded estimate is not a usable denominator (below a quarter of the exact
    value: a light at the horizon, a dark part of the sky) the SH shadow is subtracted instead;
    either way the result lies in [0, exact].
    """
    ok = unoccluded > 0.25 * exact
    ratio = jnp.clip(occluded / jnp.where(ok, unoccluded, 1.0), 0.0, 1.0)
    shifted = jnp.clip(exact + occluded - unoccluded, 0.0, jnp.maximum(exact, 0.0))
    return jnp.where(ok, exact * ratio, shifted)


def shared_normal_count(normals) -> int:
    """How many leading receivers have exactly the normal of receiver 0 (0 if ``normals`` is traced).

    A receiver plane comes first in every scene (:func:`jshadow.entities.receivers_at_time`) and all
    its vertices share one normal; :func:`combine` computes their normal-dependent terms once.
    """
    nrm = _concrete(normals)
    if nrm is None or nrm.shape[0] == 0:
        return 0
    same = np.all(nrm == nrm[:1], axis=-1)
    return int(nrm.shape[0] if same.all() else np.argmin(same))


def _stack_groups(groups, values):
    """Rows of every receiver from per-group values (a (1, ·) value is broadcast over its group)."""
    rows = [jnp.broadcast_to(v, (b - a, *v.shape[1:])) for (a, b, _), v in zip(groups, values, strict=True)]
    return jnp.concatenate(rows, 0) if len(rows) > 1 else rows[0]


def _env_rows(v: Float[Array, "N n2"], m_env: Float[Array, "3 n2 n2"], t: Float[Array, "N n2"]):
    """``Σ_ik v_i M_env[c, i, k] t_k`` per receiver (N, 3): one (N, n²)·(n², 3n²) GEMM, then the
    row-wise dots with t as a second GEMM with a constant 0/1 block matrix. An einsum over the
    three operands compiled to a batched (1 × n²)·(n² × 3) product per receiver on XLA:CPU: 1e5
    receivers 18.4 → 2.3 ms (``benchmarks/bench_sh.py``), 1901 receivers 185 → 75–104 µs."""
    n2 = v.shape[-1]
    y = v @ jnp.transpose(m_env, (1, 0, 2)).reshape(n2, 3 * n2)  # (N, 3n²): channel-major
    blocks = jnp.asarray(np.kron(np.eye(3), np.ones((n2, 1))), v.dtype)  # (3n², 3)
    return (y * jnp.tile(t, (1, 3))) @ blocks


def combine(
    scene: Scene,
    points: Float[Array, "N 3"],
    normals: Float[Array, "N 3"],
    vis: list,
    dist: list,
    lighting: Lighting | None = None,
    analytic_spheres: bool = True,
    shared_normal: int = 0,
    light_fractions: list | None = None,
    env_fraction: tuple[Float[Array, "N 3"], Bool[Array, " N"]] | None = None,
    env_visibility: tuple[Float[Array, "N n2"], Float[Array, "N n2"]] | None = None,
    own: tuple[Array, ...] | None = None,
) -> Float[Array, "N 3"]:
    """Irradiance (N, 3) from the occluders' visibilities and the scene's lights.

    Cost per receiver: the environment's term is ``Σ_ik V_i M_env[c, i, k] T_k`` with the constant
    matrix of "multiply by L_env" (no per-receiver triple product); a sphere light's radiance is a
    scalar cap times a colour, so its product with the transfer is one scalar triple product;
    visibilities multiply pairwise (one triple product per extra occluder).

    ``method.shading``: "product" is Zhou et al. 2005 (every term an n-band SH product). "ratio"
    multiplies the *exact* unoccluded irradiance of each light (closed form for sphere lights, a
    tabulated irradiance map for the environment) by the SH estimate's occluded/unoccluded ratio,
    clamped to [0, 1]: unoccluded receivers are exact, no receiver is brighter than unoccluded, and
    the n-band truncation of sharp lighting cancels in the ratio. ``lighting`` (from
    :func:`scene_lighting`) is computed here when not given. With ``analytic_spheres`` (the
    analytic sphere path) the part of a sphere light hidden by a sphere occluder is exact
    (:func:`jshadow.field.sphere_light_blocked`, multiplied over such occluders) instead of an
    n-band product, which cannot hold the sharp shadow of a small light.

    ``shared_normal`` (static): the first ``shared_normal`` receivers have exactly the normal of
    receiver 0 (a plane; :func:`shared_normal_count`). What depends on the normal alone is then
    computed once for all of them — the transfer T₀, the unoccluded environment irradiance, the
    environment's shading vectors ``w_c = M_env[c] T₀`` (each receiver's environment term becomes
    one n²×3 product ``V · w``) and the matrix P(T₀) of "multiply by T₀": a sphere light's
    ``⟨V, T ⊛ cap⟩`` becomes ``⟨V P(T₀), cap⟩``, one n²×n² product and a fused polynomial per
    receiver (:func:`jshadow.lights.sphere_light_dot`; the light's (N, n²) coefficients are never
    stored), instead of a triple product: the same numbers up to rounding, 1.8–3.5× less
    combination time per frame of the shipped configs, and the fused dot another 0.70–0.78× of the
    whole shading call of the configs with a sphere light (BENCHMARKS.md, "Rendering"). Their
    normals' cotangents all flow to receiver 0.

    ``light_fractions`` (``method.light_visibility = "images"``): per sphere light, the visible
    fraction (N,) of :func:`light_visible_fractions`; each light's term is then its exact unoccluded
    irradiance times that fraction, whatever the shading, and ``vis`` serves the environment only.
    With ``lighting.env_lights`` (:func:`uses_environment_lights`) the environment's SH terms are
    those of its rest, and its bright part adds its exact unoccluded irradiance times the visible
    fraction of ``env_fraction`` = ``(F, inside)`` from :func:`environment_visible_fraction`
    (required then); at ``inside`` receivers the bright part takes the environment's n-band path
    (with ``lighting.env_bright_sh``) instead.

    ``env_visibility``: ``(rest, last)`` of :func:`visibility_chain`, in place of ``vis`` (then
    empty; the scene must pass :func:`uses_visibility_chain`). With several occluders the
    environment's term needs only ``⟨V₁ ⊛ … ⊛ V_m, w_c⟩ = restᵀ P(w_c) last`` (P(w) "multiply by
    w", symmetric): one GEMM for the shared-normal rows instead of the last triple product.

    ``own``: the tuple of :func:`own_rows_at_time` (sliced like ``points``) or None. With cast rows
    (``self_visibility = "rays"``) each own vertex's occluded SH terms take its cast transfer
    ``rows[r]`` (:func:`occluder_own_visibility`) in place of its clamped cosine (its own
    occluder's visibility in ``vis`` is then 1, :func:`occluder_visibilities`); the unoccluded
    terms of ratio shading keep the clamped cosine.
    """
    n = scene.method.sh_bands
    ratio = scene.method.shading == "ratio"
    dtype = points.dtype
    if lighting is None:
        lighting = scene_lighting(scene)
    n_rec = points.shape[0]
    shared = min(max(int(shared_normal), 0), n_rec)
    # receivers [0, shared) share normal 0: their terms are computed from one (1, ·) transfer row
    groups = ((0, n_rec, normals),)  # (start, stop, normals)
    if shared:
        both = ((0, shared, normals[:1]), (shared, n_rec, normals[shared:]))
        groups = tuple(g for g in both if g[1] > g[0])
    transfers = [sh.clamped_cosine(nrm, n) for _, _, nrm in groups]  # max(0, n·ω): (1 or rows, n²)
    # the occluded terms' transfers: an own vertex's cast transfer where the scene casts them
    occ_transfers = transfers
    if own is not None and own[0] is not None:
        rows, mine = own[0].astype(dtype), own[1] >= 0
        occ_transfers = [
            t if t.shape[0] == 1 else jnp.where(mine[a:b, None], rows[a:b], t)
            for (a, b, _), t in zip(groups, transfers, strict=True)
        ]

    def by_group(x, shared_fn, row_fn, finish=lambda part, k: part):
        """(N, ·) rows from per-receiver ``x`` (N, ·): ``shared_fn(x, T₀)`` for a shared-normal group
        (on all rows, then sliced: XLA:CPU copies a sliced GEMM operand first), ``row_fn(x_rows, T)``
        for a group with a normal per row; ``finish(part, k)`` of group k before the concatenation
        (so that a group's shared (1, ·) terms broadcast instead of being stored per row)."""
        parts = [
            finish(shared_fn(x, t[0])[a:b] if t.shape[0] == 1 else row_fn(x[a:b], t), k)
            for k, ((a, b, _), t) in enumerate(zip(groups, occ_transfers, strict=True))
        ]
        return jnp.concatenate(parts, 0) if len(parts) > 1 else parts[0]

    e = jnp.zeros((n_rec, 3), dtype)
    exact_blockers = [
        ratio and analytic_spheres and isinstance(occ, SphereOccluder) for occ in scene.occluders
    ]
    # the environment needs only ⟨V₁ ⊛ … ⊛ V_m, w_c⟩: with several occluders the last product is a
    # bilinear form, ⟨a ⊛ b, w⟩ = aᵀ P(w) b (P(w) "multiply by w", symmetric), one GEMM for the
    # shared-normal rows instead of a triple product (the bright part of a split map reuses the
    # full product, so not with environment lights)
    split_last = len(vis) >= 2 and lighting.env_lights is None
    v_all = None
    if env_visibility is not None:
        if vis or not uses_visibility_chain(scene, lighting=lighting):
            raise ValueError(
                "combine: env_visibility stands for vis (pass vis=[]) in scenes of uses_visibility_chain"
            )
        v_all = tuple(env_visibility)
    elif scene.environment is not None:
        v_all = (_product(vis[:-1]), vis[-1]) if split_last else _product(vis)

    def env_term(l_env, env_map):
        """The environment's n-band term (N, 3) for SH radiance ``l_env`` (n², 3) whose exact
        unoccluded irradiance is ``env_map`` (ratio shading)."""
        # per group, (1, 3) for a shared normal: the exact unoccluded irradiance (ratio shading) and
        # the n-band double product, which is exact for n-band lighting
        exact = [environment_irradiance(env_map, nrm).astype(dtype) for _, _, nrm in groups] if ratio else []
        unoccluded = [t @ l_env for t in transfers]

        def finish(occluded, k):
            return _shadow_ratio(occluded, unoccluded[k], exact[k]) if ratio else occluded

        if v_all is None:
            return _stack_groups(groups, exact if ratio else unoccluded)
        m_env = sh.product_matrix(l_env.T)  # (3, n², n²): "multiply by L_env", per channel
        if isinstance(v_all, tuple):
            rest, last = v_all
            parts = []
            for k, ((a, b, _), t) in enumerate(zip(groups, occ_transfers, strict=True)):
                if t.shape[0] == 1:  # Σ_ij rest_i P(w_c)_ij last_j with w_c = M_env[c] T₀
                    w = jnp.einsum("cik,k->ci", m_env, t[0])
                    part = _env_rows(rest, sh.product_matrix(w), last)[a:b]
                else:
                    prod = staged(always(t), sh.sh_product, rest[a:b], last[a:b])  # operands as buffers
                    part = _env_rows(prod, m_env, t)
                parts.append(finish(part, k))
            return jnp.concatenate(parts, 0) if len(parts) > 1 else parts[0]
        # Σ_ik V_i M_env[c, i, k] T_k = V · w_c with the shading vector w_c = M_env[c] T
        return by_group(
            v_all,
            lambda v, t0: v @ jnp.einsum("cik,k->ic", m_env, t0),
            lambda v, t: _env_rows(v, m_env, t),
            finish,
        )

    if scene.environment is not None:
        e = e + env_term(lighting.env_sh.astype(dtype), lighting.env_map)

    env_lights = lighting.env_lights
    if env_lights is not None:
        if env_fraction is None:
            raise ValueError("combine: the lighting splits the environment; pass env_fraction")
        fraction, inside = env_fraction
        bright = environment_irradiance(env_lights.unoccluded, normals).astype(dtype) * fraction
        fallback = env_term(lighting.env_bright_sh.astype(dtype), env_lights.unoccluded)
        e = e + jnp.where(inside[:, None], fallback, bright)

    for j, light in enumerate(scene.lights):
        one = jnp.ones((1,), dtype)
        if light_fractions is not None:
            exact = sphere_light_irradiance(light.center, light.radius, one, points, normals)
            e = e + exact * light_fractions[j][:, None].astype(dtype) * light.radiance
            continue
        if ratio:
            exact = sphere_light_irradiance(light.center, light.radius, one, points, normals)
        if ratio and not vis:
            e = e + exact * light.radiance
            continue

        def cap_rows(a, b, light=light, one=one):
            return sphere_light_sh(light.center, light.radius, one, points[a:b], n)[..., 0]  # (rows, n²)

        def light_dot(a, b, w, light=light):
            # Σ_i cap_i w_i, one fused pass (the light's (rows, n²) coefficients never stored)
            return sphere_light_dot(light.center, light.radius, points[a:b], w, n)[:, None]

        caps = {
            k: cap_rows(a, b) for k, ((a, b, _), t) in enumerate(zip(groups, transfers)) if t.shape[0] > 1
        }
        unoccluded = jnp.concatenate(
            [
                light_dot(a, b, t[0]) if t.shape[0] == 1 else jnp.sum(t * caps[k], -1, keepdims=True)
                for k, ((a, b, _), t) in enumerate(zip(groups, transfers, strict=True))
            ],
            0,
        )
        if not vis:
            e = e + unoccluded * light.radiance
            continue
        d_l = safe_norm(points - light.center)
        near = [(vj, dj < d_l) for vj, dj, ex in zip(vis, dist, exact_blockers, strict=True) if not ex]
        visible = jnp.ones((points.shape[0], 1), dtype)
        for occ, dj, ex in zip(scene.occluders, dist, exact_blockers, strict=True):
            if ex:
                hidden = sphere_light_blocked(occ.center, occ.radius, light.center, light.radius, points)
                visible = visible * jnp.where(dj < d_l, 1.0 - hidden, 1.0)[:, None]
        if near:
            unit = unit_visibility((points.shape[0],), n, dtype)
            v_near = None if len(near) == 1 else _product([jnp.where(m[:, None], vj, unit) for vj, m in near])
            parts = []
            for k, ((a, b, _), t) in enumerate(zip(groups, occ_transfers, strict=True)):
                if t.shape[0] == 1:
                    # ⟨V, T₀ ⊛ cap⟩ = ⟨V P(T₀), cap⟩ with P(T₀) the matrix of "multiply by T₀": one
                    # GEMM, then the light's fused dot; one occluder selects after the GEMM (V ↦ V P
                    # is linear, and the unit visibility's row is √(4π) P₀)
                    pm = sh.product_matrix(t[0])
                    if v_near is None:
                        vj, m = near[0]
                        w = jnp.where(m[:, None], vj @ pm, math.sqrt(4.0 * math.pi) * pm[0])
                    else:
                        w = v_near @ pm
                    parts.append(light_dot(a, b, w[a:b]))
                else:
                    v_rows = (
                        jnp.where(near[0][1][a:b, None], near[0][0][a:b], unit[a:b])
                        if v_near is None
                        else v_near[a:b]
                    )
                    parts.append(jnp.sum(v_rows * sh.sh_product(t, caps[k]), -1, keepdims=True))
            occluded = jnp.concatenate(parts, 0) if len(parts) > 1 else parts[0]
            occluded = _shadow_ratio(occluded, unoccluded, exact) if ratio else occluded
        else:
            occluded = exact
        e = e + occluded * visible * light.radiance
    return e


def image_fractions(
    scene: Scene,
    images: tuple[OcclusionImages | None, ...] | None,
    lighting: Lighting,
    points: Float[Array, "N 3"],
    normals: Float[Array, "N 3"],
    own: tuple[Array, ...] | None = None,
    contact: tuple | None = None,
) -> tuple[list | None, tuple[Float[Array, "N 3"], Bool[Array, " N"]] | None]:
    """The visible fractions :func:`combine` takes from the occlusion images: of each sphere light
    (:func:`light_visible_fractions`, None without sphere lights) and of the environment's bright
    part (:func:`environment_visible_fraction` with ``own``, None unless ``lighting.env_lights``);
    both None when ``images`` is None. With ``contact`` (:func:`contact_rows_at_time`'s tuple,
    sliced like ``points``), the receivers near a mesh take its exact fractions instead (and are
    not ``inside``)."""
    if images is None:
        return None, None
    fractions = light_visible_fractions(scene, images, points, normals) if scene.lights else None
    env = lighting.env_lights
    env_fraction = (
        None if env is None else environment_visible_fraction(scene, images, env, points, normals, own)
    )
    if contact is not None:
        near, _, light_f, env_f = contact
        hit = jnp.any(near, -1)
        if fractions is not None and light_f is not None:
            fractions = [jnp.where(hit, light_f[:, j].astype(f.dtype), f) for j, f in enumerate(fractions)]
        if env_fraction is not None and env_f is not None:
            f, inside = env_fraction
            env_fraction = (jnp.where(hit[:, None], env_f.astype(f.dtype), f), inside & ~hit)
    return fractions, env_fraction


_CONTACT: list = []  # [(key, contact rows)] of concrete scenes and times, most recent last (at most 4)


def _kept_contact_rows(scene: Scene, t, lighting: Lighting) -> tuple | None:
    """:func:`contact_rows_at_time`, kept for :func:`render_at` called again on the same concrete
    scene, time and lighting (the last 4; :class:`jshadow.Renderer` keeps its own): keyed by the
    pytrees' structure and a digest of every leaf's bytes, with the contact constants. Anything
    traced: made anew, nothing kept."""
    if not uses_contact(scene):
        return None
    leaves, tree = jax.tree_util.tree_flatten((scene, lighting, t))
    arrays = [_concrete(x) if isinstance(x, (jax.Array, np.ndarray)) else x for x in leaves]
    if any(a is None for a in arrays):
        return contact_rows_at_time(scene, t, lighting)
    digest = hashlib.blake2b(digest_size=16)
    for a in arrays:
        if isinstance(a, np.ndarray):
            digest.update(repr((a.shape, str(a.dtype))).encode())
            digest.update(np.ascontiguousarray(a).tobytes())
        else:
            digest.update(repr(a).encode())
    key = (
        tree,
        digest.digest(),
        CONTACT_REACH,
        CONTACT_GRID,
        CONTACT_GRID_DIM,
        CONTACT_SH_SHARE,
        CONTACT_LARGE_FACE,
    )
    hit = [rows for k, rows in _CONTACT if k == key]
    if hit:
        return hit[0]
    rows = contact_rows_at_time(scene, t, lighting)
    _CONTACT.append((key, rows))
    del _CONTACT[:-4]
    return rows


def render_at(
    scene: Scene,
    t,
    bsvs: tuple[BSV | None, ...] | None = None,
    sphere_path="analytic",
    images: tuple[OcclusionImages | None, ...] | None = None,
):
    """Render at animation time t ∈ [0, 1] (see :func:`render`). ``bsvs`` (and with them
    ``images``, for ``light_visibility = "images"``) may be given, as :func:`scene_bsvs_and_images`
    makes them, to share them between renderings of the same occluders; else they are made here."""
    if bsvs is None and images is not None:
        raise ValueError(
            "render_at: images are given together with the bsvs they were made with (scene_bsvs_and_images)"
        )
    own = own_rows_at_time(scene, t)  # first: differentiating it raises before the BSVs are traced
    if bsvs is None:
        bsvs, images = scene_bsvs_and_images(scene, t, sphere_path)
    elif images is None:
        images = scene_images(scene, t)
    images = with_lamp_images(scene, t, images)
    points, normals = receivers_at_time(scene, t)
    lighting = scene_lighting(scene)
    contact = _kept_contact_rows(scene, t, lighting)
    vis, dist = occluder_visibilities(scene, bsvs, points, own, plane_first=True, contact=contact)
    shared = shared_normal_count(scene.receivers.normals)  # the plane's receivers lead `points`
    fractions, env_fraction = image_fractions(scene, images, lighting, points, normals, own, contact)
    e = combine(
        scene,
        points,
        normals,
        vis,
        dist,
        lighting,
        analytic_spheres=sphere_path == "analytic",
        shared_normal=shared,
        light_fractions=fractions,
        env_fraction=env_fraction,
        own=own,
    )
    radiance = e * (scene.receivers.albedo / math.pi)
    return RenderResult(points=points, normals=normals, irradiance=e, radiance=radiance)


def render(scene: Scene, frame: int = 0, sphere_path: str = "analytic") -> RenderResult:
    """Shadow-field rendering of one frame: irradiance and radiance at every receiver.

    Differentiable with respect to the scene's array leaves (light and occluder positions, radii,
    radiance, deformation amounts — but see the visibility module about gradients through binary
    visibility). Receivers are those of :func:`jshadow.entities.receivers_at`, in the same order.
    With ``self_shadow`` and ``method.self_visibility = "rays"`` the occluders' own-vertex
    visibility is cast for every pose not seen before (seconds for a 2k-vertex mesh; the last 8
    concrete poses are kept, :func:`occluder_own_visibility`) and is not differentiable with respect
    to their vertices. With ``method.contact_visibility = "rays"`` the receivers next to a mesh are
    cast for every concrete scene, time and lighting not seen before (the last 4 kept, by a digest
    of their arrays; :func:`contact_rows_at_time`), likewise not differentiable.
    """
    return render_at(scene, frame_time(frame, scene.n_frames), sphere_path=sphere_path)
