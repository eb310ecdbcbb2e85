"""Frame-by-frame rendering with reuse, per-stage timings, bounded memory and several devices.

:func:`jshadow.scene.render` is the pure, differentiable function. :class:`Renderer` runs the same
computation as two compiled calls per frame — the BSVs, then the shading (placing the frame's
receivers, field evaluation and combination in one call) — and skips work the animation does not
need: an occluder whose shape does not change over time (no deformation, or a deformation whose
amount is the same at every frame) has its BSV computed once and reused for every frame, and so has
its ray-cast visibility at its own vertices (``[method] self_visibility = "rays"``) and its
occlusion images (``[method] light_visibility = "images"``; a deforming mesh's images come from its
BSV's edge-scan pass). When the geometry does not move — one occluder deforming about a fixed
bounding-sphere centre (``[method] bsv_center = "placed"``, the default), receivers and lights that
stay where they are (:mod:`jshadow.readout`) — the per-receiver part of the field and of the
combination (cells, rotations, the lights' functionals) is computed once, and each frame only reads
the field's table (``static_readout``, on by default); a deforming occluder's own vertices, which
move, are shaded by the general path in the same call. With occlusion images, an occluder that
keeps its shape has its receivers' visible fractions made once, and the lights shadowed through
them contribute a constant per receiver, which the read-out frames add (``Readout.offset``).
``split_stages=True`` runs the shading as three calls instead (receivers, field, combination) so
that each can be timed; the one-call shading is faster (fewer dispatches and synchronisations, and
XLA schedules the stages together: the animated bunny's shading 1.99 ms against 2.57 ms split,
medians of 100 frames each, BENCHMARKS.md) and gives the same numbers up to rounding (XLA may fuse
the two differently; tests allow a few float32 ulps of the largest value).

Memory: the field and combination stages materialise per-receiver arrays (visibility SH of every
occluder, rotation blocks, products), so a frame with more than ``chunk`` receivers is evaluated in
pieces of exactly ``chunk`` receivers (the last one padded by repeating its last receiver): one
compilation serves every piece and the peak memory of those stages is bounded by ``chunk``, not by
the number of receivers. Every receiver's result is computed by the same per-receiver arithmetic
whatever the piece size; only the rounding can differ (XLA may block the small matrix products
differently for another piece size): chunked and unchunked frames agree to a few units in the last
place, and a given piece size is deterministic (tests check both).

Devices: with ``devices`` the receivers of each piece are sharded over a one-axis device mesh
(:mod:`jshadow._parallel`); :func:`render_frames` also spreads whole frames over devices.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _parallel
from ._numerics import eps
from .entities import MeshOccluder, Receivers, Scene, frame_time, receivers_at_time, shape_is_static
from .readout import prepare_readout, readout_unsupported, shade_readout
from .scene import (
    RenderResult,
    assemble_own_rows,
    bsv_input_vertices,
    casts_own_sh,
    combine,
    contact_rows_at_time,
    image_fractions,
    occluder_bsv,
    occluder_bsv_and_images,
    occluder_images,
    occluder_lamp_images,
    occluder_own_casts,
    occluder_own_light_visibility,
    occluder_own_visibility,
    occluder_visibilities,
    occlusion_table,
    scene_lighting,
    self_visibility_owners,
    shared_normal_count,
    uses_contact,
    uses_light_images,
    uses_self_rays,
    uses_visibility_chain,
    visibility_chain,
)

__all__ = ["Renderer", "shape_is_static", "render_frames", "DEFAULT_CHUNK"]

DEFAULT_CHUNK = 2**17  # receivers per piece: 131072 (1.6 GiB peak RSS with 8 occluders, memory_scale.py)


@eqx.filter_jit
def _receivers(scene, t):
    return receivers_at_time(scene, t)


@eqx.filter_jit
def _fields(scene, bsvs, points, own=None, contact=None):
    vis, dist = occluder_visibilities(scene, bsvs, points, own, contact=contact)
    # one (m, N, n²) array across the jit boundary, not m separate ones (measured with 16 occluders,
    # when the product chain stacked them again: combination 49 -> 44 ms, BENCHMARKS.md)
    return (jnp.stack(vis), jnp.stack(dist)) if vis else (vis, dist)


def _combine_piece(
    scene,
    points,
    normals,
    vis,
    dist,
    lighting,
    analytic_spheres,
    shared_normal,
    images=None,
    own=None,
    env_visibility=None,
    fractions=None,
    contact=None,
):
    """Combination of one piece (``images``: the occluders' occlusion images with
    ``light_visibility = "images"``, else None; ``own``: the piece's rows of the ray-cast
    own-vertex visibility; see :func:`jshadow.scene.image_fractions`; ``env_visibility``: see
    :func:`jshadow.scene.combine`; ``fractions``: the pair :func:`jshadow.scene.image_fractions`
    returns for these receivers, made beforehand, in place of computing it from ``images``;
    ``contact``: the piece's rows of :func:`jshadow.scene.contact_rows_at_time`, or None)."""
    vis, dist = list(vis), list(dist)  # (m, ...) arrays or empty lists -> lists of m arrays
    if fractions is None:
        fractions = image_fractions(scene, images, lighting, points, normals, own, contact)
    fractions, env_fraction = fractions
    e = combine(
        scene,
        points,
        normals,
        vis,
        dist,
        lighting,
        analytic_spheres,
        shared_normal,
        fractions,
        env_fraction,
        env_visibility,
        own,
    )
    return e, e * (scene.receivers.albedo / math.pi)


_combine = eqx.filter_jit(_combine_piece)
_image_fractions = eqx.filter_jit(image_fractions)


def _shade_piece(
    scene,
    bsvs,
    points,
    normals,
    lighting,
    analytic_spheres,
    shared_normal,
    own=None,
    images=None,
    fractions=None,
    contact=None,
):
    """Field evaluation and combination of one piece of receivers, traced together (``own``: the
    piece's rows of the ray-cast own-vertex visibility, see :func:`jshadow.scene.occluder_visibilities`;
    ``images``, ``fractions``, ``contact``: see :func:`_combine_piece`). Where only the product of
    the visibilities is needed (:func:`jshadow.scene.uses_visibility_chain`), each is multiplied in
    as soon as it is made (:func:`jshadow.scene.visibility_chain`)."""
    if fractions is None and uses_visibility_chain(scene, own, images, lighting, contact):
        chain = visibility_chain(scene, bsvs, points)
        return _combine_piece(
            scene, points, normals, [], [], lighting, analytic_spheres, shared_normal, images, own, chain
        )
    vis, dist = occluder_visibilities(scene, bsvs, points, own, contact=contact)
    return _combine_piece(
        scene,
        points,
        normals,
        vis,
        dist,
        lighting,
        analytic_spheres,
        shared_normal,
        images,
        own,
        fractions=fractions,
        contact=contact,
    )


_shade = eqx.filter_jit(_shade_piece)


def _place_and_shade_frame(
    scene,
    bsvs,
    t,
    lighting,
    analytic_spheres,
    shared_normal,
    own=None,
    images=None,
    fractions=None,
    contact=None,
):
    """A whole frame's shading: its receivers (:func:`receivers_at_time`), then
    :func:`_shade_piece` on all of them (traced on the scene without its receiver arrays, as the
    pieces of the split path are, so that both compile the same field and combination).

    Returns ``(points, normals, e, rad)``; ``points`` and ``normals`` are None where they are the
    scene's own receiver arrays (no occluder's vertices among them): XLA copies an output that is
    an input (two copy kernels per frame in a profile; no change measurable in the frame's time,
    BENCHMARKS.md). :func:`_with_receivers` puts them back."""
    points, normals = receivers_at_time(scene, t)
    light = _without_receivers(scene)
    e, rad = _shade_piece(
        light,
        bsvs,
        points,
        normals,
        lighting,
        analytic_spheres,
        shared_normal,
        own,
        images,
        fractions,
        contact,
    )
    if points is scene.receivers.points and normals is scene.receivers.normals:
        return None, None, e, rad
    return points, normals, e, rad


def _with_receivers(scene, out):
    """``out`` of :func:`_place_and_shade_frame` with the scene's receivers in place of None."""
    points, normals, e, rad = out
    if points is None:
        points, normals = scene.receivers.points, scene.receivers.normals
    return points, normals, e, rad


def _readout_frame(scene, bsvs, t, lighting, analytic_spheres, readout, table):
    """A frame read out of the field's table (:func:`jshadow.readout.shade_readout`) at its first
    receivers, the fixed ones ``readout`` was prepared for, and shaded by the general path
    (:func:`_shade_piece`) at the rest: a deforming occluder's own vertices with ``self_shadow``,
    which move. One call; returns ``(points, normals, e, rad)`` as :func:`_place_and_shade_frame`."""
    e, rad = shade_readout(readout, bsvs[0], table, scene.method.sh_bands, scene.receivers.albedo)
    fixed = readout.inv_d.shape[0]
    points, normals = receivers_at_time(scene, t)
    if points.shape[0] == fixed:
        if points is scene.receivers.points and normals is scene.receivers.normals:
            return None, None, e, rad
        return points, normals, e, rad
    light = _without_receivers(scene)
    e2, rad2 = _shade_piece(
        light, bsvs, points[fixed:], normals[fixed:], lighting, analytic_spheres, 0, None, None
    )
    return points, normals, jnp.concatenate([e, e2]), jnp.concatenate([rad, rad2])


_place_and_shade = eqx.filter_jit(_place_and_shade_frame)
_readout_and_shade = eqx.filter_jit(_readout_frame)
_prepare_readout = eqx.filter_jit(prepare_readout)  # ``shared`` (an int) is static


def _centre_moved(center, reference: np.ndarray, shell_radius) -> bool:
    """Whether a bounding-sphere centre differs from ``reference`` by more than rounding (the box
    centre of a deformation symmetric about it can differ in the last bits; that changes the field
    by about as much as the float rounding of its evaluation does, except at receivers within
    rounding of the centre, whose direction to it is undefined anyway)."""
    shift = np.abs(np.asarray(center) - reference).max()
    return bool(shift > eps(reference.dtype) * float(np.abs(reference).max() + np.asarray(shell_radius)))


def _centre_moves(occ, bsv, method) -> bool:
    """Whether a deforming mesh's bounding-sphere centre moves: the centre its BSV takes
    (:func:`jshadow.geometry.bounding_sphere` of :func:`jshadow.scene.bsv_input_vertices`: the
    deformed vertices' box centre, or the placed centre with ``method.bsv_center = "placed"``) at
    times 0, 1/3, 2/3 and 1 against the BSV's (one compiled call, vmapped over the times: 0.13–0.18 s
    to compile, against 0.64 s for the same operations dispatched one by one). False for shapes that
    do not change."""
    if shape_is_static(occ):
        return False
    ref = np.asarray(bsv.center)
    times = jnp.asarray([0.0, 1 / 3, 2 / 3, 1.0], ref.dtype)
    centres = np.asarray(_bsv_centres(occ, method, times))
    return any(_centre_moved(c, ref, bsv.shell_radius) for c in centres)


@eqx.filter_jit
def _bsv_centres(occ, method, times):
    """The centres (T, 3) of the occluder's BSV at ``times`` (T,), as :func:`jshadow.scene.mesh_bsv`
    takes them."""
    from .geometry import bounding_sphere

    return jax.vmap(lambda t: bounding_sphere(bsv_input_vertices(occ, occ.vertices(t), method))[0])(times)


_FLAT_SHADERS: dict = {}


def _flat_shader(scene: Scene, lighting, analytic_spheres: bool, shared_normal: int, readout: bool = False):
    """:func:`_place_and_shade` for one scene as ``(call, dynamic)``: ``call(dynamic, bsvs, t, own,
    images, extra, fractions, contact)`` is a plain ``jax.jit`` function of the scene's and lighting's arrays
    (``dynamic``, a list flattened once here) and of the frame's BSVs and time; with ``readout``, it is
    :func:`_readout_frame` instead, and ``extra`` is its ``(readout, table)`` (None otherwise).
    ``eqx.filter_jit`` partitions,
    flattens and hashes the whole scene on every call: without that the six shipped configs shade in
    0.86–0.91× the time (the airplane 2.69 → 2.32 ms, BENCHMARKS.md, "Rendering"). Same trace, same
    numbers. Scenes with the same structure and static parts share one compiled function (a renderer
    per thread, or per test, compiles once); ``own`` is the frame's ray-cast own-vertex visibility or
    None, ``images`` the occluders' occlusion images or None, ``fractions`` the receivers' visible
    fractions made from them beforehand (:meth:`Renderer._fractions`) or None. Returns None if the
    static parts cannot be hashed (the caller then uses :func:`_place_and_shade`)."""
    leaves, tree = jax.tree_util.tree_flatten((scene, lighting))
    mask = tuple(eqx.is_array(x) for x in leaves)
    static = tuple(None if m else x for x, m in zip(leaves, mask, strict=True))
    dynamic = [x for x, m in zip(leaves, mask, strict=True) if m]
    key = (tree, static, bool(analytic_spheres), int(shared_normal), bool(readout))
    try:
        call = _FLAT_SHADERS.get(key)
    except TypeError:  # an unhashable static leaf
        return None
    if call is None:

        def run(dyn, bsvs, t, own, images, extra, fractions, contact):
            it = iter(dyn)
            full = [next(it) if m else x for x, m in zip(static, mask, strict=True)]
            scn, light = jax.tree_util.tree_unflatten(tree, full)
            if readout:
                return _readout_frame(scn, bsvs, t, light, analytic_spheres, *extra)
            return _place_and_shade_frame(
                scn, bsvs, t, light, analytic_spheres, shared_normal, own, images, fractions, contact
            )

        if len(_FLAT_SHADERS) >= 32:  # scenes are few per process; bound the cache anyway
            _FLAT_SHADERS.clear()
        call = _FLAT_SHADERS[key] = jax.jit(run)
    return call, dynamic


def _without_receivers(scene: Scene) -> Scene:
    """The scene minus its receiver arrays (the pieces bring their own; only the albedo is used)."""
    albedo = scene.receivers.albedo
    empty = jnp.zeros((0, 3), albedo.dtype)
    return eqx.tree_at(lambda s: s.receivers, scene, Receivers(points=empty, normals=empty, albedo=albedo))


class Renderer:
    """Renders the frames of one scene, reusing BSVs of occluders whose shape does not change.

    Args:
        scene: the scene.
        sphere_path: "analytic" (exact caps) or "bsv" for sphere occluders (see :func:`jshadow.render`).
        chunk: receivers per piece of the field and combination stages (default
            :data:`DEFAULT_CHUNK`); frames with at most ``chunk`` receivers are evaluated in one piece.
            Peak memory of those stages grows linearly with ``chunk``.
        progress: show a progress bar over the pieces of a frame (when there are several).
        devices: None (the default device, no sharding), an integer n (the first n JAX devices) or a
            list of devices: each piece's receivers are sharded over them (the piece size is rounded
            up to a multiple of the device count).
        split_stages: run the shading as separate calls — placing the receivers, field evaluation,
            combination — so that :meth:`frame` can time each (module docstring); slower than the
            default single shading call.
        static_readout: read fixed-geometry frames out of the field's table
            (:mod:`jshadow.readout`): prepared at the first frame of an animation (at the second
            call of a one-frame scene), used for every frame whose occluder keeps its
            bounding-sphere centre (its radius may change), at the receivers that do not move (a
            deforming occluder's own vertices are shaded by the general path in the same call).
            Same numbers as the general path up to rounding. Not with ``split_stages``,
            ``devices`` or frames of more than ``chunk`` receivers, nor for an occluder whose
            bounding sphere's centre moves (``bsv_center = "box"`` and a deformation not
            symmetric about the centre; sampled at four times of the animation before preparing,
            checked every frame). ``readout_frames``
            counts the frames it shaded; ``readout_reason`` says why it does not apply (None if
            it does). A frame with receivers next to a mesh (``method.contact_visibility =
            "rays"``, :func:`jshadow.scene.contact_rows_at_time`) is shaded by the general path.

    With ``contact_visibility = "rays"`` the receivers next to a mesh are cast once when no
    occluder changes its shape, else every frame (``contact_computations`` counts the casts; the
    frame's timings then hold ``contact_ms``).
    """

    def __init__(
        self,
        scene: Scene,
        sphere_path: str = "analytic",
        chunk: int | None = None,
        progress: bool = False,
        devices: int | Sequence[jax.Device] | None = None,
        split_stages: bool = False,
        static_readout: bool = True,
    ):
        if not isinstance(split_stages, bool):
            raise TypeError(f"split_stages must be True or False, got {split_stages!r}")
        if not isinstance(static_readout, bool):
            raise TypeError(f"static_readout must be True or False, got {static_readout!r}")
        chunk = DEFAULT_CHUNK if chunk is None else chunk
        if isinstance(chunk, bool) or not isinstance(chunk, int | np.integer) or chunk < 1:
            raise ValueError(f"chunk must be a positive integer (receivers per piece), got {chunk!r}")
        self.scene = scene
        self.sphere_path = sphere_path
        self.chunk = int(chunk)
        self.progress = progress
        self.split_stages = split_stages
        self.mesh = None if devices is None else _parallel.receiver_mesh(devices)
        self._light = _without_receivers(scene)
        # environment SH / irradiance map: once per renderer, not per frame (and finished here, so
        # that the asynchronous dispatch does not leak into the first frame's BSV timing)
        self._lighting = jax.block_until_ready(scene_lighting(scene))
        self._shared_normal = shared_normal_count(scene.receivers.normals)  # the plane's rows lead
        # receivers per frame (the plane's and, with self-shadowing, the occluders' vertices): the
        # same at every time; from the shapes alone
        self._receiver_count = jax.eval_shape(lambda: receivers_at_time(scene, 0.0))[0].shape[0]
        self._static_bsvs: dict[int, object] = {}
        self.bsv_computations = 0  # how many BSVs were actually sampled (tests check the reuse)
        # method.self_visibility = "rays": the own-vertex rows' owners (constant), the cast per occluder
        # for shapes that do not change, and how many casts ran (tests check the reuse)
        self._owners = jnp.asarray(self_visibility_owners(scene)) if uses_self_rays(scene) else None
        self._casts_sh = casts_own_sh(scene)  # "rays"; "light_rays" casts toward the lamps only
        self._static_own: dict[int, object] = {}
        self._static_rows = None  # all of them, when no mesh occluder deforms
        self.self_visibility_computations = 0
        self._flat = {}  # readout or not -> _flat_shader(...) (or ()), built at the first such frame
        # method.light_visibility = "images": the occluders' occlusion images, once for shapes that
        # do not change, every frame for those that deform (tests check the reuse)
        self._uses_images = uses_light_images(scene)
        self._static_images: dict[int, object] = {}
        self._fresh_images: dict[int, object] = {}  # this frame's, made with its BSV (one edge-scan)
        self.image_computations = 0
        # ... and, when every occluder keeps its shape (so the receivers, the lights and the images
        # are the same at every frame), the receivers' visible fractions made from them, once
        self._static_fractions = None
        self.fraction_computations = 0
        self._shapes_static = all(shape_is_static(o) for o in scene.occluders)
        # method.contact_visibility = "rays": the receivers next to a mesh (once where no occluder
        # changes its shape: the receivers and lights are fixed too; tests check the reuse)
        self._uses_contact = uses_contact(scene)
        self._static_contact: list = []  # [contact] once made for a scene whose shapes are static
        self.contact_computations = 0
        # static_readout: None until decided, then False or (Readout, points, normals, centre)
        self.static_readout = static_readout
        self._readout = None
        self.readout_reason: str | None = None
        self.readout_frames = 0
        self._frames_shaded = 0

    def _readout_for(self, bsvs, own, images):
        """The prepared readout if this frame can use it (:mod:`jshadow.readout`), else None."""
        if not self.static_readout or self._readout is False:
            return None
        if self._readout is None:
            scene = self.scene
            split = self._image_split(own, images)
            if split is not None:  # a static scene's image terms: an offset (_with_image_offset)
                reason = readout_unsupported(split[0], bsvs, None, None, None)
            else:
                reason = readout_unsupported(scene, bsvs, own, images, self._lighting.env_lights)
            fixed = self._receiver_count
            if reason is None and scene.self_shadow and not shape_is_static(scene.occluders[0]):
                # a deforming occluder's own vertices move: the general path shades them, in the
                # same call (_readout_frame); the plane's receivers are read out
                fixed = scene.receivers.points.shape[0]
                if fixed == 0:
                    reason = "no fixed receivers (only a deforming occluder's own vertices)"
            if reason is not None:
                self.readout_reason, self._readout = reason, False
                return None
            if _centre_moves(scene.occluders[0], bsvs[0], scene.method):
                self.readout_reason, self._readout = "the bounding sphere's centre moves", False
                return None
            if scene.n_frames <= 1 and self._frames_shaded == 0:
                return None  # a single frame: the general path; prepare if it is rendered again
            points, normals = receivers_at_time(scene, 0.0)
            points, normals = points[:fixed], normals[:fixed]
            table = occlusion_table(scene)
            shared = shared_normal_count(normals)
            if split is None:
                ro = _prepare_readout(scene, bsvs[0], self._lighting, table, points, normals, shared)
            else:
                sh_scene, sh_lighting = split
                ro = _prepare_readout(sh_scene, bsvs[0], sh_lighting, table, points, normals, shared)
                ro = self._with_image_offset(ro, split, bsvs, own, images)
            self._readout = (ro, np.asarray(ro.center))
        ro, center = self._readout
        if _centre_moved(bsvs[0].center, center, bsvs[0].shell_radius):  # a check the sampling missed
            self.readout_reason, self._readout = "the bounding sphere's centre moves", False
            return None
        return ro

    def _image_split(self, own, images):
        """For a scene whose occluders keep their shape and whose lights go through the occlusion
        images (their visible fractions made once, :meth:`_fractions`), or whose own vertices'
        transfer is cast (``self_visibility = "rays"``, cast once): ``(scene, lighting)`` without
        those lights — no sphere lights, no environment lights — and with the field's visibility at
        the own vertices, whose frames the readout can take; what the scene adds to them (the image
        terms, the cast transfer's difference at the own vertices) does not change from frame to
        frame and is a constant offset per receiver (:meth:`_with_image_offset`). None otherwise,
        or when there is no environment (nothing left to read out)."""
        if not self._shapes_static or self.scene.environment is None:
            return None
        cast = own is not None and own[0] is not None
        if images is None and not cast:
            return None
        method = self.scene.method
        if cast:
            method = dataclasses.replace(method, self_visibility="field")
        sh_scene = dataclasses.replace(self.scene, lights=(), method=method)
        sh_lighting = dataclasses.replace(self._lighting, env_lights=None, env_bright_sh=None)
        return sh_scene, sh_lighting

    def _with_image_offset(self, ro, split, bsvs, own, images):
        """``ro`` with its offset: the static scene's whole frame less the frame of ``split``'s
        scene and lighting (the same field, only the SH-lit terms), both by the general path once
        (the whole frame by the renderer's own one call, compiled already when a one-frame scene
        prepares at its second frame); every read-out frame then adds it to the SH terms it reads
        (the same numbers as the general path up to rounding)."""
        analytic = self.sphere_path == "analytic"
        t = jnp.asarray(0.0, self.scene.receivers.points.dtype)
        full = self._shade_once(bsvs, t, own, images)
        sh_scene, sh_lighting = split
        sh = _place_and_shade(sh_scene, bsvs, t, sh_lighting, analytic, self._shared_normal)
        fixed = ro.inv_d.shape[0]
        offset = (full[2] - sh[2])[:fixed]
        return eqx.tree_at(lambda r: r.offset, ro, offset, is_leaf=lambda x: x is None)

    def _bsvs(self, t):
        out = []
        for i, occ in enumerate(self.scene.occluders):
            if shape_is_static(occ):
                if i not in self._static_bsvs:
                    self._static_bsvs[i] = occluder_bsv(occ, 0.0, self.scene, self.sphere_path, False)
                    self.bsv_computations += self._static_bsvs[i] is not None
                out.append(self._static_bsvs[i])
            else:
                both = occluder_bsv_and_images(occ, t, self.scene) if self._uses_images else None
                if both is None:
                    out.append(occluder_bsv(occ, t, self.scene, self.sphere_path, False))
                else:  # a deforming mesh whose images are needed too: one edge-scan for both
                    out.append(both[0])
                    self._fresh_images[i] = both[1]
                self.bsv_computations += 1
        return tuple(out)

    def _own(self, t):
        """The frame's ray-cast own-vertex visibility ``(rows, owners)`` — and, with environment
        lights, the own vertices' visibility toward them (:func:`jshadow.scene.own_rows_at_time`)
        — or None unless the scene uses it: cast once for an occluder whose shape does not change,
        every frame for one that does."""
        if self._owners is None:
            return None
        if self._static_rows is not None:
            return self._static_rows
        lights = self._lighting.env_lights
        own, own_lights = [], []
        for i, occ in enumerate(self.scene.occluders):
            if not isinstance(occ, MeshOccluder):
                continue
            if shape_is_static(occ) and i in self._static_own:
                v, vl = self._static_own[i]
            else:
                at = 0.0 if shape_is_static(occ) else t
                if self._casts_sh and lights is not None:  # both, from one cast where they can be
                    v, vl = occluder_own_casts(occ, at, self.scene, lights.directions, cache=False)
                else:
                    v = occluder_own_visibility(occ, at, self.scene, cache=False) if self._casts_sh else None
                    vl = None
                    if lights is not None:
                        d = lights.directions
                        vl = occluder_own_light_visibility(occ, at, self.scene, d, cache=False)
                self.self_visibility_computations += 1
                if shape_is_static(occ):
                    self._static_own[i] = (v, vl)
            own.append(v)
            own_lights.append(vl)
        out = assemble_own_rows(
            self.scene,
            own if self._casts_sh else None,
            None if lights is None else own_lights,
            None if lights is None else lights.directions,
            self._owners,
        )
        if all(shape_is_static(o) for o in self.scene.occluders if isinstance(o, MeshOccluder)):
            self._static_rows = out
        return out

    def _images(self, t):
        """The frame's occlusion images per occluder (None unless the scene uses them): once for a
        shape that does not change; for a deforming mesh sampled by the edge-scan, made by
        :meth:`_bsvs` in the same pass as its BSV (so ``light_images_ms`` is about 0 and
        ``bsv_ms`` holds both)."""
        if not self._uses_images:
            return None
        out = []
        for i, occ in enumerate(self.scene.occluders):
            static = shape_is_static(occ)
            if static and i in self._static_images:
                out.append(self._static_images[i])
                continue
            if i in self._fresh_images:  # made with this frame's BSV
                out.append(occluder_lamp_images(occ, t, self.scene, self._fresh_images.pop(i)))
                self.image_computations += 1
                continue
            img = occluder_images(occ, 0.0 if static else t, self.scene, differentiable=False)
            img = occluder_lamp_images(occ, 0.0 if static else t, self.scene, img)
            self.image_computations += img is not None
            if static:
                self._static_images[i] = img
            out.append(img)
        return tuple(out)

    def _contact(self, t):
        """The frame's :func:`jshadow.scene.contact_rows_at_time` (None where unused or no receiver
        is near a mesh): once when no occluder changes its shape, else every frame."""
        if not self._uses_contact:
            return None
        if self._static_contact:
            return self._static_contact[0]
        out = contact_rows_at_time(self.scene, t, self._lighting)
        self.contact_computations += 1
        if self._shapes_static:
            self._static_contact.append(out)
        return out

    def _fractions(self, own, images, contact=None):
        """The receivers' visible fractions of the lights through the occlusion images
        (:func:`jshadow.scene.image_fractions`), made once and kept when no occluder changes its
        shape: the renderer's lights and placements are fixed, so the receivers (a static mesh's
        own vertices included), the images and the own-vertex rows are then the same at every
        frame, and so are the fractions. None otherwise (each frame makes them with its shading)."""
        if images is None or not self._shapes_static:
            return None
        if self._static_fractions is None:
            points, normals = receivers_at_time(self.scene, 0.0)
            self._static_fractions = _image_fractions(
                self._light, images, self._lighting, points, normals, own, contact
            )
            self.fraction_computations += 1
        return self._static_fractions

    def _shade_once(self, bsvs, t, own=None, images=None, readout=None, contact=None):
        """One call placing every receiver of the frame at time ``t`` (an array) and shading them;
        with ``readout`` (a prepared :class:`jshadow.readout.Readout`), the fixed ones read out
        (:func:`_readout_frame`). The visible fractions of a scene whose occluders keep their shape
        are made once (:meth:`_fractions`) and given to the shading in place of the images."""
        fractions = None if readout is not None else self._fractions(own, images, contact)
        if fractions is not None:
            images = None
        analytic = self.sphere_path == "analytic"
        mode = readout is not None
        if mode not in self._flat:  # () when the scene cannot be flattened into a hashable key
            self._flat[mode] = (
                _flat_shader(self.scene, self._lighting, analytic, self._shared_normal, mode) or ()
            )
        extra = None if readout is None else (readout, occlusion_table(self.scene))
        if self._flat[mode]:
            call, dynamic = self._flat[mode]
            out = call(dynamic, bsvs, t, own, images, extra, fractions, contact)
        elif readout is not None:
            out = _readout_and_shade(self.scene, bsvs, t, self._lighting, analytic, *extra)
        else:
            out = _place_and_shade(
                self.scene,
                bsvs,
                t,
                self._lighting,
                analytic,
                self._shared_normal,
                own,
                images,
                fractions,
                contact,
            )
        return _with_receivers(self.scene, out)

    def piece_size(self, n: int) -> int:
        """Receivers per piece for a frame of n receivers (a multiple of the device count)."""
        size = min(n, self.chunk)
        if self.mesh is not None:
            k = self.mesh.devices.size
            size = -(-size // k) * k
        return size

    def frame(self, frame: int) -> tuple[RenderResult, dict]:
        """Render one frame; returns the result and its timings in milliseconds.

        ``bsv_ms``: the BSVs; ``shading_ms``: placing the frame's receivers, field evaluation and
        combination; ``total_ms``: all stages. With ``method.self_visibility = "rays"`` also
        ``self_visibility_ms``: casting the occluders' own-vertex visibility (about 0 after the
        first frame for shapes that do not change). With ``method.light_visibility = "images"``
        (and sphere lights or ``environment_lights``) also ``light_images_ms``: the occluders'
        occlusion images (likewise).
        With ``split_stages`` also ``field_ms`` (including placing the receivers) and
        ``combine_ms``, whose sum is ``shading_ms``. With several pieces the shading times are
        summed over the pieces.
        """
        from tqdm.auto import tqdm

        t = frame_time(frame, self.scene.n_frames)
        t0 = time.perf_counter()
        bsvs = jax.block_until_ready(self._bsvs(t))
        t_own = time.perf_counter()
        own = jax.block_until_ready(self._own(t))
        t_img = time.perf_counter()
        images = jax.block_until_ready(self._images(t))
        t_contact = time.perf_counter()
        contact = jax.block_until_ready(self._contact(t))
        t1 = time.perf_counter()
        first = {"bsv_ms": 1e3 * (t_own - t0)}
        if own is not None:
            first["self_visibility_ms"] = 1e3 * (t_img - t_own)
        if images is not None:
            first["light_images_ms"] = 1e3 * (t_contact - t_img)
        if self._uses_contact:
            first["contact_ms"] = 1e3 * (t1 - t_contact)
        t_arr = jnp.asarray(t, self.scene.receivers.points.dtype)  # traced: one compilation for all frames
        analytic = self.sphere_path == "analytic"
        n = self._receiver_count
        one_call = not self.split_stages and self.mesh is None and n <= self.chunk
        # a frame with receivers next to the mesh shades them by its contact rows, not the readout
        readout = self._readout_for(bsvs, own, images) if one_call and contact is None else None
        self._frames_shaded += 1
        if one_call:
            points, normals, e, rad = jax.block_until_ready(
                self._shade_once(bsvs, t_arr, own, images, readout, contact)
            )
            self.readout_frames += readout is not None
            t2 = time.perf_counter()
            res = RenderResult(points=points, normals=normals, irradiance=e, radiance=rad)
            times = {**first, "shading_ms": 1e3 * (t2 - t1)}
            times["total_ms"] = sum(times.values())
            return res, times
        points, normals = jax.block_until_ready(_receivers(self.scene, t_arr))
        size = self.piece_size(n)
        starts = range(0, n, size)
        field_s = time.perf_counter() - t1
        combine_s = 0.0
        e_parts, r_parts = [], []
        bar = tqdm(
            starts, desc="receivers", unit="piece", leave=False, disable=not self.progress or len(starts) < 2
        )
        for s in bar:
            p = _parallel.pad_rows(points[s : s + size], size) if (s, size) != (0, n) else points
            q = _parallel.pad_rows(normals[s : s + size], size) if (s, size) != (0, n) else normals
            o = None
            if own is not None:
                o = (
                    own
                    if (s, size) == (0, n)
                    else tuple(None if x is None else _parallel.pad_rows(x[s : s + size], size) for x in own)
                )
            c = None
            if contact is not None:
                c = (
                    contact
                    if (s, size) == (0, n)
                    else tuple(
                        None if x is None else _parallel.pad_rows(x[s : s + size], size) for x in contact
                    )
                )
            if self.mesh is not None:
                p, q = _parallel.shard_rows(p, self.mesh), _parallel.shard_rows(q, self.mesh)
                o = (
                    None
                    if o is None
                    else tuple(None if x is None else _parallel.shard_rows(x, self.mesh) for x in o)
                )
                c = (
                    None
                    if c is None
                    else tuple(None if x is None else _parallel.shard_rows(x, self.mesh) for x in c)
                )
            shared = min(max(self._shared_normal - s, 0), size)
            ta = time.perf_counter()
            if self.split_stages:
                vis, dist = jax.block_until_ready(_fields(self._light, bsvs, p, o, c))
                tb = time.perf_counter()
                e, rad = jax.block_until_ready(
                    _combine(
                        self._light, p, q, vis, dist, self._lighting, analytic, shared, images, o, contact=c
                    )
                )
            else:
                e, rad = jax.block_until_ready(
                    _shade(self._light, bsvs, p, q, self._lighting, analytic, shared, o, images, contact=c)
                )
                tb = time.perf_counter()
            tc = time.perf_counter()
            field_s += tb - ta
            combine_s += tc - tb
            m = min(size, n - s)
            e_parts.append(e if m == size else e[:m])
            r_parts.append(rad if m == size else rad[:m])
        bar.close()
        if len(e_parts) == 1 and self.mesh is None:
            e, rad = e_parts[0], r_parts[0]
        else:  # gathered on the host, then one array on the default device
            e = jnp.asarray(np.concatenate([np.asarray(x) for x in e_parts]))
            rad = jnp.asarray(np.concatenate([np.asarray(x) for x in r_parts]))
        res = RenderResult(points=points, normals=normals, irradiance=e, radiance=rad)
        times = {**first, "shading_ms": 1e3 * (field_s + combine_s)}
        times["total_ms"] = sum(times.values())
        if self.split_stages:
            times |= {"field_ms": 1e3 * field_s, "combine_ms": 1e3 * combine_s}
        return res, times


def render_frames(
    scene: Scene,
    frames: Sequence[int] | None = None,
    devices: int | Sequence[jax.Device] | None = None,
    sphere_path: str = "analytic",
    chunk: int | None = None,
    threads: int = 1,
) -> list[RenderResult]:
    """Render several frames, spread round-robin over devices and host threads.

    Each device gets its own copy of the scene (:func:`jshadow._parallel.put_on`) and ``threads``
    host threads, each with its own :class:`Renderer` (compiled stages are shared), so the frames
    assigned to a thread run there while the others work: useful where one frame leaves cores idle.
    On the 2-core benchmark machine it no longer is: since a frame's shading runs as one call, two
    threads lower the animated bunny's throughput (6.5-8.9 -> 8.1-11.5 ms per frame in six runs,
    ``benchmarks/bench_render.py``; with three calls per frame they raised it by 0-15 %). Per-frame
    latency does not improve. ``frames`` defaults to every
    frame of the scene. Returns the results in the order of ``frames``, as host (NumPy-backed) arrays
    on the default device.
    """
    if isinstance(threads, bool) or not isinstance(threads, int | np.integer) or threads < 1:
        raise ValueError(f"threads must be a positive integer (host threads per device), got {threads!r}")
    frames = list(range(scene.n_frames)) if frames is None else [int(f) for f in frames]
    for f in frames:
        frame_time(f, scene.n_frames)  # range check, before any thread starts
    assigned = _parallel.frame_devices(len(frames), devices)
    devs = list(dict.fromkeys(assigned))
    results: list = [None] * len(frames)
    errors: list = []

    def work(dev, k):
        try:
            rend = Renderer(_parallel.put_on(scene, dev), sphere_path=sphere_path, chunk=chunk)
            mine = [i for i in range(len(frames)) if assigned[i] == dev]
            for i in mine[k::threads]:
                res, _ = rend.frame(frames[i])
                results[i] = jax.tree_util.tree_map(np.asarray, res)
        except BaseException as err:  # re-raised in the calling thread
            errors.append(err)

    workers = [
        threading.Thread(target=work, args=(d, k), daemon=True) for d in devs for k in range(int(threads))
    ]
    for th in workers:
        th.start()
    for th in workers:
        th.join()
    if errors:
        raise errors[0]
    return [jax.tree_util.tree_map(jnp.asarray, r) for r in results]
