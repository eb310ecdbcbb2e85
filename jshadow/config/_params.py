"""Dotted parameter paths into a config ("occluder.0.deform.amount"), for fitting and sweeps."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._errors import ConfigError, did_you_mean

__all__ = ["get_param", "set_param", "param_paths"]

_POSITIVE = ("radius", "size", "period")  # leaves that must stay > 0


def _is_float_leaf(x) -> bool:
    return isinstance(x, jax.Array) and jnp.issubdtype(x.dtype, jnp.floating)


def _fields(obj) -> dict[str, bool]:
    """Field name -> is it a (differentiable) leaf field, for a config Module."""
    return {f.name: not f.metadata.get("static", False) for f in dataclasses.fields(obj)}


def param_paths(config) -> list[str]:
    """Every dotted path of ``config`` that names a float leaf (what ``[fit] params`` may list)."""
    out: list[str] = []

    def walk(obj, prefix):
        if isinstance(obj, tuple):
            for i, x in enumerate(obj):
                walk(x, f"{prefix}{i}.")
        elif isinstance(obj, eqx.Module):
            for name, is_leaf in _fields(obj).items():
                if is_leaf and name != "fit":
                    walk(getattr(obj, name), f"{prefix}{name}.")
        elif _is_float_leaf(obj):
            out.append(prefix[:-1])

    walk(config, "")
    return out


def _resolve(config, path: str):
    """(getter, value) of ``path``; raises ConfigError naming the first part that does not resolve."""
    source = getattr(config, "source", None)
    if not isinstance(path, str) or not path:
        raise ConfigError(source, None, f"expected a dotted parameter path, got {path!r}")
    parts = path.split(".")
    obj = config
    getters = []
    for depth, part in enumerate(parts):
        done = ".".join(parts[:depth]) or "the config"
        if isinstance(obj, tuple):
            if not part.isdigit():
                raise ConfigError(source, path, f"{done} is a list: expected an index, got {part!r}")
            i = int(part)
            if i >= len(obj):
                raise ConfigError(source, path, f"index {i} out of range: {done} has {len(obj)} entries")
            obj = obj[i]
            getters.append(lambda o, i=i: o[i])
        elif isinstance(obj, eqx.Module):
            fields = _fields(obj)
            if part not in fields or part == "fit":
                choices = [f for f in fields if f != "fit"]
                raise ConfigError(source, path, f"{done} has no field {part!r}{did_you_mean(part, choices)}")
            if not fields[part]:
                raise ConfigError(source, path, f"{part!r} is a static setting, not a numeric parameter")
            obj = getattr(obj, part)
            getters.append(lambda o, part=part: getattr(o, part))
        else:
            raise ConfigError(source, path, f"{done} is a value; nothing lies below it")
        if obj is None:
            raise ConfigError(source, path, f"{'.'.join(parts[: depth + 1])} is not set in this config")
    if not _is_float_leaf(obj):
        raise ConfigError(source, path, "does not name a numeric value (expected a number or vector)")

    def get(c):
        for g in getters:
            c = g(c)
        return c

    return get, obj


def get_param(config, path: str) -> jax.Array:
    """The float leaf of ``config`` at the dotted ``path`` (list indices as numbers), e.g.
    ``get_param(cfg, "occluder.0.deform.amount")`` or ``get_param(cfg, "light.0.center")``.

    Raises :class:`ConfigError` naming the path when it does not resolve to a numeric leaf.
    """
    return _resolve(config, path)[1]


def set_param(config, path: str, value):
    """A copy of ``config`` with the leaf at ``path`` replaced by ``value`` (``eqx.tree_at``).

    ``value`` must have the leaf's shape; it is cast to the leaf's dtype. Traced values (under
    ``jax.grad``/``jax.jvp``) pass through, so fitting differentiates through this. Concrete values
    must be finite (and positive for radii, sizes and periods). Raises :class:`ConfigError` naming
    the path otherwise.
    """
    get, old = _resolve(config, path)
    source = getattr(config, "source", None)
    if isinstance(value, bool) or isinstance(value, str):
        raise ConfigError(source, path, f"expected a number or vector, got {value!r}")
    try:
        new = jnp.asarray(value)
    except TypeError as err:
        raise ConfigError(source, path, f"expected a number or vector: {err}") from None
    if not (jnp.issubdtype(new.dtype, jnp.floating) or jnp.issubdtype(new.dtype, jnp.integer)):
        raise ConfigError(source, path, f"expected a number or vector, got dtype {new.dtype}")
    if new.shape != old.shape:
        raise ConfigError(source, path, f"expected shape {old.shape}, got {new.shape}")
    new = new.astype(old.dtype)
    if not isinstance(new, jax.core.Tracer):
        arr = np.asarray(new)
        if not np.all(np.isfinite(arr)):
            raise ConfigError(source, path, f"expected finite numbers, got {arr.tolist()}")
        if path.rsplit(".", 1)[-1] in _POSITIVE and not np.all(arr > 0):
            raise ConfigError(source, path, f"expected positive numbers, got {arr.tolist()}")
    return eqx.tree_at(get, config, new)
