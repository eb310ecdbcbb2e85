"""Frozen configuration objects that mirror the TOML scene description (DESIGN.md §4).

Tables become attributes, ``[[occluder]]`` / ``[[light]]`` become tuples ``occluder`` / ``light``.
Numbers that describe the scene (centres, radii, radiances, sizes, deformation amounts) are JAX float
array leaves, so ``eqx.tree_at`` can replace them and ``jax.jvp``/``jax.grad`` can differentiate
:func:`jshadow.config.build_scene` with respect to them. Strings, paths, booleans, counts and shapes,
and the options of ``[method]`` are static fields.

Every object checks its own invariants when constructed (``__check_init__``): array shapes always,
values (finite, positive) when they are concrete. ``eqx.tree_at`` does not re-run these checks;
:func:`jshadow.config.set_param` checks what it sets. The loader (:mod:`._load`) validates the raw
TOML first and names the exact key path in its errors.
"""

from __future__ import annotations

import equinox as eqx
import jax
import numpy as np
from jaxtyping import Array, Float

from ..entities import BSV_CENTERS as BSV_CENTERS
from ..entities import BSV_GRADIENTS as BSV_GRADIENTS
from ..entities import BSV_IMAGES as BSV_IMAGES
from ..entities import CONTACT_VISIBILITIES as CONTACT_VISIBILITIES
from ..entities import LAMP_PENUMBRAE as LAMP_PENUMBRAE
from ..entities import LIGHT_IMAGES as LIGHT_IMAGES
from ..entities import LIGHT_VISIBILITIES as LIGHT_VISIBILITIES
from ..entities import SELF_VISIBILITIES as SELF_VISIBILITIES
from ..entities import Method
from ._errors import ConfigError

__all__ = [
    "MethodConfig",
    "EnvironmentConfig",
    "DeformConfig",
    "OccluderConfig",
    "LightConfig",
    "ReceiverConfig",
    "AnimationConfig",
    "FitConfig",
    "Config",
    "ENVIRONMENT_TYPES",
    "OCCLUDER_TYPES",
    "MESH_SHAPES",
    "LIGHT_TYPES",
    "RECEIVER_TYPES",
    "MODELS",
    "SHADINGS",
    "PRESETS",
]

ENVIRONMENT_TYPES = ("constant", "hdr", "sky")
OCCLUDER_TYPES = ("sphere", "mesh")
MESH_SHAPES = ("egg", "icosphere")
LIGHT_TYPES = ("sphere",)
RECEIVER_TYPES = ("plane",)
MODELS = ("paper", "sphere")
SHADINGS = ("product", "ratio")
PRESETS = ("default", "paper")


def _check_leaf(owner: str, name: str, value, shape: tuple[int, ...] | None, positive: bool = False):
    """Shape (always) and finiteness/positivity (for concrete values) of one float leaf."""
    key = f"{owner}.{name}"
    if value is None:
        raise ConfigError(None, key, "missing value")
    if not hasattr(value, "shape") or not hasattr(value, "dtype"):
        raise ConfigError(None, key, f"expected a float array, got {type(value).__name__}")
    if not np.issubdtype(value.dtype, np.floating):
        raise ConfigError(None, key, f"expected a float array, got dtype {value.dtype}")
    if shape is not None and tuple(value.shape) != shape:
        raise ConfigError(None, key, f"expected shape {shape}, got {tuple(value.shape)}")
    if isinstance(value, jax.core.Tracer):
        return
    arr = np.asarray(value)
    if not np.all(np.isfinite(arr)):
        raise ConfigError(None, key, f"expected finite numbers, got {arr.tolist()}")
    if positive and not np.all(arr > 0):
        raise ConfigError(None, key, f"expected positive numbers, got {arr.tolist()}")


# what an "auto" option of [method] means where build_scene has not decided it (MethodConfig.to_method)
_AUTO_FALLBACK = {
    "bsv_images": "samples",
    "light_visibility": "sh",
    "environment_lights": 0,
    "self_visibility": "field",
    "directions": (32, 32),
    "light_cap": (4, 8),
    "lamp_images": 0,
    "self_maps_grid": (8, 16),
    "self_maps_resolution": 64,
    "contact_visibility": "field",
    "lamp_penumbrae": "none",
}


class MethodConfig(eqx.Module):
    """``[method]``: the static options of :class:`jshadow.entities.Method` (every key optional).

    ``preset`` "default" | "paper" chooses the defaults of ``shell``, ``model``, ``bsv_bands``,
    ``shading`` and ``bsv_center``: the accurate setting, or the deformable-shadow-fields paper's
    method exactly (:meth:`jshadow.entities.Method.paper`); keys given explicitly override the
    preset.

    ``sh_bands`` n (n² coefficients, 1..8), ``bsv_grid`` (θ, φ) sample points on the bounding sphere
    (Zhou et al. 2005 use 12×20), ``directions`` per sample point ("auto", the default: 64 × 64
    where ``light_visibility = "auto"`` takes the occlusion images, which are that many pixels,
    else 32 × 32), ``dtype`` "float32" | "float64",
    ``shell`` sampling-shell radius over bounding radius (≥ 1; 1 is the paper), ``model`` "paper" |
    "sphere" (extrapolation model), ``radial_samples`` tabulated distances, ``d_range`` their range in
    shell radii, ``bsv_method`` "auto" | "brute" | "edgescan", ``bsv_center`` "placed" | "box" (a
    deforming mesh's bounding-sphere centre: its placed ``center``, or its box centre per pose; the
    paper's), ``bsv_bands`` bands of the BSV and
    M_k (≥ ``sh_bands``; default ``sh_bands`` + 1, or ``sh_bands`` for the paper), ``shading``
    "ratio" | "product" (see :func:`jshadow.scene.combine`), ``bsv_gradient`` "auto" | "raycast" |
    "image" | "scanline" (visibility in the BSV's vertex derivative, see :class:`jshadow.entities.Method`),
    ``self_visibility`` "auto" | "field" | "rays" | "light_rays" | "maps" (an occluder's
    visibility at its own vertices with ``self_shadow``: extrapolated by the field, each vertex's
    transfer cast by rays, the field's with rays toward the environment lights, or "rays"'
    quantities from depth images and rays against nearby faces; "auto", the default: "rays" where
    every mesh keeps its shape, or where closed deforming meshes under an environment not split
    into lamps are small enough to cast every frame, else "maps" for closed meshes, else "field",
    :func:`jshadow.config.auto_light_path`) and
    ``self_visibility_grid`` (θ, φ) ray directions over each vertex's normal hemisphere for "rays",
    ``light_visibility`` "auto" | "sh" | "images" (how mesh occluders shadow sphere lights: the
    field's SH, or rays to the light looked up in the BSV's images; "auto", the default: "images"
    where they apply and a sphere light or a lat-long map is there to shadow, unless ``[fit]`` is
    given, see :func:`jshadow.config.build_scene`), ``light_cap`` (rings, sectors) of those
    rays per light ("auto", the default: 8 × 16 where ``light_visibility = "auto"`` takes the
    images, else 4 × 8), ``light_images`` "samples" | "coverage" (the images those rays read),
    ``bsv_images`` "auto" | "samples" | "coverage" (the images a mesh's BSV is projected from; "auto":
    "coverage" where the config's ``[fit]`` fits a mesh's deformation and every mesh allows it, so
    that the fitted loss is continuous in the shape and its gradient exact, else "samples"; see
    :func:`jshadow.config.build_scene`), and
    ``environment_lights`` "auto" | K (0, or a power of two: the lat-long map's radiance
    above ``environment_threshold`` (default 2) × its mean split off as K distant lights shadowed through the
    images; :mod:`jshadow.envlights`; "auto", the default: where ``light_visibility = "auto"``
    takes the images and the environment is a lat-long map, 256 over meshes that keep their
    shape, 128 over a mesh that deforms — 64 unless 128 lamps' images cost at most
    :data:`jshadow.config.AUTO_LAMP_TESTS_PER_FACE` pixel tests per face — else 0), and
    ``lamp_images`` "auto" |
    R (0, or ≥ 8: those lights looked up in orthographic R × R images of each mesh along their
    directions instead of the shell's images, :mod:`jshadow.visibility._lamps`; "auto", the
    default: 128 where ``environment_lights = "auto"`` takes the lights, else 0), and for
    ``self_visibility = "maps"`` ``self_maps_grid`` "auto" | (θ, φ) (the own vertices' transfer
    over that sphere grid) and ``self_maps_resolution`` "auto" | R (≥ 8: its depth images' pixels
    per side); "auto", the defaults: 12 × 24 at R from the meshes' edge lengths where an
    environment reaches the vertices through the transfer alone, else 8 × 16 at 64
    (:func:`jshadow.config.auto_light_path`). ``contact_visibility`` "auto" | "field" | "rays"
    (the fixed receivers next to a mesh: the field's visibility and the images' lookups, or exact
    rays, :class:`jshadow.entities.Method`; "auto", the default: "rays" where every mesh keeps its
    shape, they are cast once, and over a deforming mesh where a frame's casts take at most
    :data:`jshadow.config.AUTO_CONTACT_TESTS` ray–triangle tests, else "field").
    ``lamp_penumbrae`` "auto" | "none" | "region" (lamp lookups widened to the penumbrae of the
    map regions the lamps stand for, :class:`jshadow.entities.Method`; "auto", the default:
    "region" where the lamp images are taken and the fixed receivers times the lamps are at most
    :data:`jshadow.config.AUTO_PENUMBRA_PAIRS`, else "none").
    """

    preset: str = eqx.field(static=True, default="default")
    sh_bands: int = eqx.field(static=True, default=4)
    bsv_grid: tuple[int, int] = eqx.field(static=True, default=(12, 20))
    directions: tuple[int, int] | str = eqx.field(static=True, default="auto")
    dtype: str = eqx.field(static=True, default="float32")
    shell: float = eqx.field(static=True, default=1.5)
    model: str = eqx.field(static=True, default="sphere")
    radial_samples: int = eqx.field(static=True, default=16)
    d_range: tuple[float, float] = eqx.field(static=True, default=(0.2, 8.0))
    bsv_method: str = eqx.field(static=True, default="auto")
    bsv_center: str = eqx.field(static=True, default="placed")
    bsv_bands: int | None = eqx.field(static=True, default=None)
    shading: str = eqx.field(static=True, default="ratio")
    bsv_gradient: str = eqx.field(static=True, default="auto")
    self_visibility: str = eqx.field(static=True, default="auto")
    self_visibility_grid: tuple[int, int] = eqx.field(static=True, default=(12, 48))
    light_visibility: str = eqx.field(static=True, default="auto")
    light_cap: tuple[int, int] | str = eqx.field(static=True, default="auto")
    light_images: str = eqx.field(static=True, default="samples")
    bsv_images: str = eqx.field(static=True, default="auto")
    environment_lights: int | str = eqx.field(static=True, default="auto")
    environment_threshold: float = eqx.field(static=True, default=2.0)
    lamp_images: int | str = eqx.field(static=True, default="auto")
    self_maps_grid: tuple[int, int] | str = eqx.field(static=True, default="auto")
    self_maps_resolution: int | str = eqx.field(static=True, default="auto")
    contact_visibility: str = eqx.field(static=True, default="auto")
    lamp_penumbrae: str = eqx.field(static=True, default="auto")

    def __check_init__(self):
        if self.model not in MODELS:
            raise ConfigError(
                None, "method.model", f"expected one of {', '.join(MODELS)}, got {self.model!r}"
            )
        # explicit environment lights with light_visibility "auto": checked as the images they
        # need (build_scene says so if "auto" does not take the images for the config)
        k = self.environment_lights
        self.to_method(light_visibility="images" if k not in (0, "auto") else None)

    def to_method(self, **decided) -> Method:
        """The :class:`jshadow.entities.Method` these options describe. The options that may be
        "auto" (``bsv_images``, ``light_visibility``, ``environment_lights``, ``self_visibility``,
        ``directions``, ``light_cap``, ``lamp_images``, ``self_maps_grid``, ``self_maps_resolution``)
        take the value given for them in ``decided`` — what
        :func:`jshadow.config.build_scene` decides for a config
        (:func:`jshadow.config._build._bsv_images`, :func:`~jshadow.config._build._light_path`) —
        or, without one, the library's default ("samples", "sh", 0, "field", 32 × 32, 4 × 8, 0,
        8 × 16, 64)."""
        chosen = {}
        for name, fallback in _AUTO_FALLBACK.items():
            value = getattr(self, name)
            chosen[name] = value if value != "auto" else (decided.get(name) or fallback)
        try:
            return Method(
                sh_bands=self.sh_bands,
                bsv_grid=tuple(self.bsv_grid),
                directions=tuple(chosen["directions"]),
                dtype=self.dtype,
                shell=float(self.shell),
                model=self.model,
                radial_samples=self.radial_samples,
                d_range=tuple(float(d) for d in self.d_range),
                bsv_method=self.bsv_method,
                bsv_center=self.bsv_center,
                bsv_bands=self.bsv_bands,
                shading=self.shading,
                bsv_gradient=self.bsv_gradient,
                self_visibility=chosen["self_visibility"],
                self_visibility_grid=tuple(self.self_visibility_grid),
                light_visibility=chosen["light_visibility"],
                light_cap=tuple(chosen["light_cap"]),
                light_images=self.light_images,
                bsv_images=chosen["bsv_images"],
                environment_lights=chosen["environment_lights"],
                environment_threshold=float(self.environment_threshold),
                lamp_images=chosen["lamp_images"],
                self_maps_grid=tuple(chosen["self_maps_grid"]),
                self_maps_resolution=chosen["self_maps_resolution"],
                contact_visibility=chosen["contact_visibility"],
                lamp_penumbrae=chosen["lamp_penumbrae"],
            )
        except (ValueError, TypeError) as err:
            raise ConfigError(None, None, str(err)) from None


class EnvironmentConfig(eqx.Module):
    """``[environment]``: distant light.

    ``type`` "constant" | "hdr" | "sky"; ``radiance`` (3,) linear RGB (the colour, or the multiplier
    of the map or sky); ``file`` the resolved path of the lat-long map (type "hdr" only);
    ``rotation_y`` radians about +y, counter-clockwise seen from above (a feature in direction d moves
    to R_y(rotation_y)·d).
    """

    type: str = eqx.field(static=True)
    radiance: Float[Array, "3"]
    rotation_y: Float[Array, ""]
    file: str | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        if self.type not in ENVIRONMENT_TYPES:
            raise ConfigError(None, "environment.type", f"expected one of {', '.join(ENVIRONMENT_TYPES)}")
        if (self.type == "hdr") != (self.file is not None):
            raise ConfigError(None, "environment.file", "required for type 'hdr' and only for it")
        _check_leaf("environment", "radiance", self.radiance, (3,))
        _check_leaf("environment", "rotation_y", self.rotation_y, ())


class DeformConfig(eqx.Module):
    """``deform = {type, amount, ...}`` of a mesh occluder (see :func:`jshadow.geometry.make_deformation`).

    ``amount`` is a scalar (constant over the animation) or a pair (start, end), shape () or (2,).
    ``axis``/``toward`` ("x" | "y" | "z") and ``origin`` are static; ``period`` (breathe) is a leaf.
    Unset options are ``None`` (the deformation's default).
    """

    type: str = eqx.field(static=True)
    amount: Float[Array, ""] | Float[Array, "2"]
    period: Float[Array, ""] | None = None
    axis: str | None = eqx.field(static=True, default=None)
    toward: str | None = eqx.field(static=True, default=None)
    origin: float | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        _check_leaf("deform", "amount", self.amount, None)
        if self.amount.shape not in ((), (2,)):
            raise ConfigError(
                None, "deform.amount", f"expected a number or a pair, got shape {self.amount.shape}"
            )
        if self.period is not None:
            _check_leaf("deform", "period", self.period, (), positive=True)

    def params(self) -> dict:
        """The keyword options for :func:`jshadow.geometry.make_deformation` (those that are set)."""
        out = {}
        for name in ("axis", "toward", "origin", "period"):
            v = getattr(self, name)
            if v is not None:
                out[name] = v
        return out


class OccluderConfig(eqx.Module):
    """``[[occluder]]``: a sphere, or a mesh whose bounding sphere is placed at ``center``/``radius``.

    A mesh comes from ``file`` (resolved path) or from a procedural ``shape`` ("egg" | "icosphere",
    with ``subdivisions`` and, for the egg, ``stretch``); ``up`` ("x" | "y" | "z", default "y") names
    the mesh file's up axis, which is turned onto the world's +y by a 90° rotation (for "z": about x,
    (x, y, z) → (x, z, −y); for "x": about z, (x, y, z) → (−y, x, z)); ``deform`` is optional (meshes
    only) and acts in the rotated, normalised frame.
    """

    type: str = eqx.field(static=True)
    center: Float[Array, "3"]
    radius: Float[Array, ""]
    file: str | None = eqx.field(static=True, default=None)
    shape: str | None = eqx.field(static=True, default=None)
    subdivisions: int = eqx.field(static=True, default=3)
    stretch: float = eqx.field(static=True, default=0.2)
    up: str = eqx.field(static=True, default="y")
    deform: DeformConfig | None = None

    def __check_init__(self):
        if self.type not in OCCLUDER_TYPES:
            raise ConfigError(None, "occluder.type", f"expected one of {', '.join(OCCLUDER_TYPES)}")
        _check_leaf("occluder", "center", self.center, (3,))
        _check_leaf("occluder", "radius", self.radius, (), positive=True)
        if self.type == "mesh" and (self.file is None) == (self.shape is None):
            raise ConfigError(None, "occluder.file", "a mesh needs exactly one of 'file' or 'shape'")
        if self.type == "sphere" and (self.file, self.shape, self.deform) != (None, None, None):
            raise ConfigError(None, "occluder", "a sphere takes no 'file', 'shape' or 'deform'")
        if self.up not in ("x", "y", "z"):
            raise ConfigError(None, "occluder.up", f"expected 'x', 'y' or 'z', got {self.up!r}")
        if self.shape is not None and self.shape not in MESH_SHAPES:
            raise ConfigError(None, "occluder.shape", f"expected one of {', '.join(MESH_SHAPES)}")


class LightConfig(eqx.Module):
    """``[[light]]``: a spherical light of uniform radiance (3,) linear RGB."""

    type: str = eqx.field(static=True)
    center: Float[Array, "3"]
    radius: Float[Array, ""]
    radiance: Float[Array, "3"]

    def __check_init__(self):
        if self.type not in LIGHT_TYPES:
            raise ConfigError(None, "light.type", f"expected one of {', '.join(LIGHT_TYPES)}")
        _check_leaf("light", "center", self.center, (3,))
        _check_leaf("light", "radius", self.radius, (), positive=True)
        _check_leaf("light", "radiance", self.radiance, (3,))


class ReceiverConfig(eqx.Module):
    """``[receiver]``: a plane of ``resolution`` = (nx, nz) vertices spanning ``size`` = (w, d) in x and z,
    centred at ``center`` (height ``center[1]``), normal +y, diffuse ``albedo`` (3,).
    ``self_shadow``: the mesh occluders' own vertices are receivers too (appended after the plane's).
    """

    type: str = eqx.field(static=True)
    center: Float[Array, "3"]
    size: Float[Array, "2"]
    albedo: Float[Array, "3"]
    resolution: tuple[int, int] = eqx.field(static=True)
    self_shadow: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        if self.type not in RECEIVER_TYPES:
            raise ConfigError(None, "receiver.type", f"expected one of {', '.join(RECEIVER_TYPES)}")
        _check_leaf("receiver", "center", self.center, (3,))
        _check_leaf("receiver", "size", self.size, (2,), positive=True)
        _check_leaf("receiver", "albedo", self.albedo, (3,))
        if len(self.resolution) != 2 or min(self.resolution) < 1:
            raise ConfigError(
                None, "receiver.resolution", f"expected two integers >= 1, got {self.resolution}"
            )


class AnimationConfig(eqx.Module):
    """``[animation]``: ``frames`` ≥ 1 (frame f is at time t = f / (frames − 1), see entities.frame_time)."""

    frames: int = eqx.field(static=True, default=1)

    def __check_init__(self):
        if self.frames < 1:
            raise ConfigError(None, "animation.frames", f"expected an integer >= 1, got {self.frames}")


class FitConfig(eqx.Module):
    """``[fit]``: which numeric leaves to fit, and to what.

    ``params`` dotted paths into the config ("occluder.0.deform.amount", "light.0.center");
    ``target_values`` one value per parameter (the target is rendered with them), or
    ``target_image`` a picture of the receiver plane (resolved path); ``init`` start values (``None``:
    the config's own values); ``steps`` optimiser steps, ``learning_rate`` Adam's step size;
    ``regularization`` weight of the penalty ``Σ ‖p − p_init‖²`` (0: none); ``frame`` the frame fitted.
    """

    params: tuple[str, ...] = eqx.field(static=True)
    target_values: tuple | None = None
    init: tuple | None = None
    target_image: str | None = eqx.field(static=True, default=None)
    steps: int = eqx.field(static=True, default=200)
    learning_rate: float = eqx.field(static=True, default=0.05)
    regularization: float = eqx.field(static=True, default=0.0)
    frame: int = eqx.field(static=True, default=0)

    def __check_init__(self):
        if not self.params:
            raise ConfigError(None, "fit.params", "expected at least one parameter path")
        if (self.target_values is None) == (self.target_image is None):
            raise ConfigError(None, "fit", "expected exactly one of 'target_values' or 'target_image'")
        for name in ("target_values", "init"):
            v = getattr(self, name)
            if v is not None and len(v) != len(self.params):
                raise ConfigError(
                    None, f"fit.{name}", f"expected {len(self.params)} values (one per param), got {len(v)}"
                )
        if self.steps < 1:
            raise ConfigError(None, "fit.steps", f"expected an integer >= 1, got {self.steps}")
        if not self.learning_rate > 0:
            raise ConfigError(
                None, "fit.learning_rate", f"expected a positive number, got {self.learning_rate}"
            )
        if not self.regularization >= 0:
            raise ConfigError(
                None, "fit.regularization", f"expected a number >= 0, got {self.regularization}"
            )


class Config(eqx.Module):
    """A whole scene configuration (plus an optional ``[fit]``); build it with :func:`build_scene`.

    ``source`` is the file it came from (used in error messages), ``root`` the folder that relative
    paths were resolved against.
    """

    method: MethodConfig
    receiver: ReceiverConfig
    environment: EnvironmentConfig | None = None
    occluder: tuple[OccluderConfig, ...] = ()
    light: tuple[LightConfig, ...] = ()
    animation: AnimationConfig = AnimationConfig()
    fit: FitConfig | None = None
    source: str = eqx.field(static=True, default="<config>")
    root: str = eqx.field(static=True, default=".")

    def __check_init__(self):
        if not isinstance(self.occluder, tuple) or not all(
            isinstance(o, OccluderConfig) for o in self.occluder
        ):
            raise ConfigError(self.source, "occluder", "expected a tuple of OccluderConfig")
        if not isinstance(self.light, tuple) or not all(isinstance(o, LightConfig) for o in self.light):
            raise ConfigError(self.source, "light", "expected a tuple of LightConfig")
