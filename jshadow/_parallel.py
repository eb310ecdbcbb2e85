"""Placing work on several JAX devices with :mod:`jax.sharding` (receivers and frames).

Receivers are independent of one another, so a frame's receiver axis is split over a one-axis
device mesh (:func:`receiver_mesh`, :func:`shard_rows`): arrays of shape (N, ...) are laid out with
``NamedSharding(mesh, P("receivers"))`` and every jit-compiled stage that consumes them runs on each
device for its block (computation follows data). Frames are independent as well; they are assigned
to devices round-robin (:func:`frame_devices`) and each device's frames run on its own placed copy
of the scene (:func:`put_on`).

On CPU, several host devices can be simulated with ``XLA_FLAGS=--xla_force_host_platform_device_count=N``
set before JAX is imported. Nothing here imports the rest of jshadow.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import Array, Shaped

__all__ = [
    "RECEIVER_AXIS",
    "select_devices",
    "receiver_mesh",
    "pad_rows",
    "shard_rows",
    "frame_devices",
    "put_on",
]

RECEIVER_AXIS = "receivers"


def select_devices(devices: int | Sequence[jax.Device] | None = None) -> list[jax.Device]:
    """The devices to use: all of ``jax.devices()`` for None, the first n for an integer n >= 1, or
    the given sequence. Raises ``ValueError`` when more are asked for than exist."""
    available = jax.devices()
    if devices is None:
        return list(available)
    if isinstance(devices, int | np.integer) and not isinstance(devices, bool):
        n = int(devices)
        if not 1 <= n <= len(available):
            raise ValueError(
                f"devices must be in 1..{len(available)} (the JAX devices available: "
                f"{', '.join(str(d) for d in available)}), got {n}"
            )
        return list(available[:n])
    out = list(devices)
    if not out or not all(isinstance(d, jax.Device) for d in out):
        raise ValueError(
            f"devices must be None, a positive integer or a list of jax devices, got {devices!r}"
        )
    return out


def receiver_mesh(devices: int | Sequence[jax.Device] | None = None) -> Mesh:
    """A one-axis device mesh (axis name :data:`RECEIVER_AXIS`) over :func:`select_devices`."""
    return Mesh(np.asarray(select_devices(devices), dtype=object), (RECEIVER_AXIS,))


def pad_rows(x: Shaped[Array, "N ..."], size: int) -> Shaped[Array, "size ..."]:
    """``x`` padded to ``size`` rows by repeating its last row (padding stays a valid receiver, so
    no NaN enters through it). Requires ``1 <= N <= size``."""
    n = x.shape[0]
    if not 1 <= n <= size:
        raise ValueError(f"pad_rows needs between 1 and {size} rows, got {n}")
    if n == size:
        return x
    return jnp.concatenate([x, jnp.broadcast_to(x[-1:], (size - n, *x.shape[1:]))], axis=0)


def shard_rows(x: Shaped[Array, "N ..."], mesh: Mesh) -> Shaped[Array, "N ..."]:
    """``x`` laid out over ``mesh`` along its first axis (N must be a multiple of the mesh size)."""
    n_dev = mesh.devices.size
    if x.shape[0] % n_dev:
        raise ValueError(f"shard_rows needs a row count divisible by {n_dev} devices, got {x.shape[0]} rows")
    spec = PartitionSpec(RECEIVER_AXIS, *([None] * (x.ndim - 1)))
    return jax.device_put(x, NamedSharding(mesh, spec))


def frame_devices(n_frames: int, devices: int | Sequence[jax.Device] | None = None) -> list[jax.Device]:
    """The device of each of ``n_frames`` frames, assigned round-robin over :func:`select_devices`."""
    devs = select_devices(devices)
    return [devs[f % len(devs)] for f in range(n_frames)]


def put_on(tree, device: jax.Device):
    """A copy of a pytree with every JAX array leaf committed to ``device`` (other leaves kept)."""
    return jax.tree_util.tree_map(
        lambda x: jax.device_put(x, device) if isinstance(x, jax.Array) else x, tree
    )
