"""Fitting scene parameters to target shadows with optax.

The loss compares the outgoing radiance of the receiver plane with a target, normalised by the
target's mean square so that it is scale-free:
``loss(θ) = mean((L(θ) − L*)²) / mean(L*²)``. Gradients flow through
:func:`jshadow.scene.render`; for mesh occluders whose *shape* changes, the BSV's gradient with
respect to vertex positions is only non-zero with the silhouette (visibility) gradient, see
:mod:`jshadow.visibility` (the deformable-shadow-fields paper resamples the BSV per frame; its
derivative is the silhouette line integral of DESIGN.md §1.6).

Several targets at once: :func:`plane_radiances` renders one scene under several light sets while
computing each occluder's BSV only once (the BSV does not depend on the lights), so a shape can be
fitted to the shadows it casts under, e.g., four different sphere-light positions.

Shape priors: :func:`laplacian_penalty` is the squared uniform (umbrella) Laplacian of a per-vertex
field, the usual smoothness regulariser for free vertex offsets.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Float

from ._types import Faces
from .entities import Scene, frame_time
from .scene import grow_slots, render, render_at, scene_bsvs_and_images, uses_light_images

__all__ = [
    "FitResult",
    "plane_radiance",
    "plane_radiances",
    "relative_mse",
    "laplacian_penalty",
    "uniform_laplacian",
    "fit",
    "fit_params",
    "jit_growing",
]


@dataclass
class FitResult:
    """What a fit returns.

    ``params``: final values (one array per parameter); ``loss``: the loss per step, evaluated at the
    parameters *before* that step's update; ``history``: parameter values before each step (empty
    when not kept); ``first_step_s``: wall time of the first step (compilation included);
    ``step_s``: wall time of every later step (seconds; a retraced step's includes its compilation);
    ``retraced``: the steps traced again after a static-size overflow (see :func:`fit`).
    """

    params: list  # final values, one array per parameter
    loss: list[float] = field(default_factory=list)
    history: list = field(default_factory=list)  # parameter values per step
    first_step_s: float = 0.0
    step_s: list[float] = field(default_factory=list)
    retraced: list[int] = field(default_factory=list)

    @property
    def ms_per_step(self) -> float:
        """Median wall time of one compiled step in milliseconds (nan for a single step)."""
        return float(np.median(self.step_s) * 1e3) if self.step_s else float("nan")


def plane_radiance(scene: Scene, frame: int = 0) -> Float[Array, "N 3"]:
    """Outgoing radiance (N_plane, 3) of the scene's plane receivers at ``frame``."""
    n = scene.receivers.points.shape[0]
    return render(scene, frame).radiance[:n]


def plane_radiances(scene: Scene, light_sets: Sequence[tuple], frame: int = 0) -> Float[Array, "K N 3"]:
    """Plane radiance of ``scene`` under each of K light sets (the scene's own lights replaced).

    Args:
        scene: the scene; its ``lights`` are ignored, its occluders and environment are kept.
        light_sets: K tuples of :class:`jshadow.entities.SphereLight` (a tuple may be empty).
        frame: the animation frame.

    Returns:
        (K, N_plane, 3) outgoing radiance. The occluders' BSVs (and occlusion images) are sampled
        once and shared by the K renderings (they do not depend on the lights), so K targets cost
        about one BSV.
    """
    if len(light_sets) == 0:
        raise ValueError("plane_radiances expects at least one light set, got none")
    t = frame_time(frame, scene.n_frames)
    # with light_visibility = "images" a set with lights needs the occlusion images too
    lit = next((tuple(s) for s in light_sets if len(s)), ())
    bsvs, images = scene_bsvs_and_images(eqx.tree_at(lambda s: s.lights, scene, lit), t)
    n = scene.receivers.points.shape[0]
    out = []
    for lights in light_sets:
        sc = eqx.tree_at(lambda s: s.lights, scene, tuple(lights))
        out.append(render_at(sc, t, bsvs=bsvs, images=images if uses_light_images(sc) else None).radiance[:n])
    return jnp.stack(out)


def relative_mse(pred: Float[Array, "... N C"], target: Float[Array, "... N C"]) -> Float[Array, ""]:
    """mean((pred − target)²) / mean(target²): 0 for a perfect fit, 1 for predicting zeros.

    Symmetric in a common scale (``relative_mse(s·p, s·t) = relative_mse(p, t)``), non-negative.
    Means run over all axes; a target of all zeros divides by the dtype's tiny value instead of 0.
    """
    pred, target = jnp.asarray(pred), jnp.asarray(target)
    if pred.shape != target.shape:
        raise ValueError(f"relative_mse expects equal shapes, got {pred.shape} and {target.shape}")
    tiny = jnp.finfo(target.dtype).tiny
    return jnp.mean((pred - target) ** 2) / jnp.maximum(jnp.mean(target**2), tiny)


def _check_faces(faces, n_vertices: int) -> np.ndarray:
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"faces must be an integer array of shape (F, 3), got {f.dtype} {f.shape}")
    if f.size and (f.min() < 0 or f.max() >= n_vertices):
        raise ValueError(f"faces index vertices 0..{n_vertices - 1}, got indices {f.min()}..{f.max()}")
    return f


def uniform_laplacian(field: Float[Array, "... V C"], faces: Faces) -> Float[Array, "... V C"]:
    """Uniform ("umbrella") Laplacian of a per-vertex field: ``(L u)_i = u_i − mean_{j ∈ N(i)} u_j``.

    N(i) are the vertices sharing an edge with i (each neighbour counted once). Isolated vertices
    (no edge) get 0. ``faces`` must be concrete (the adjacency is built with numpy); ``field`` may be
    traced and carries leading batch axes. The uniform weights ignore edge lengths and angles (unlike
    the cotangent Laplacian), so L of a linear field is exactly 0 only on regular neighbourhoods.
    """
    field = jnp.asarray(field)
    if field.ndim < 2:
        raise ValueError(f"uniform_laplacian expects a field of shape (..., V, C), got {field.shape}")
    v = field.shape[-2]
    f = _check_faces(faces, v)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)  # undirected edges, once each
    e = e[e[:, 0] != e[:, 1]]
    src = np.concatenate([e[:, 0], e[:, 1]])
    dst = np.concatenate([e[:, 1], e[:, 0]])
    deg = np.bincount(src, minlength=v).astype(np.float64)
    inv_deg = jnp.asarray(np.where(deg > 0, 1.0 / np.maximum(deg, 1.0), 0.0), field.dtype)
    neigh_sum = jnp.zeros_like(field).at[..., src, :].add(field[..., dst, :])
    has = jnp.asarray(deg > 0)[:, None]
    return jnp.where(has, field - neigh_sum * inv_deg[:, None], 0.0)


def laplacian_penalty(offsets: Float[Array, "... V 3"], faces: Faces) -> Float[Array, "..."]:
    """Smoothness penalty of per-vertex offsets: ``mean_i ‖(L o)_i‖²`` with the *uniform* Laplacian.

    Args:
        offsets: (..., V, 3) per-vertex displacements (any units; the penalty has units²).
        faces: (F, 3) concrete integer faces defining the vertex adjacency.

    Returns:
        (...) the penalty: 0 for a constant field (a rigid translation costs nothing), positive for a
        spike; quadratic in ``offsets``, so its gradient is ``2 Lᵀ L o / V``. See
        :func:`uniform_laplacian` for the weights and their limitation on irregular meshes.
    """
    lap = uniform_laplacian(offsets, faces)
    return jnp.mean(jnp.sum(lap * lap, axis=-1), axis=-1)


def jit_growing(fn: Callable, on_overflow: Callable[..., bool] | None = None, tries: int = 3) -> Callable:
    """``eqx.filter_jit(fn)`` that outgrows the static sizes of the traced poses it meets.

    When a call raises a static-size overflow (an ``equinox.EquinoxRuntimeError`` whose message says
    "overflowed": a traced pose needs more slots than were measured) and ``on_overflow(*args)``
    returns True (the sizes grew, e.g. :func:`jshadow.scene.grow_slots` of the scene at these
    arguments), ``fn`` is traced again and the call retried, at most ``tries`` times per call;
    otherwise the error propagates. Each call blocks until its result is ready (the error is raised
    at run time). The returned function counts its retraces in ``.retraces``.
    """
    jitted = [eqx.filter_jit(fn)]

    def call(*args):
        for attempt in range(tries + 1):
            try:
                return jax.block_until_ready(jitted[0](*args))
            except eqx.EquinoxRuntimeError as err:
                grown = on_overflow is not None and attempt < tries and "overflowed" in str(err)
                if not (grown and on_overflow(*args)):
                    raise
                jitted[0] = eqx.filter_jit(lambda *a: fn(*a))  # a new function: a fresh trace
                call.retraces += 1

    call.retraces = 0
    return call


def fit(
    loss_fn: Callable[[list], Float[Array, ""]],
    init: Sequence,
    steps: int = 200,
    optimizer: optax.GradientTransformation | None = None,
    learning_rate: float = 0.05,
    progress: bool = False,
    keep_history: bool = True,
    dtype=jnp.float32,
    on_overflow: Callable[[list], bool] | None = None,
) -> FitResult:
    """Minimise ``loss_fn(params)`` over a list of arrays with optax (Adam by default).

    The whole step (loss, gradient, update) is one ``eqx.filter_jit``; the loss is read back each
    step. ``init`` values are cast to ``dtype``. Raises ``ValueError`` for ``steps < 1``.

    ``on_overflow(params)``, if given, is called with the current (concrete) parameters when a step
    raises a static-size overflow; if it returns True (the sizes grew) the step is traced again and
    retried, at most three times per step (:func:`jit_growing`); otherwise the error propagates.
    """
    if steps < 1:
        raise ValueError(f"steps must be a positive integer, got {steps}")
    params = [jnp.asarray(p, dtype) for p in init]
    opt = optimizer or optax.adam(learning_rate)
    with jax.numpy_dtype_promotion("standard"):
        state = opt.init(params)

    def step_fn(params, state):
        loss, g = jax.value_and_grad(loss_fn)(params)
        # optax mixes its int32 step count with float decay rates (Adam's bias correction): allow
        # the standard promotion there even when the caller runs with strict dtype promotion
        with jax.numpy_dtype_promotion("standard"):
            updates, state = opt.update(g, state, params)
            params = optax.apply_updates(params, updates)
        return params, state, loss

    step = jit_growing(step_fn, None if on_overflow is None else lambda p, s: on_overflow(p))
    result = FitResult(params=params)

    it = range(steps)
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(it, desc="fit", unit="step")
    for i in it:
        if keep_history:
            result.history.append([np.asarray(p).tolist() for p in params])
        t0, retraces = time.perf_counter(), step.retraces
        params, state, loss = step(params, state)
        loss = float(loss)
        if step.retraces > retraces:
            result.retraced.append(i)
        dt = time.perf_counter() - t0
        if i == 0:
            result.first_step_s = dt
        else:
            result.step_s.append(dt)
        result.loss.append(loss)
        if progress:
            it.set_postfix(loss=f"{loss:.3e}")
    result.params = params
    return result


def fit_params(
    make_scene: Callable[[Sequence[jax.Array]], Scene],
    init: Sequence[jax.Array],
    target: jax.Array,
    steps: int = 200,
    learning_rate: float = 0.05,
    optimizer: optax.GradientTransformation | None = None,
    progress: bool = False,
    frame: int = 0,
    regularization: float = 0.0,
    light_sets: Sequence[tuple] | None = None,
    penalty: Callable[[list], jax.Array] | None = None,
    keep_history: bool = True,
) -> FitResult:
    """Minimise :func:`relative_mse` of the plane radiance over the parameters with optax (Adam).

    Args:
        make_scene: parameters (a list of arrays) → scene; must be traceable (``build_scene`` of a
            config with the parameters set by ``eqx.tree_at`` is).
        init: starting values.
        target: (N_plane, 3) target radiance; with ``light_sets``, (K, N_plane, 3), one per set.
        frame: the animation frame rendered.
        regularization: weight w of the penalty ``w · Σ ‖p − p_init‖²`` added to the loss.
        light_sets: optional K light sets (see :func:`plane_radiances`); the loss is then the *sum*
            over k of the relative MSE against ``target[k]``.
        penalty: optional ``params → scalar`` added to the loss (e.g. a weighted
            :func:`laplacian_penalty` of an offset field).
        keep_history: record the parameters before every step in ``FitResult.history``.

    A traced pose that needs larger static sizes than were measured (a mesh deformed further than
    any concrete pose seen) makes the scene's sizes be measured again at the current parameters
    (:func:`jshadow.scene.grow_slots`) and the step retraced.
    """
    target = jnp.asarray(target)
    if light_sets is not None and (target.ndim != 3 or target.shape[0] != len(light_sets)):
        raise ValueError(
            f"with {len(light_sets)} light sets the target must have shape ({len(light_sets)}, N, 3), "
            f"got {target.shape}"
        )
    start = [jnp.asarray(p, jnp.float32) for p in init]

    def loss_fn(p):
        scene = make_scene(p)
        if light_sets is None:
            loss = relative_mse(plane_radiance(scene, frame), target)
        else:
            pred = plane_radiances(scene, light_sets, frame)
            loss = sum(relative_mse(pred[k], target[k]) for k in range(len(light_sets)))
        if regularization:
            loss = loss + regularization * sum(jnp.sum((a - b) ** 2) for a, b in zip(p, start, strict=True))
        if penalty is not None:
            loss = loss + penalty(p)
        return loss

    def grow(p):
        return grow_slots(make_scene([jnp.asarray(x) for x in p]))

    return fit(
        loss_fn,
        start,
        steps=steps,
        optimizer=optimizer,
        learning_rate=learning_rate,
        progress=progress,
        keep_history=keep_history,
        on_overflow=grow,
    )
