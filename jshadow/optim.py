"""Fitting scene parameters to target shadows with optax.

The loss compares the outgoing radiance of the receiver plane with a target, normalised by the
target's mean square so that it is scale-free:
``loss(θ) = mean((L(θ) − L*)²) / mean(L*²)``. Gradients flow through
:func:`jshadow.scene.render`; for mesh occluders whose *shape* changes, the BSV's gradient with
respect to vertex positions is only non-zero with the silhouette (visibility) gradient, see
:mod:`jshadow.visibility`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from .entities import Scene
from .scene import render

__all__ = ["FitResult", "plane_radiance", "relative_mse", "fit_params"]


@dataclass
class FitResult:
    params: list  # final values, one array per parameter
    loss: list[float] = field(default_factory=list)
    history: list = field(default_factory=list)  # parameter values per step


def plane_radiance(scene: Scene, frame: int = 0) -> jax.Array:
    """Outgoing radiance (N_plane, 3) of the scene's plane receivers at ``frame``."""
    n = scene.receivers.points.shape[0]
    return render(scene, frame).radiance[:n]


def relative_mse(pred: jax.Array, target: jax.Array) -> jax.Array:
    """mean((pred − target)²) / mean(target²) (0 for a perfect fit, 1 for predicting zeros)."""
    return jnp.mean((pred - target) ** 2) / jnp.maximum(jnp.mean(target**2), 1e-30)


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
) -> FitResult:
    """Minimise :func:`relative_mse` of the plane radiance over the parameters with optax (Adam).

    Args:
        make_scene: parameters (a list of arrays) → scene; must be traceable (``build_scene`` of a
            config with the parameters set by ``eqx.tree_at`` is).
        init: starting values.
        target: (N_plane, 3) target radiance.
        frame: the animation frame rendered.
        regularization: weight w of the penalty ``w · Σ ‖p − p_init‖²`` added to the loss.
    """
    params = [jnp.asarray(p, jnp.float32) for p in init]
    opt = optimizer or optax.adam(learning_rate)
    state = opt.init(params)

    start = [jnp.asarray(p) for p in params]

    def loss_fn(p):
        loss = relative_mse(plane_radiance(make_scene(p), frame), target)
        if regularization:
            loss = loss + regularization * sum(jnp.sum((a - b) ** 2) for a, b in zip(p, start, strict=True))
        return loss

    @eqx.filter_jit
    def step(params, state):
        loss, g = jax.value_and_grad(loss_fn)(params)
        updates, state = opt.update(g, state, params)
        return optax.apply_updates(params, updates), state, loss

    result = FitResult(params=params)
    it = range(steps)
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(it, desc="fit", unit="step")
    for _ in it:
        result.history.append([np.asarray(p).tolist() for p in params])
        params, state, loss = step(params, state)
        result.loss.append(float(loss))
        if progress:
            it.set_postfix(loss=f"{float(loss):.3e}")
    result.params = params
    return result
