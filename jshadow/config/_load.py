"""Reading and validating TOML scene configs (DESIGN.md §4) into :class:`~._schema.Config`.

Every problem raises :class:`ConfigError` with one line naming the file and the key path:
unknown keys and tables (with a difflib suggestion), missing required keys, wrong types (a string
or a boolean where a number is expected, a vector of the wrong length), non-finite numbers,
non-positive sizes, radii and resolutions, bad enum values, missing mesh or environment-map files
(relative paths resolve against the config file's folder), unreadable meshes, TOML syntax errors
(with their line), and ``[fit]`` parameter paths that do not name a numeric leaf of the config.
"""

from __future__ import annotations

import math
import os
import pathlib
import tomllib
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from ._errors import ConfigError, did_you_mean
from ._schema import (
    BSV_CENTERS,
    BSV_GRADIENTS,
    BSV_IMAGES,
    CONTACT_VISIBILITIES,
    ENVIRONMENT_TYPES,
    LAMP_PENUMBRAE,
    LIGHT_IMAGES,
    LIGHT_TYPES,
    LIGHT_VISIBILITIES,
    MESH_SHAPES,
    MODELS,
    OCCLUDER_TYPES,
    PRESETS,
    RECEIVER_TYPES,
    SELF_VISIBILITIES,
    SHADINGS,
    AnimationConfig,
    Config,
    DeformConfig,
    EnvironmentConfig,
    FitConfig,
    LightConfig,
    MethodConfig,
    OccluderConfig,
    ReceiverConfig,
)

__all__ = ["load_config", "config_from_dict"]

_REQUIRED = object()
_TOP = ("method", "environment", "occluder", "light", "receiver", "animation", "fit")
_ARRAYS = ("occluder", "light")  # [[...]] tables


def _describe(v) -> str:
    if isinstance(v, bool):
        return f"{str(v).lower()} (a boolean)"
    if isinstance(v, str):
        return f"{v!r} (a string)"
    if isinstance(v, Mapping):
        return "a table"
    if isinstance(v, list | tuple):
        return f"a list of {len(v)} value(s)"
    return repr(v)


def _is_number(v) -> bool:
    return isinstance(v, int | float | np.integer | np.floating) and not isinstance(v, bool | np.bool_)


class _Table:
    """One TOML table being read: remembers its key path and rejects unknown keys up front."""

    def __init__(self, source: str, root: pathlib.Path, data, path: str, label: str, allowed):
        self.source, self.root, self.path = source, root, path
        if not isinstance(data, Mapping):
            raise ConfigError(source, path, f"expected a table, got {_describe(data)}")
        self.data = dict(data)
        for key in self.data:
            if key not in allowed:
                raise ConfigError(source, None, f"unknown key {key!r} in {label}{did_you_mean(key, allowed)}")

    def key(self, name: str) -> str:
        return f"{self.path}.{name}" if self.path else name

    def error(self, name: str, message: str) -> ConfigError:
        return ConfigError(self.source, self.key(name), message)

    def has(self, name: str) -> bool:
        return name in self.data

    def raw(self, name: str, default=_REQUIRED):
        if name in self.data:
            return self.data[name]
        if default is _REQUIRED:
            raise ConfigError(self.source, self.key(name), f"missing required key {name!r}")
        return default

    # --- typed readers ---------------------------------------------------------------------------
    def _number(self, name: str, v, check: str | None, where: str = "") -> float:
        if not _is_number(v):
            raise self.error(name, f"expected a number{where}, got {_describe(v)}")
        x = float(v)
        if not math.isfinite(x):
            raise self.error(name, f"expected a finite number{where}, got {x}")
        if check == "positive" and not x > 0:
            raise self.error(name, f"expected a positive number{where}, got {x}")
        if check == "nonneg" and not x >= 0:
            raise self.error(name, f"expected a number >= 0{where}, got {x}")
        if check == ">=1" and not x >= 1:
            raise self.error(name, f"expected a number >= 1{where}, got {x}")
        return x

    def number(self, name: str, default=_REQUIRED, check: str | None = None) -> float:
        v = self.raw(name, default)
        return v if v is None else self._number(name, v, check)

    def vector(self, name: str, n: int, default=_REQUIRED, check: str | None = None) -> list[float] | None:
        v = self.raw(name, default)
        if v is None:
            return None
        if not isinstance(v, list | tuple):
            raise self.error(name, f"expected a list of {n} numbers, got {_describe(v)}")
        if len(v) != n:
            raise self.error(name, f"expected a list of {n} numbers, got {len(v)} value(s)")
        return [self._number(name, x, check, where=f" at index {i}") for i, x in enumerate(v)]

    def integer(self, name: str, default=_REQUIRED, lo: int | None = None, hi: int | None = None) -> int:
        v = self.raw(name, default)
        return self._integer(name, v, lo, hi)

    def _integer(self, name, v, lo, hi, where: str = "") -> int:
        if isinstance(v, bool) or not isinstance(v, int | np.integer):
            raise self.error(name, f"expected an integer{where}, got {_describe(v)}")
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            rng = f"in {lo}..{hi}" if lo is not None and hi is not None else f">= {lo}"
            raise self.error(name, f"expected an integer {rng}{where}, got {v}")
        return int(v)

    def integers(self, name: str, n: int, default=_REQUIRED, lo: int | None = None) -> tuple[int, ...]:
        v = self.raw(name, default)
        if not isinstance(v, list | tuple):
            raise self.error(name, f"expected a list of {n} integers, got {_describe(v)}")
        if len(v) != n:
            raise self.error(name, f"expected a list of {n} integers, got {len(v)} value(s)")
        return tuple(self._integer(name, x, lo, None, where=f" at index {i}") for i, x in enumerate(v))

    def string(self, name: str, default=_REQUIRED, choices=None) -> str | None:
        v = self.raw(name, default)
        if v is None:
            return None
        if not isinstance(v, str):
            raise self.error(name, f"expected a string, got {_describe(v)}")
        if choices is not None and v not in choices:
            opts = " | ".join(repr(c) for c in choices)
            raise self.error(name, f"expected one of {opts}, got {v!r}{did_you_mean(v, choices)}")
        return v

    def boolean(self, name: str, default=_REQUIRED) -> bool:
        v = self.raw(name, default)
        if not isinstance(v, bool):
            raise self.error(name, f"expected true or false, got {_describe(v)}")
        return v

    def file(self, name: str, what: str) -> str:
        v = self.string(name)
        p = pathlib.Path(os.path.expanduser(v))
        p = p if p.is_absolute() else self.root / p
        if not p.is_file():
            raise self.error(name, f"{what} file not found: {v} (looked for {p})")
        return str(p.resolve())


def _leaf(x, dtype) -> jax.Array:
    return jnp.asarray(np.asarray(x, dtype=np.float64), dtype=dtype)


# --- tables ---------------------------------------------------------------------------------------
_METHOD_KEYS = (
    "preset",
    "sh_bands",
    "bsv_grid",
    "directions",
    "dtype",
    "shell",
    "model",
    "radial_samples",
    "d_range",
    "bsv_method",
    "bsv_center",
    "bsv_bands",
    "shading",
    "bsv_gradient",
    "self_visibility",
    "self_visibility_grid",
    "light_visibility",
    "light_cap",
    "light_images",
    "bsv_images",
    "environment_lights",
    "lamp_images",
    "environment_threshold",
    "self_maps_grid",
    "self_maps_resolution",
    "contact_visibility",
    "lamp_penumbrae",
)


def _auto_or(t: _Table, name: str, read):
    """ "auto" where the key is absent or "auto", else what ``read()`` reads and checks."""
    return "auto" if t.raw(name, "auto") == "auto" else read()


def _method(t: _Table) -> MethodConfig:
    d_range = tuple(t.vector("d_range", 2, [0.2, 8.0], check="positive"))
    if not d_range[0] < d_range[1]:
        raise t.error("d_range", f"expected two increasing distances, got {list(d_range)}")
    preset = t.string("preset", "default", choices=PRESETS)
    sh_bands = t.integer("sh_bands", 4, lo=1, hi=8)
    paper = preset == "paper"
    cfg = dict(
        preset=preset,
        sh_bands=sh_bands,
        bsv_grid=t.integers("bsv_grid", 2, [12, 20], lo=2),
        directions=_auto_or(t, "directions", lambda: t.integers("directions", 2, [32, 32], lo=2)),
        dtype=t.string("dtype", "float32", choices=("float32", "float64")),
        shell=t.number("shell", 1.0 if paper else 1.5, check=">=1"),
        model=t.string("model", "paper" if paper else "sphere", choices=MODELS),
        radial_samples=t.integer("radial_samples", 16, lo=2),
        d_range=d_range,
        bsv_method=t.string("bsv_method", "auto", choices=("auto", "brute", "edgescan")),
        bsv_center=t.string("bsv_center", "box" if paper else "placed", choices=BSV_CENTERS),
        bsv_bands=(
            t.integer("bsv_bands", 4, lo=1, hi=8) if t.has("bsv_bands") else (sh_bands if paper else None)
        ),
        shading=t.string("shading", "product" if paper else "ratio", choices=SHADINGS),
        bsv_gradient=t.string("bsv_gradient", "auto", choices=BSV_GRADIENTS),
        self_visibility=t.string("self_visibility", "auto", choices=("auto", *SELF_VISIBILITIES)),
        self_visibility_grid=t.integers("self_visibility_grid", 2, [12, 48], lo=2),
        light_visibility=t.string("light_visibility", "auto", choices=("auto", *LIGHT_VISIBILITIES)),
        light_cap=_auto_or(t, "light_cap", lambda: t.integers("light_cap", 2, [4, 8], lo=1)),
        light_images=t.string("light_images", "samples", choices=LIGHT_IMAGES),
        bsv_images=t.string("bsv_images", "auto", choices=("auto", *BSV_IMAGES)),
        environment_lights=_auto_or(
            t, "environment_lights", lambda: t.integer("environment_lights", 0, lo=0)
        ),
        environment_threshold=t.number("environment_threshold", 2.0, check="positive"),
        lamp_images=_auto_or(t, "lamp_images", lambda: t.integer("lamp_images", 0, lo=0)),
        self_maps_grid=_auto_or(t, "self_maps_grid", lambda: t.integers("self_maps_grid", 2, [8, 16], lo=2)),
        self_maps_resolution=_auto_or(
            t, "self_maps_resolution", lambda: t.integer("self_maps_resolution", 64, lo=8)
        ),
        contact_visibility=t.string("contact_visibility", "auto", choices=("auto", *CONTACT_VISIBILITIES)),
        lamp_penumbrae=t.string("lamp_penumbrae", "auto", choices=("auto", *LAMP_PENUMBRAE)),
    )
    try:
        return MethodConfig(**cfg)
    except ConfigError as err:
        raise ConfigError(t.source, err.key or "method", err.message) from None


def _environment(t: _Table, dtype) -> EnvironmentConfig:
    kind = t.string("type", choices=ENVIRONMENT_TYPES)
    if kind != "hdr" and t.has("file"):
        raise t.error("file", f"only an environment of type 'hdr' takes a file (this one is {kind!r})")
    file = t.file("file", "environment map") if kind == "hdr" else None
    return EnvironmentConfig(
        type=kind,
        radiance=_leaf(t.vector("radiance", 3, [1.0, 1.0, 1.0], check="nonneg"), dtype),
        rotation_y=_leaf(t.number("rotation_y", 0.0), dtype),
        file=file,
    )


def _deform(t: _Table, dtype) -> DeformConfig:
    from ..geometry import DEFORMATION_TYPES, make_deformation

    kinds = tuple(k for k in DEFORMATION_TYPES if k != "offsets")  # offsets need per-vertex arrays
    kind = t.string("type", choices=kinds)
    allowed = {"type", "amount", *DEFORMATION_TYPES[kind][1]}
    for key in t.data:
        if key not in allowed:
            raise ConfigError(
                t.source,
                None,
                f"unknown key {key!r} in {t.path} for deformation {kind!r}{did_you_mean(key, allowed)}",
            )
    amount = t.raw("amount")
    if isinstance(amount, list | tuple):
        amount = t.vector("amount", 2)
    else:
        amount = t.number("amount")
    axis = t.string("axis", None, choices=("x", "y", "z"))
    toward = t.string("toward", None, choices=("x", "y", "z"))
    origin = t.number("origin", None)
    period = t.number("period", None, check="positive")
    cfg = DeformConfig(
        type=kind,
        amount=_leaf(amount, dtype),
        period=None if period is None else _leaf(period, dtype),
        axis=axis,
        toward=toward,
        origin=origin,
    )
    try:  # the geometry's own checks (e.g. a squash_stretch amount <= -1, toward == axis)
        make_deformation(kind, tuple(amount) if isinstance(amount, list) else amount, **cfg.params())
    except ValueError as err:
        raise ConfigError(t.source, t.path, str(err)) from None
    return cfg


def _occluder(t: _Table, dtype) -> OccluderConfig:
    kind = t.string("type", choices=OCCLUDER_TYPES)
    center = _leaf(t.vector("center", 3), dtype)
    radius = _leaf(t.number("radius", check="positive"), dtype)
    if kind == "sphere":
        for key in ("file", "shape", "subdivisions", "stretch", "up", "deform"):
            if t.has(key):
                raise t.error(key, "only a mesh occluder takes this key (this one is a sphere)")
        return OccluderConfig(type=kind, center=center, radius=radius)
    if t.has("file") == t.has("shape"):
        raise t.error(
            "file", "a mesh occluder needs exactly one of 'file' or 'shape' (\"egg\" | \"icosphere\")"
        )
    file = t.file("file", "mesh") if t.has("file") else None
    shape = t.string("shape", None, choices=MESH_SHAPES)
    if file is not None:
        for key in ("subdivisions", "stretch"):
            if t.has(key):
                raise t.error(key, "only a procedural mesh ('shape') takes this key")
    subdivisions = t.integer("subdivisions", 3, lo=0, hi=6)
    stretch = t.number("stretch", 0.2, check="nonneg")
    if shape != "egg" and t.has("stretch"):
        raise t.error("stretch", 'only shape = "egg" takes a stretch')
    if not stretch < 1.0:
        raise t.error("stretch", f"expected a number in [0, 1), got {stretch}")
    up = t.string("up", "y", choices=("x", "y", "z"))
    deform = None
    if t.has("deform"):
        allowed = ("type", "amount", "axis", "toward", "origin", "period")
        sub = _Table(t.source, t.root, t.data["deform"], t.key("deform"), t.key("deform"), allowed)
        deform = _deform(sub, dtype)
    return OccluderConfig(
        type=kind,
        center=center,
        radius=radius,
        file=file,
        shape=shape,
        subdivisions=subdivisions,
        stretch=stretch,
        up=up,
        deform=deform,
    )


def _light(t: _Table, dtype) -> LightConfig:
    return LightConfig(
        type=t.string("type", "sphere", choices=LIGHT_TYPES),
        center=_leaf(t.vector("center", 3), dtype),
        radius=_leaf(t.number("radius", check="positive"), dtype),
        radiance=_leaf(t.vector("radiance", 3, check="nonneg"), dtype),
    )


MAX_RECEIVERS = 2**31 - 1  # receivers are indexed with int32 (JAX's default integer)


def _receiver(t: _Table, dtype) -> ReceiverConfig:
    resolution = t.integers("resolution", 2, lo=1)
    if resolution[0] * resolution[1] > MAX_RECEIVERS:
        raise t.error(
            "resolution",
            f"expected at most {MAX_RECEIVERS} receivers in all (int32 indices), got "
            f"{resolution[0]} x {resolution[1]} = {resolution[0] * resolution[1]}",
        )
    return ReceiverConfig(
        type=t.string("type", "plane", choices=RECEIVER_TYPES),
        center=_leaf(t.vector("center", 3), dtype),
        size=_leaf(t.vector("size", 2, check="positive"), dtype),
        albedo=_leaf(t.vector("albedo", 3, [0.8, 0.8, 0.8], check="nonneg"), dtype),
        resolution=resolution,
        self_shadow=t.boolean("self_shadow", False),
    )


def _animation(t: _Table) -> AnimationConfig:
    return AnimationConfig(frames=t.integer("frames", 1, lo=1))


_FIT_KEYS = (
    "params",
    "target_values",
    "target_image",
    "init",
    "steps",
    "learning_rate",
    "regularization",
    "frame",
)


def _fit_values(t: _Table, name: str, params, shapes, dtype) -> tuple | None:
    v = t.raw(name, None)
    if v is None:
        return None
    if not isinstance(v, list):
        raise t.error(name, f"expected a list with one value per param, got {_describe(v)}")
    if len(v) != len(params):
        raise t.error(name, f"expected {len(params)} value(s) (one per param), got {len(v)}")
    out = []
    for i, (x, shape) in enumerate(zip(v, shapes)):
        key = f"{name}[{i}]"
        want = "a number" if shape == () else f"a list of {shape[0]} numbers"
        if shape == ():
            if not _is_number(x):
                raise t.error(key, f"expected {want}, got {_describe(x)}")
            x = t._number(key, x, None)
        else:
            if not isinstance(x, list) or len(x) != shape[0]:
                raise t.error(key, f"expected {want} (the shape of {params[i]}), got {_describe(x)}")
            x = [t._number(key, y, None, where=f" at index {j}") for j, y in enumerate(x)]
        out.append(_leaf(x, dtype))
    return tuple(out)


def _fit(t: _Table, partial: Config, dtype) -> FitConfig:
    from ._params import get_param

    params = t.raw("params")
    if not isinstance(params, list) or not params or not all(isinstance(p, str) for p in params):
        raise t.error("params", f"expected a non-empty list of strings, got {_describe(params)}")
    shapes = []
    for i, p in enumerate(params):
        try:
            shapes.append(tuple(get_param(partial, p).shape))
        except ConfigError as err:
            raise ConfigError(t.source, f"fit.params[{i}]", f"{p!r}: {err.message}") from None
    if t.has("target_values") == t.has("target_image"):
        raise t.error("target_values", "expected exactly one of 'target_values' or 'target_image'")
    target_image = t.file("target_image", "target image") if t.has("target_image") else None
    return FitConfig(
        params=tuple(params),
        target_values=_fit_values(t, "target_values", params, shapes, dtype),
        init=_fit_values(t, "init", params, shapes, dtype),
        target_image=target_image,
        steps=t.integer("steps", 200, lo=1),
        learning_rate=t.number("learning_rate", 0.05, check="positive"),
        regularization=t.number("regularization", 0.0, check="nonneg"),
        frame=t.integer("frame", 0, lo=0),
    )


# --- entry points ---------------------------------------------------------------------------------
def config_from_dict(d: Mapping, source: str = "<dict>", root: str | os.PathLike | None = None):
    """Validate a parsed TOML document (nested dicts and lists) into a frozen :class:`Config`.

    Args:
        d: the document, as :func:`tomllib.load` returns it.
        source: names the origin in error messages.
        root: the folder that relative file paths resolve against (default: the working directory).

    Number leaves get the dtype of ``method.dtype`` as JAX can represent it now (float32 when
    float64 is requested but x64 is disabled). Raises :class:`ConfigError`.
    """
    root = pathlib.Path(root if root is not None else os.getcwd())
    try:
        return _from_dict(d, source, root)
    except ConfigError as err:
        if err.source is None:  # raised by a config object's own checks: add the file
            raise ConfigError(source, err.key, err.message) from None
        raise


def _from_dict(d: Mapping, source: str, root: pathlib.Path):
    top = _Table(source, root, d, "", "the config (top level)", _TOP)
    for name in _ARRAYS:
        v = d.get(name, [])
        if not (isinstance(v, list | tuple) and all(isinstance(x, Mapping) for x in v)):
            raise top.error(name, f"expected an array of tables [[{name}]], got {_describe(d[name])}")
    for name in ("method", "environment", "receiver", "animation", "fit"):
        if top.has(name) and not isinstance(d[name], Mapping):
            raise top.error(name, f"expected a table [{name}], got {_describe(d[name])}")

    def table(name, allowed):
        return _Table(source, root, d.get(name, {}), name, f"[{name}]", allowed)

    method = _method(table("method", _METHOD_KEYS))
    dtype = jax.dtypes.canonicalize_dtype(np.dtype(method.dtype))
    environment = None
    if top.has("environment"):
        environment = _environment(table("environment", ("type", "radiance", "file", "rotation_y")), dtype)
    occ_keys = ("type", "center", "radius", "file", "shape", "subdivisions", "stretch", "up", "deform")
    occluders = tuple(
        _occluder(_Table(source, root, o, f"occluder[{i}]", f"occluder[{i}]", occ_keys), dtype)
        for i, o in enumerate(d.get("occluder", []))
    )
    lights = tuple(
        _light(
            _Table(source, root, o, f"light[{i}]", f"light[{i}]", ("type", "center", "radius", "radiance")),
            dtype,
        )
        for i, o in enumerate(d.get("light", []))
    )
    if not top.has("receiver"):
        raise ConfigError(source, "receiver", "missing required table [receiver]")
    receiver = _receiver(
        table("receiver", ("type", "center", "size", "resolution", "albedo", "self_shadow")), dtype
    )
    animation = _animation(table("animation", ("frames",)))
    cfg = Config(
        method=method,
        receiver=receiver,
        environment=environment,
        occluder=occluders,
        light=lights,
        animation=animation,
        source=source,
        root=str(root),
    )
    _check_meshes(cfg)
    if top.has("fit"):
        fit = _fit(table("fit", _FIT_KEYS), cfg, dtype)
        if fit.frame >= animation.frames:
            raise ConfigError(
                source, "fit.frame", f"expected a frame in 0..{animation.frames - 1}, got {fit.frame}"
            )
        cfg = Config(
            method=method,
            receiver=receiver,
            environment=environment,
            occluder=occluders,
            light=lights,
            animation=animation,
            fit=fit,
            source=source,
            root=str(root),
        )
    return cfg


def _check_meshes(cfg: Config) -> None:
    """Read (and cache) every mesh and map now, so that bad files are reported by the loader."""
    from ._build import _environment_image, _unit_mesh

    for i, occ in enumerate(cfg.occluder):
        if occ.type == "mesh":
            _unit_mesh(cfg, i, occ)
    if cfg.environment is not None and cfg.environment.type == "hdr":
        _environment_image(cfg)


def load_config(path: str | os.PathLike) -> Config:
    """Read a TOML scene config (DESIGN.md §4) into a frozen, validated :class:`Config`.

    Relative file paths inside resolve against the config file's folder. Raises
    :class:`ConfigError` (one line: file, key path, what was expected) for every problem, including
    a missing or unreadable file and TOML syntax errors (with the line).
    """
    source = os.fspath(path)
    try:
        with open(source, "rb") as fh:
            doc = tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(source, None, "config file not found") from None
    except IsADirectoryError:
        raise ConfigError(source, None, "expected a TOML file, got a directory") from None
    except OSError as err:
        raise ConfigError(source, None, f"cannot read config file: {err.strerror or err}") from None
    except UnicodeDecodeError as err:
        raise ConfigError(source, None, f"not a UTF-8 text file: {err.reason}") from None
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(source, None, f"TOML syntax error: {err}") from None
    return config_from_dict(doc, source=source, root=pathlib.Path(source).resolve().parent)
