"""From a validated :class:`~._schema.Config` to a :class:`jshadow.entities.Scene`.

``build_scene`` is traceable: it is a pure function of the config's float leaves (centres, radii,
radiances, sizes, deformation amounts, the environment's rotation), so ``jax.jvp``/``jax.grad``
differentiate through it and it may run under ``jax.jit`` with the config as an argument. Files
(meshes, environment maps) are read once per path and kept as NumPy arrays in a cache, so tracing
does not re-read them.
"""

from __future__ import annotations

import functools
import math
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..entities import (
    Environment,
    MeshOccluder,
    Receivers,
    Scene,
    SphereLight,
    SphereOccluder,
    shape_is_static,
)
from ._errors import ConfigError
from ._schema import _AUTO_FALLBACK, Config, OccluderConfig

__all__ = ["build_scene", "plane_receivers", "rotate_latlong_y", "clear_file_cache"]


def _dtype(config: Config):
    return jax.dtypes.canonicalize_dtype(np.dtype(config.method.dtype))


def plane_receivers(
    center: Float[Array, "3"],
    size: Float[Array, "2"],
    resolution: tuple[int, int],
    albedo: Float[Array, "3"],
) -> Receivers:
    """A plane of receiver vertices at height ``center[1]``, normal +y (DESIGN.md §4 ``[receiver]``).

    ``resolution`` = (nx, nz) vertices spanning ``size`` = (w, d) scene units in x and z, centred at
    ``center``: x_c = cx + w·(c/(nx−1) − ½), z_r = cz + d·(r/(nz−1) − ½) (a single vertex sits at the
    centre). Points are in row-major order, rows along z and columns along x: index ``r·nx + c``;
    ``grid_shape`` = (nz, nx). Differentiable in ``center``, ``size`` and ``albedo``.
    """
    nx, nz = (int(n) for n in resolution)
    if nx < 1 or nz < 1:
        raise ValueError(f"plane resolution must be two integers >= 1, got {tuple(resolution)}")
    center, size = jnp.asarray(center), jnp.asarray(size)
    dtype = center.dtype

    def offsets(n):
        return jnp.zeros((1,), dtype) if n == 1 else jnp.linspace(-0.5, 0.5, n, dtype=dtype)

    x = center[0] + size[0] * offsets(nx)  # (nx,)
    z = center[2] + size[1] * offsets(nz)  # (nz,)
    xx = jnp.broadcast_to(x[None, :], (nz, nx))
    zz = jnp.broadcast_to(z[:, None], (nz, nx))
    yy = jnp.broadcast_to(center[1], (nz, nx))
    points = jnp.stack([xx, yy, zz], axis=-1).reshape(nz * nx, 3)
    normals = jnp.broadcast_to(jnp.asarray([0.0, 1.0, 0.0], dtype), (nz * nx, 3))
    return Receivers(points=points, normals=normals, albedo=jnp.asarray(albedo), grid_shape=(nz, nx))


def rotate_latlong_y(image: Float[Array, "H W C"], angle: Float[Array, ""] | float) -> Float[Array, "H W C"]:
    """Rotate a lat-long environment map about +y by ``angle`` radians.

    Positive angles turn the map counter-clockwise seen from above (right-handed about +y): the
    radiance that arrived from direction d arrives from R_y(angle)·d afterwards. With the lat-long
    convention of :func:`jshadow.entities.latlong_to_dir` (φ = 2πu counter-clockwise from +x) that is
    L'(φ) = L(φ − angle): a shift of the columns by +angle·W/(2π), linear between columns (exact
    ``np.roll`` for multiples of 2π/W), wrapping around. Differentiable in ``angle`` (piecewise
    linear).
    """
    image = jnp.asarray(image)
    w = image.shape[1]
    angle = jnp.asarray(angle, image.dtype)
    s = jnp.arange(w, dtype=image.dtype) - angle * (w / (2.0 * jnp.pi))  # source column of each column
    j0 = jnp.floor(s)
    frac = (s - j0)[None, :, None]
    j0 = j0.astype(jnp.int32) % w
    j1 = (j0 + 1) % w
    return (1.0 - frac) * image[:, j0] + frac * image[:, j1]


@functools.lru_cache(maxsize=64)
def _mesh_arrays(key: tuple, dtype_name: str) -> tuple[np.ndarray, np.ndarray, str]:
    """(unit vertices, faces, name) of a mesh file or procedural shape, cached by path/parameters."""
    from ..geometry import egg, icosphere, load_mesh, normalize_to_unit_sphere

    with jax.ensure_compile_time_eval():  # concrete even inside a trace: the cache holds no tracers
        if key[0] == "file":
            mesh = load_mesh(key[1], dtype=dtype_name)
            name = pathlib.Path(key[1]).stem
        elif key[1] == "egg":
            mesh = egg(key[2], stretch=key[3], dtype=dtype_name)
            name = "egg"
        else:
            mesh = icosphere(key[2], dtype=dtype_name)
            name = "icosphere"
        v = np.asarray(mesh.vertices)
        up = key[-1]
        if up == "z":  # rotation about x by -90°: +z -> +y, +y -> -z
            v = np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1)
        elif up == "x":  # rotation about z by +90°: +x -> +y, +y -> -x
            v = np.stack([-v[:, 1], v[:, 0], v[:, 2]], axis=1)
        unit = normalize_to_unit_sphere(jnp.asarray(v))
        return np.asarray(unit), np.asarray(mesh.faces), name


def _unit_mesh(config: Config, i: int, occ: OccluderConfig) -> tuple[np.ndarray, np.ndarray, str]:
    if occ.file is not None:
        key = ("file", occ.file, occ.up)
        where = f"occluder[{i}].file"
    else:
        key = ("shape", occ.shape, occ.subdivisions, float(occ.stretch), occ.up)
        where = f"occluder[{i}].shape"
    try:
        return _mesh_arrays(key, np.dtype(_dtype(config)).name)
    except ConfigError:
        raise
    except (ValueError, OSError) as err:
        # load_mesh's errors already name the (resolved) file; procedural shapes are named here
        msg = str(err) if occ.file else f"cannot build mesh {occ.shape!r}: {err}"
        raise ConfigError(config.source, where, msg) from None


@functools.lru_cache(maxsize=16)
def _latlong_array(path: str) -> np.ndarray:
    from ..lights import read_latlong

    return np.asarray(read_latlong(path))


def _environment_image(config: Config) -> np.ndarray:
    try:
        return _latlong_array(config.environment.file)
    except (ValueError, OSError) as err:
        raise ConfigError(config.source, "environment.file", str(err)) from None


def clear_file_cache() -> None:
    """Forget the meshes and environment maps read so far (e.g. after a file changed on disk)."""
    _mesh_arrays.cache_clear()
    _latlong_array.cache_clear()


def _occluder(config: Config, i: int, occ: OccluderConfig, dtype):
    center, radius = occ.center.astype(dtype), occ.radius.astype(dtype)
    if occ.type == "sphere":
        return SphereOccluder(center=center, radius=radius)
    from ..geometry import make_deformation

    unit, faces, name = _unit_mesh(config, i, occ)
    deform = None
    if occ.deform is not None:
        params = occ.deform.params()
        if "period" in params:
            params["period"] = params["period"].astype(dtype)
        try:
            deform = make_deformation(occ.deform.type, occ.deform.amount.astype(dtype), **params)
        except ValueError as err:
            raise ConfigError(config.source, f"occluder[{i}].deform", str(err)) from None
    # The mesh read from file is data, not a parameter: keep it concrete even when build_scene runs
    # under jit/grad, so that the BSV can use the topology statically (edge tables, slot counts).
    with jax.ensure_compile_time_eval():
        unit_vertices, faces = jnp.asarray(unit, dtype), jnp.asarray(faces, jnp.int32)
    return MeshOccluder(
        unit_vertices=unit_vertices,
        faces=faces,
        center=center,
        radius=radius,
        deform=deform,
        name=name,
    )


def _bsv_images(config: Config, occluders: tuple) -> str:
    """What ``[method] bsv_images = "auto"`` means for this config: "coverage" if its ``[fit]`` fits
    a mesh occluder's deformation (a parameter path ``occluder.<i>.deform…``) and the coverage BSV
    applies (shell > 1, ``bsv_gradient = "auto"``, every mesh closed and consistently wound), else
    "samples". The coverage BSV makes the fitted loss continuous in the shape and its gradient the
    exact derivative of that loss (BENCHMARKS.md, "Fitting": the bend fit reaches 0.80000 for a
    target of 0.8 where the samples' staircase stalls it at 0.63, 0.73 with 32² directions);
    rendering alone keeps the cheaper samples."""
    from ..geometry import mesh_is_closed_manifold

    m = config.method
    meshes = [o for o in occluders if isinstance(o, MeshOccluder)]
    fitted = set()
    for path in config.fit.params if config.fit is not None else ():
        parts = path.split(".")
        if len(parts) >= 3 and parts[0] == "occluder" and parts[1].isdigit() and parts[2] == "deform":
            fitted.add(int(parts[1]))
    if not any(isinstance(occluders[i], MeshOccluder) for i in fitted if i < len(occluders)):
        return "samples"
    if not (m.shell > 1.0 and m.bsv_gradient == "auto"):
        return "samples"
    closed = all(mesh_is_closed_manifold(np.asarray(o.faces)) for o in meshes)  # faces are concrete
    return "coverage" if closed else "samples"


AUTO_ENVIRONMENT_LIGHTS = 128  # what environment_lights = "auto" takes for a lat-long map
# ... over meshes that keep their shape, whose lamp images and visible fractions are made once per
# shape: against 128, the twisted airplane under the studio map 0.44 -> 0.33 % relative RMSE (max
# 4.0 -> 2.9 %), the studio bunny 0.60 -> 0.58 % (max 5.2 -> 4.9 %), spot_sunset 0.79 -> 0.78 %,
# their first frames 101 -> 173, 1424 -> 1621 and 87 -> 158 ms (the paper's 208, 122 and 184 ms),
# later frames 1 ms either way; 512 lamps gave spot_sunset 0.78 % again at 250 ms (BENCHMARKS.md
# "The default against the paper", seventh run)
AUTO_ENVIRONMENT_LIGHTS_STATIC = 256
# ... over a mesh that deforms, whose lamp images are made every frame (the animated bunny: 1.23 %
# relative RMSE with 64, 1.26 % with 128, at 1.45x and 1.88x the paper's frame in one run of
# distinct frames at its 160² plane, margins of 2 pixels then; BENCHMARKS.md "Self-shadowing by
# depth images")
AUTO_ENVIRONMENT_LIGHTS_DEFORMING = 64
# ... unless 128 lamps' images cost no more pixel tests per face than that: their images are
# K·Σ stamp²/2 pixel tests a frame (entry faces), the paper's BSV about 245,760 ray tests per face,
# so per face is the ratio that the 1.5x budget bounds. 3500 lies between the bending airplane's
# 128 lamps (2499: 0.41-0.46x the paper's frame) and the animated bunny's 128 (5311), whose 64
# (2655) take 1.33-1.34x the paper's frame at its 160² plane with the ambiguous pairs settled (BENCHMARKS.md
# "The default against the paper, every scene in one run", fifth run; windows of powers of two)
AUTO_LAMP_TESTS_PER_FACE = 3500.0


def lamp_tests_per_face(meshes, lamps: int, resolution: int) -> float:
    """Pixel tests per face of ``lamps`` entry-face lamp images at ``resolution`` pixels
    (:func:`jshadow.visibility.lamp_images`: each face's stamp² window per direction, about half
    of the faces entering), the largest over ``meshes`` (rest poses); inf where one is traced."""
    from ..visibility import stamp_groups

    worst = 0.0
    for o in meshes:
        if isinstance(o.unit_vertices, jax.core.Tracer):
            return math.inf
        f = np.asarray(o.faces)
        with jax.ensure_compile_time_eval():  # concrete under a traced build_scene too
            groups = stamp_groups(np.asarray(o.unit_vertices), f, resolution)
        per_face = sum(len(i) * s * s for i, s in groups) / max(f.shape[0], 1)
        worst = max(worst, 0.5 * lamps * per_face)
    return worst


# the n-band light path: what the light options' "auto" falls back to (MethodConfig.to_method's too)
_LIGHT_KEYS = (
    "light_visibility",
    "environment_lights",
    "self_visibility",
    "directions",
    "light_cap",
    "lamp_images",
    "self_maps_grid",
    "self_maps_resolution",
    "contact_visibility",
    "lamp_penumbrae",
)
_N_BAND = {k: _AUTO_FALLBACK[k] for k in _LIGHT_KEYS}
# what directions = "auto" and light_cap = "auto" take with the occlusion images: sharper images
# and twice the cap directions each way (BENCHMARKS.md "The default against the paper")
AUTO_IMAGE_DIRECTIONS = (64, 64)
AUTO_LIGHT_CAP = (8, 16)
# pixels per side of the orthographic images that a static mesh's map lamps are looked up in
AUTO_LAMP_IMAGES = 128
# self_visibility = "maps" where an environment reaches the own vertices through their transfer
# alone (no lamps split off): a finer sphere grid, in images whose pixel is about a third of the
# mesh's median edge (the bending spot cow under a sky 2.07 -> 1.03 % at 128² pixels, 0.99 % at
# 160² at 1.17x the paper's fresh frame; the bending bunny 1.47 -> 0.89 % at 96², 1.2-1.35x in
# three runs; BENCHMARKS.md "The default against the paper, every scene in one run", fourth and
# fifth runs). 3.0 pixels per median edge, within 64-160: the cow 160, the bunny 96 (at 2.8 the
# cow took 128; both meshes were used to choose it)
AUTO_MAPS_GRID = (12, 24)
# ... unless the deforming meshes' own vertices are cheap enough to cast by rays every frame: at most
# this many (vertex, face) pairs summed over them (each vertex's 12 x 48 hemisphere against the faces
# above its plane within its sectors, jshadow.visibility.hemisphere_fan_any_hit: the bunny's 1901 x
# 3798 = 7.2e6 in 0.15 s, the spot cow's 2930 x 5856 = 1.7e7 in 0.29 s, benchmarks/bench_own_rays.py).
# The bending bunny under a sky 0.89 -> 0.43 % relative RMSE, max 10.4 -> 4.8 %, at 150-215 ms a
# frame against the paper's 120-160 ms in earlier runs; the bending cow's frame 300-330 ms against
# the paper's 176-236 ms (1.3-1.9x; max 8.2 -> 4.4 %, on a 10 x 40 grid too), so it keeps "maps"
# (BENCHMARKS.md "Deforming meshes' own vertices by rays")
AUTO_SELF_RAYS_PAIRS = 1.0e7
# a deforming mesh's receivers next to it (contact_visibility) are cast every frame: "auto" casts them
# where they take at most this many ray-triangle tests per frame at four times of the animation
# (jshadow.scene.contact_ray_tests; about 0.2 s at the 5e9 tests per second measured here, the
# twisting cow's 4.8e8 tests in 91 ms; the paper's frames take 0.12-0.19 s), else keeps the field:
# the twisting spot cow 0.05 above its floor 1.90 -> 0.53 % relative RMSE at a 32² plane (98 ms per
# frame), not at 128² (5.3e9 tests)
AUTO_CONTACT_TESTS = 1.0e9
# lamp_penumbrae = "auto": the lookups widened to the lamps' regions where the fixed receivers times
# the lamps are at most this many pairs. They cost 43-48 ns a pair alone (the plain lookup 5 ns; the
# animated bunny's 160² plane and 64 lamps: 70-77 against 7.7-7.8 ms,
# benchmarks/bench_lamp_penumbra.py) and about 75 ns in a frame (the bending airplane's 1024 x 128:
# shading 4.0 -> 13.9 ms), so this bounds them to about 20 ms a frame
AUTO_PENUMBRA_PAIRS = 2**18
AUTO_MAPS_EDGE_PIXELS = 3.0
AUTO_MAPS_RESOLUTION = (64, 160)  # the range of that resolution, in steps of 32


def own_ray_pairs(meshes) -> float:
    """(vertex, face) pairs of the deforming ``meshes``' own-vertex casts per frame: V·F summed over
    those that do not keep their shape (:func:`jshadow.entities.shape_is_static`), what
    :data:`AUTO_SELF_RAYS_PAIRS` bounds; the shapes of traced vertices count as well."""
    return float(sum(o.unit_vertices.shape[0] * o.faces.shape[0] for o in meshes if not shape_is_static(o)))


def maps_resolution(meshes) -> int:
    """Pixels per side of the own-vertex depth images at which the median edge of the finest of
    ``meshes`` (rest poses) spans :data:`AUTO_MAPS_EDGE_PIXELS` pixels of the bounding diameter,
    rounded up to a multiple of 32 within :data:`AUTO_MAPS_RESOLUTION` (the spot cow: 160, the
    bunny: 96)."""
    lo, hi = AUTO_MAPS_RESOLUTION
    need = lo
    for o in meshes:
        if isinstance(o.unit_vertices, jax.core.Tracer):  # traced (build_scene under jit): the floor
            continue
        v = np.asarray(o.unit_vertices, np.float64)
        f = np.asarray(o.faces)
        e = np.concatenate([v[f[:, i]] - v[f[:, (i + 1) % 3]] for i in range(3)])
        center = 0.5 * (v.max(0) + v.min(0))
        diameter = 2.0 * np.linalg.norm(v - center, axis=1).max()
        edge = float(np.median(np.linalg.norm(e, axis=1))) / diameter
        if edge > 0:
            need = max(need, 32 * math.ceil(AUTO_MAPS_EDGE_PIXELS / edge / 32))
    return int(min(max(need, lo), hi))


def auto_light_path(
    occluders,
    has_lights: bool,
    hdr: bool,
    self_shadow: bool,
    shell: float,
    bsv_method: str,
    environment: bool = True,
    receivers=None,
) -> dict:
    """The light path the "auto" options take for a scene's content, as the ``[method]`` keys
    ``light_visibility``, ``environment_lights``, ``self_visibility``, ``directions``,
    ``light_cap`` and ``lamp_images``. Where the occlusion images apply (shell > 1 and
    ``bsv_method`` not "brute", at least one mesh occluder and every mesh closed):

    * a lat-long map (``hdr``) has its bright part split off as K distant lights, each looked up
      in orthographic images of every mesh along its direction, :data:`AUTO_LAMP_IMAGES` pixels
      wide: K = :data:`AUTO_ENVIRONMENT_LIGHTS_STATIC` (256) over meshes that keep their shape
      (:func:`jshadow.entities.shape_is_static`; images made once per shape, and the visible
      fractions too, :class:`jshadow.Renderer`; the untuned twisted airplane under the studio map
      2.84 → 0.53 % relative RMSE with 32 lamps, BENCHMARKS.md "Lamp images", 0.33 % with 256),
      K = :data:`AUTO_ENVIRONMENT_LIGHTS` (128) over a mesh that deforms, whose images are made
      every frame, or :data:`AUTO_ENVIRONMENT_LIGHTS_DEFORMING` (64) where 128 would cost more than
      :data:`AUTO_LAMP_TESTS_PER_FACE` pixel tests per face (:func:`lamp_tests_per_face`; the
      animated bunny 23.1 → 0.69 % with its vertices' "maps" below and 64 lamps, at 1.33–1.34× the
      paper's frame at its shipped plane; the bending airplane keeps 128, 0.60 → 0.43 %;
      BENCHMARKS.md "The default against the paper", fourth to sixth runs);
    * sphere lights (``has_lights``) are shadowed through the shell's images;

    light visibility "images" if the first or second applies, with shell images of
    :data:`AUTO_IMAGE_DIRECTIONS` pixels and :data:`AUTO_LIGHT_CAP` directions per sphere light
    where there are sphere lights (the bent airplane's largest error 8.0 → 4.0 %, its frame 12 →
    17 ms at 32²), else 32 × 32 and 4 × 8; otherwise "sh" (the n-band path) with K = 0.
    Independently of the images, where the own vertices are receivers (``self_shadow``):
    ``self_visibility = "rays"`` if every mesh keeps its shape: each own vertex's shadowed
    transfer by rays (and its visibility of the lamps where they are split off), cast once,
    instead of the field's extrapolation inward (:func:`jshadow.scene.occluder_own_visibility`;
    the bunny's vertices under a sky 9.7 → 0.3 % relative RMSE, BENCHMARKS.md "The default
    against the paper, every scene in one run"); "maps" for closed meshes that deform: the same
    two quantities from depth images and rays against each vertex's nearby faces, made every
    frame (cheaper than the cast and less accurate: the bunny's vertices under a sky 1.8 % against
    0.3 %; :mod:`jshadow.visibility._own_maps`); else "field". Where an ``environment`` not split
    into lamps reaches the own vertices through their transfer alone, deforming meshes whose casts
    take at most :data:`AUTO_SELF_RAYS_PAIRS` (vertex, face) pairs a frame (:func:`own_ray_pairs`)
    take "rays" instead, cast every frame (the bending bunny under a sky: max 10.4 → 4.8 %); with
    "maps" there the transfer takes :data:`AUTO_MAPS_GRID` directions in images of
    :func:`maps_resolution` pixels (``self_maps_grid``, ``self_maps_resolution``; else 8 × 16 at
    64: where lamps carry the map's bright part the transfer carries its dim rest, the animated
    bunny's vertices 1.40 % either way, and "rays" would add the lamp rays every frame: 354 ms, about
    2.4× the paper's frame, with the same max in a probe, BENCHMARKS.md "Deforming meshes' own
    vertices by rays").
    Where every mesh keeps its shape, ``contact_visibility = "rays"``: the fixed receivers within
    :data:`jshadow.scene.CONTACT_REACH` of a mesh's bounding radius from its vertices (or its
    large faces) take its
    visibility, and the lights' visible fractions, from exact rays instead of the field's
    extrapolation inward and the images' lookups, made once (:func:`jshadow.scene.contact_rows_at_time`;
    the untuned spot cow 0.05 above its floor under a sphere light and a sky 2.12 → 0.54 %, the
    bunny 0.05 above its floor under the studio map 0.70 → 0.41 %, max 11.9 → 2.7 %; BENCHMARKS.md
    "The default against the paper", eighth run). Over a deforming mesh they are cast every frame:
    "rays" where ``receivers`` (the fixed receivers' points) are given and the casts take at most
    :data:`AUTO_CONTACT_TESTS` ray–triangle tests per frame at four times of the animation
    (:func:`jshadow.scene.contact_ray_tests`), else "field".
    With the lamp images, ``lamp_penumbrae = "region"`` where the fixed ``receivers`` times the
    lamps are at most :data:`AUTO_PENUMBRA_PAIRS` (each lookup widened to the penumbra of the map
    region its lamp stands for, about 10× the plain lookup's cost; the animated bunny at a 32²
    plane: max 10.1 → 6.7 %, BENCHMARKS.md "Lamp penumbrae"), else "none".
    (For a config, :func:`build_scene` asks this only for the default preset without ``[fit]``.)

    Why: the n-band path cannot shadow small bright sources within the accuracy targets (exact
    4-band visibility at every receiver still leaves 2.5–19 % relative RMSE on the shipped
    sphere-light and map scenes, BENCHMARKS.md "The floor of any extrapolation model"); through
    the images the sphere-light scenes reach 0.5–1.0 % (BENCHMARKS.md "The default against the
    paper"), at 2.6–3.0× the n-band path's warm frame on the deforming configs (a fresh frame about
    the same), 0.07–0.25× the paper's."""
    from ..geometry import mesh_is_closed_manifold

    meshes = [o for o in occluders if isinstance(o, MeshOccluder)]
    static = bool(meshes) and all(shape_is_static(o) for o in meshes)
    closed = bool(meshes) and all(mesh_is_closed_manifold(np.asarray(o.faces)) for o in meshes)
    own = "field"
    if self_shadow and static:
        own = "rays"
    elif self_shadow and closed:
        own = "maps"
    applies = shell > 1.0 and bsv_method != "brute" and closed  # faces are concrete
    k = 0
    if hdr and bool(meshes):
        k = AUTO_ENVIRONMENT_LIGHTS_STATIC if static else AUTO_ENVIRONMENT_LIGHTS
        if not static and lamp_tests_per_face(meshes, k, AUTO_LAMP_IMAGES) > AUTO_LAMP_TESTS_PER_FACE:
            k = AUTO_ENVIRONMENT_LIGHTS_DEFORMING
    images = applies and (has_lights or k)
    through_transfer = environment and not (images and k)  # no lamps split off: the transfer carries it
    if own == "maps" and through_transfer and own_ray_pairs(meshes) <= AUTO_SELF_RAYS_PAIRS:
        own = "rays"
    contact = {"contact_visibility": "rays" if static else "field"}
    maps = {key: _N_BAND[key] for key in ("self_maps_grid", "self_maps_resolution")}
    if own == "maps" and through_transfer:
        maps = {"self_maps_grid": AUTO_MAPS_GRID, "self_maps_resolution": maps_resolution(meshes)}
    if meshes and not static and receivers is not None:
        # a deforming mesh's contact rows are cast every frame: where they are affordable
        from ..scene import CONTACT_GRID, contact_ray_tests

        lamps = k if images else 0
        cap = AUTO_LIGHT_CAP if images and has_lights else (0, 0)
        # the whole grid's rays: where the mesh lies above the receivers' planes half of them are cast
        rays = math.prod(CONTACT_GRID) + lamps + (cap[0] * cap[1] if has_lights else 0)
        if contact_ray_tests(occluders, receivers, rays) <= AUTO_CONTACT_TESTS:
            contact = {"contact_visibility": "rays"}
    pairs = (receivers.shape[0] if receivers is not None else math.inf) * k
    penumbrae = "region" if images and k and pairs <= AUTO_PENUMBRA_PAIRS else "none"
    if images:
        return {
            "light_visibility": "images",
            "environment_lights": k,
            "self_visibility": own,
            # the shell's images are read for sphere lights only (a map's lamps have their own)
            "directions": AUTO_IMAGE_DIRECTIONS if has_lights else _N_BAND["directions"],
            "light_cap": AUTO_LIGHT_CAP if has_lights else _N_BAND["light_cap"],
            "lamp_images": AUTO_LAMP_IMAGES if k else 0,
            "lamp_penumbrae": penumbrae,
            **maps,
            **contact,
        }
    return dict(_N_BAND, self_visibility=own, **maps, **contact)


def _light_path(config: Config, occluders: tuple, has_lights: bool, receivers=None) -> dict:
    """What ``[method] light_visibility``, ``environment_lights``, ``self_visibility``,
    ``directions`` and ``light_cap`` = "auto" (the defaults) mean for this config, as those keys
    (an explicit value of one is kept by :meth:`MethodConfig.to_method`): :func:`auto_light_path`
    for the default preset without ``[fit]``, else the n-band path ("sh", 0, "field"). An explicit
    ``light_visibility`` is kept, and with "auto" lights gets K = 0 and "field" (what they meant
    before "auto");
    explicit environment lights need the images; an explicit ``self_visibility`` is kept
    (:meth:`MethodConfig.to_method`).

    A fit keeps the n-band path: its gradient costs 1.7–12× less than the images' (BENCHMARKS.md
    "Gradients through the occlusion images"), and the fitted parameters do not need the shadow's
    sharpness, only a loss that the same method renders for the target and the fit."""
    m = config.method
    env = config.environment
    hdr = env is not None and env.type == "hdr"
    chosen = dict(_N_BAND)
    if m.light_visibility != "auto":
        chosen["light_visibility"] = m.light_visibility
    elif m.preset == "default" and config.fit is None:
        self_shadow = config.receiver.self_shadow
        chosen = auto_light_path(
            occluders,
            has_lights,
            hdr,
            self_shadow,
            m.shell,
            m.bsv_method,
            environment=env is not None,
            receivers=receivers,
        )
    visibility = chosen["light_visibility"]
    k = m.environment_lights
    if k not in (0, "auto") and visibility != "images":
        raise ConfigError(
            config.source,
            "method.environment_lights",
            f"{k} environment lights are shadowed through the occlusion images, which "
            "light_visibility = 'auto' does not take for this config (they need the default preset, "
            "no [fit], shell > 1, the edge-scan, closed meshes and a sphere light or a lat-long map): "
            "set light_visibility = 'images', or leave environment_lights out",
        )
    if k != "auto":
        chosen["environment_lights"] = k
    return chosen


def build_scene(config: Config) -> Scene:
    """The :class:`jshadow.entities.Scene` that ``config`` describes.

    * ``Method`` from ``[method]``; arrays in its dtype (float32 unless float64 is requested and
      JAX's x64 mode is on).
    * Receivers: :func:`plane_receivers` of ``[receiver]`` (row-major, rows along z).
    * Occluders in config order: ``SphereOccluder``, or ``MeshOccluder`` whose rest pose is the mesh
      normalised to its unit bounding sphere (AABB centre, radius to the farthest vertex) and placed
      at ``center`` with bounding radius ``radius``, deformed by ``make_deformation(type, amount,
      ...)``.
    * Lights: ``SphereLight``; environment: ``Environment`` ("hdr": the lat-long map from
      :func:`jshadow.lights.read_latlong`, rotated by :func:`rotate_latlong_y`).
    * ``n_frames`` = ``[animation] frames``; ``self_shadow`` from ``[receiver]``.
    * ``[method] bsv_images = "auto"`` (the default) is "coverage" where ``[fit]`` fits a mesh's
      deformation and the coverage BSV applies, else "samples" (:func:`_bsv_images`).
    * ``[method] light_visibility``, ``environment_lights``, ``self_visibility``, ``directions``,
      ``light_cap`` and ``lamp_images`` = "auto" (the defaults) shadow sphere lights through the
      occlusion images, and the lamps of a lat-long map over meshes that keep their shape through
      orthographic lamp images (256 distant lights), where they apply and no ``[fit]`` is given,
      else through the n-band path; the own vertices of meshes that keep their shape get their
      transfer cast by rays (:func:`auto_light_path`, :func:`_light_path`).

    Traceable and differentiable in every float leaf of ``config`` (``eqx.tree_at`` + ``jax.jvp``).
    Raises :class:`ConfigError` naming the key when a mesh or map cannot be read.
    """
    if not isinstance(config, Config):
        raise ConfigError(
            None, None, f"build_scene expects a Config (from load_config), got {type(config).__name__}"
        )
    dtype = _dtype(config)
    rc = config.receiver
    receivers = plane_receivers(
        rc.center.astype(dtype), rc.size.astype(dtype), rc.resolution, rc.albedo.astype(dtype)
    )
    occluders = tuple(_occluder(config, i, occ, dtype) for i, occ in enumerate(config.occluder))
    lights = tuple(
        SphereLight(
            center=lc.center.astype(dtype), radius=lc.radius.astype(dtype), radiance=lc.radiance.astype(dtype)
        )
        for lc in config.light
    )
    environment = None
    ec = config.environment
    if ec is not None:
        radiance = ec.radiance.astype(dtype)
        if ec.type == "hdr":
            image = rotate_latlong_y(
                jnp.asarray(_environment_image(config), dtype), ec.rotation_y.astype(dtype)
            )
            environment = Environment(radiance=radiance, image=image, kind="hdr")
        else:
            environment = Environment(radiance=radiance, kind=ec.type)
    return Scene(
        method=config.method.to_method(
            bsv_images=_bsv_images(config, occluders),
            **_light_path(config, occluders, bool(lights), receivers.points),
        ),
        receivers=receivers,
        occluders=occluders,
        lights=lights,
        environment=environment,
        self_shadow=rc.self_shadow,
        n_frames=config.animation.frames,
    )
