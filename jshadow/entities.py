"""Scene entities as plain data: occluders, lights, receivers, and the method options.

This module sits low in the import order (above ``sh``/``geometry``, below everything that renders),
so that the shadow-field renderer (:mod:`jshadow.scene`) and the Monte Carlo reference
(:mod:`jshadow.reference`) read the *same* scene description without importing each other.

All classes are frozen ``equinox.Module``s. Array fields are pytree leaves (differentiable, e.g.
``jax.grad`` with respect to ``SphereLight.center``); ``eqx.field(static=True)`` fields are not.

Time: an animation of ``n_frames`` frames maps frame ``f`` to ``t = f / (n_frames - 1)`` in [0, 1]
(``t = 0`` for a single frame); deformation parameters are interpolated linearly in ``t``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ._numerics import eps, safe_acos, safe_atan2

__all__ = [
    "Method",
    "SphereOccluder",
    "MeshOccluder",
    "SphereLight",
    "Environment",
    "Receivers",
    "Scene",
    "frame_time",
    "shape_is_static",
    "latlong_to_dir",
    "dir_to_latlong",
    "sky_radiance",
    "receivers_at",
    "receivers_at_time",
    "surface_offset",
    "remembered_rest_shape",
]


SHADINGS = ("product", "ratio")
BSV_GRADIENTS = ("auto", "raycast", "image", "scanline")
BSV_CENTERS = ("placed", "box")
SELF_VISIBILITIES = ("field", "rays", "light_rays", "maps")
CONTACT_VISIBILITIES = ("field", "rays")
LIGHT_VISIBILITIES = ("sh", "images")
LIGHT_IMAGES = ("samples", "coverage")
LAMP_PENUMBRAE = ("none", "region")
BSV_IMAGES = ("samples", "coverage")


@dataclass(frozen=True)
class Method:
    """Static options of the shadow-field method (the ``[method]`` table). Validated on creation.

    The defaults are the accurate setting measured in ``experiments/models.py`` (BENCHMARKS.md,
    "Accuracy beyond the paper"); :meth:`paper` gives the deformable-shadow-fields paper's method
    exactly. The four options that differ:

    * ``shell`` — the BSV is sampled on a shell of ``shell`` × the bounding radius (paper: 1.0, on
      the bounding sphere itself; 1.5 keeps every sample point off the surface and enables the
      edge-scan sampler);
    * ``model`` — the M_k rescaling: "paper" (square silhouette f_k) or "sphere" (concentric
      spheres, asin(k sin θ)); see :mod:`jshadow.scaling`;
    * ``bsv_bands`` — bands in which visibility is sampled and extrapolated before it is truncated
      to ``sh_bands`` (paper: ``sh_bands``; default None = ``sh_bands + 1``, at most 8), so M_k does
      not warp an already-truncated function;
    * ``shading`` — "product" (Zhou et al. 2005: every term an n-band SH product) or "ratio"
      (exact unoccluded irradiance times the SH estimate's occluded/unoccluded ratio; exact sphere
      occluder/sphere light overlap): see :func:`jshadow.scene.combine`.

    ``bsv_center`` chooses the centre of a *deforming* mesh occluder's bounding sphere, about which
    its BSV is sampled: "placed" (default) the occluder's ``center`` (where its rest pose's
    box-centred sphere sits when the rest pose is normalised, as ``build_scene`` normalises it; the
    radius is the farthest deformed vertex from it, per frame), "box" the deformed mesh's own box
    centre, recomputed per pose (:func:`jshadow.geometry.bounding_sphere`; the paper's choice: its
    BSV is the deformed mesh's bounding sphere). A rigid mesh always takes its box-centred sphere.
    The two differ where the deformed mesh's box centre is not ``center``: a deformation that moves
    it, or a rest pose not normalised about its box centre. On the three deforming scenes measured
    their error against the reference differs by at most 0.09 points (relative RMSE; BENCHMARKS.md,
    "A fixed bounding-sphere centre"), and a fixed centre lets :class:`jshadow.Renderer` read frames
    out of the field's table (:mod:`jshadow.readout`).

    ``bsv_gradient`` chooses how the BSV's vertex derivative (its silhouette-edge term) decides which
    silhouette points are visible: "image" (the winding number of the projected silhouette in the
    edge-scan's image plane, exact up to float rounding; :func:`jshadow.visibility.bsv_mesh_edgescan_diff`;
    needs the edge-scan forward pass: shell > 1 and a closed manifold mesh), "raycast" (rays against
    the mesh, :func:`jshadow.visibility.bsv_mesh_diff`; any mesh and shell) or "auto" (default:
    "image" where the forward pass is the edge-scan, else "raycast";
    :func:`jshadow.scene.bsv_gradient_mode`). Both agree with each other and with finite differences
    of whole frames; "image" is 11–31× faster there (BENCHMARKS.md "BSV gradients"). "scanline"
    (:func:`jshadow.visibility.bsv_mesh_edgescan_scan_diff`; needs the edge-scan like "image") takes
    the same boundary integral as a sum over the edge-scan's pixel columns and rows, with the exact
    layer count at every crossing: faster than "image" on the larger meshes (BENCHMARKS.md), as
    accurate along smooth motions, but the gradient of a single vertex is noisier (a Riemann sum at
    the pixel spacing).

    ``self_visibility`` chooses an occluder's visibility at its own vertices when they are receivers
    (``Scene.self_shadow``): "field" (default) extrapolates the shell's visibility inward like any
    other receiver's, about 10 % relative RMSE on the bunny's vertices under a constant sky;
    "rays" casts ``self_visibility_grid`` (θ × φ, Gauss–Legendre × uniform over the hemisphere about
    the vertex normal) rays from every vertex against the mesh
    (:func:`jshadow.visibility.vertex_visibility_sh`): 1.3 % there, at about a second of ray casting
    per pose of a 2k-vertex mesh on two CPU cores, so
    :class:`jshadow.Renderer` casts once for an occluder whose shape does not change and every frame
    for one that deforms. "rays" has no derivative with respect to the vertices (binary visibility):
    differentiating it raises (BENCHMARKS.md "Self-shadowing"). "light_rays" keeps the field's
    visibility and casts rays only toward the environment lights (``environment_lights`` > 0): the
    own vertices' shadows of the map's lamps are then exact, where "field" shades their lamps by the
    n-band path too (the studio bunny's 1901 vertices: 24.1 % "field", 4.4 % "light_rays", 4.2 %
    "rays" relative RMSE; BENCHMARKS.md "The default against the paper"), at the cost of V × K
    rays per pose (K directions, not the grid's); without environment lights it is "field".
    "maps" gives "rays"' two quantities (the transfer, and the lamps' visibility) from depth images
    of the mesh's entry faces plus exact rays against the faces within two rings of each vertex
    (:mod:`jshadow.visibility._own_maps`: the transfer over a ``self_maps_grid`` sphere grid, 8 × 16
    by default, looked up in ``self_maps_resolution``² pixels, 64; the lamps at ``lamp_images``
    pixels, 128 if 0), for a mesh that deforms: the animated bunny's vertices under the studio map
    1.26 % relative RMSE with "rays" (1.4 s per frame when every face was tested, 0.35 s cast by
    sector, BENCHMARKS.md "Deforming meshes' own vertices by rays"), 1.40 % with "maps" (0.12–0.15 s with the
    lamp images; 1.24 % with the scene's ambiguous lamp pairs settled, 0.88 % with the map split at
    2 × its mean, the sixth run of BENCHMARKS.md "The default against the paper"), the bunny's
    under a sky 0.34 against 1.77 % (8 × 16 at 64²; BENCHMARKS.md "Self-shadowing by depth
    images"); closed meshes, concrete poses (a traced pose is cast by
    rays).

    ``contact_visibility`` chooses the visibility at the fixed receivers (``Scene.receivers``, not
    an occluder's own vertices) next to a mesh occluder: within :data:`jshadow.scene.CONTACT_REACH`
    (0.3) of its bounding radius from one of its vertices or of a face larger than half that, where
    the field's extrapolation inward from the shell fails (a mesh resting just above its floor).
    "field" (default) keeps the field's visibility and the images' lookups there; "rays" casts that
    mesh's visibility SH from a 24 × 48 sphere grid's rays (12 × 24 where a split map's rest carries
    at most a quarter of its energy, :func:`jshadow.scene.contact_grid`; only the half above the
    receiver's plane where every mesh lies above it), and the sphere lights' and environment lights'
    visible fractions by exact rays against every occluder (:func:`jshadow.scene.contact_rows_at_time`):
    the untuned spot cow 0.05 above its floor under a sphere light and a sky 2.12 → 0.54 % relative
    RMSE (max 27.7 → 4.2 %), the bunny 0.05 above its floor under the studio map 0.70 → 0.41 % (max
    11.9 → 2.7 %), for 36–64 ms of rays there at a 32² plane (the bunny's 91 such receivers, the
    cow's 39), 0.4–0.9 ms per such receiver at 64² (the bunny's 366 in 143 ms on the coarser grid,
    the cow's 172 in 159 ms; BENCHMARKS.md "The default against the paper", eighth to tenth runs).
    :class:`jshadow.Renderer` makes them once for shapes that do not change, every frame for a
    deforming mesh. Binary visibility: differentiating them raises.

    ``light_visibility`` chooses how sphere lights are shadowed by mesh occluders: "sh" (default)
    through the field's n-band visibility, like the environment; "images" by the visible fraction
    of the light over ``light_cap`` = (rings, sectors) directions of its cap, each ray looked up in
    the BSV's occlusion images (:func:`jshadow.visibility.image_ray_visibility`; sphere occluders
    by an exact ray test), times the light's exact unoccluded irradiance. Sharp where n-band SH
    blur: 0.5–1.0 % relative RMSE on the mesh scenes with sphere lights against 2.5–9 % (BENCHMARKS.md
    "Sharp sphere-light shadows"), at the cost of the images (from the BSV's own edge-scan pass)
    and the lookups (run only for receivers whose cone toward the light may meet an occluder's
    bounding sphere: 2.6–3.0× the n-band path's frame on the deforming configs; a renderer of a
    scene whose meshes keep their shape makes them once and reads its frames out, 1.01–1.03× —
    BENCHMARKS.md "The default against the paper, every scene in one run"). A config takes it by
    default where it applies (``light_visibility = "auto"``, :func:`jshadow.config.build_scene`);
    this class's default stays "sh". It needs the
    edge-scan (shell > 1, closed meshes). Differentiable through the
    coverage images (:func:`jshadow.scene.occluder_images`): the lookups carry the silhouette term
    of the mesh's vertices and the read points' motion (lights, receivers), an estimate within
    0.6–19 % of exact ray-cast differences on the shipped deforming configs (BENCHMARKS.md
    "Gradients through the occlusion images"); a sphere occluder's exact ray test has no derivative
    (differentiating its centre or radius raises).

    ``light_images`` chooses the images those lookups read: "samples" (default) the edge-scan's
    0/1 pixel-centre samples, read at the nearest pixel, whose derivative is an estimate (the
    pixel taken as box-filtered coverage); "coverage" the same images made continuous along the
    scan lines (:func:`jshadow.visibility.scan_coverage`), read bilinearly: the lookups are then
    continuous in the vertices, lights and receivers, and their derivative is exact (JAX's, of
    the forward pass that runs), at the cost of the scan lines' boundary crossings each pose
    (BENCHMARKS.md "Coverage images").

    ``bsv_images`` chooses the images a mesh's BSV is projected from: "samples" (default) the
    edge-scan's 0/1 pixel-centre samples, with the silhouette derivative that ``bsv_gradient``
    selects (an estimate of the converged visibility's derivative); "coverage" the scan lines'
    coverage images (as ``light_images = "coverage"``, and shared with them), whose projection is
    continuous in the vertices, so that the BSV's derivative is JAX's own and exact for the forward
    pass that runs, and much cheaper than the silhouette terms (no per-node visibility): the frame
    gradient's backward / forward 0.4–1.2× on the deforming configs, against 3.4–18× (BENCHMARKS.md
    "BSV from coverage images"). The forward pass costs the scan lines' boundary crossings: a
    deforming frame about 3× the default's. Needs the edge-scan (shell > 1, closed meshes);
    ``bsv_gradient`` must stay "auto". Use it for gradient work: a loss through the samples is a
    staircase in the shape, which stalls fits (a bend fit stops at 0.63 for a target of 0.8, where
    the coverage's reaches 0.80000; BENCHMARKS.md "Fitting"). A config whose ``[fit]`` fits a mesh's
    deformation gets it by default (``bsv_images = "auto"`` in configs).

    ``environment_lights`` K > 0 (a power of two; needs ``light_visibility = "images"``) splits a
    lat-long environment at ``environment_threshold`` × its mean luminance: the rest keeps the
    n-band path, the excess becomes K distant lights by median cut, shadowed through the same
    images (:mod:`jshadow.envlights`, :func:`jshadow.scene.environment_visible_fraction`). For maps
    with small intense lamps (the studio map: 91 % of its energy in 2 % of the sphere), whose
    shadows no n-band path holds. Other environments are not split.

    ``lamp_images`` R > 0 (with environment lights) looks those K lights up in orthographic
    coverage images of each mesh occluder along their directions, R × R pixels over its bounding
    sphere (:mod:`jshadow.visibility._lamps`), instead of in the BSV shell's images: exact up to
    the pixel for receivers outside the occluder, without the parallax between shell points. They
    are a per-shape cost (K·F small rasterisations: the bunny's 128 at 128² take 94–109 ms, of a
    closed mesh's entry faces 74–81 ms), made once for a mesh that keeps its shape and every frame
    for one that deforms; an occluder's own vertices keep their rays or "maps" (which read the
    same images' depth), else the n-band fallback. 0 (default): the shell's.

    ``lamp_penumbrae`` "region" (with lamp images) widens each receiver's lookup of a lamp to the
    penumbra of the map region the lamp stands for (the region's angular extent times the distance
    to the blocker, averaged over taps in the image: :func:`jshadow.visibility.lamp_visibility`
    with ``spread``) instead of one bilinear lookup, whose edge is a pixel wide at any distance;
    about 10× the lookups' cost; without lamp images (``lamp_images`` 0 or no environment lights)
    it changes nothing. "none" (default): the bilinear lookup.
    """

    sh_bands: int = 4  # n: n² coefficients
    bsv_grid: tuple[int, int] = (12, 20)  # θ × φ sample points on the bounding sphere
    directions: tuple[int, int] = (32, 32)  # hemisphere directions per sample point
    dtype: str = "float32"
    shell: float = 1.5  # sampling-shell radius R / bounding radius r (1.0 = the paper)
    model: str = "sphere"  # extrapolation model (see jshadow.scaling); "paper" = the paper
    radial_samples: int = 16  # number of tabulated M_k (Zhou et al. 2005 use 16)
    d_range: tuple[float, float] = (0.2, 8.0)  # tabulated receiver distances, in shell radii
    bsv_method: str = "auto"  # "auto" | "brute" | "edgescan"
    bsv_center: str = "placed"  # "placed" | "box": a deforming mesh's bounding-sphere centre
    bsv_bands: int | None = None  # bands of the BSV and M_k (None: sh_bands + 1, at most 8)
    shading: str = "ratio"  # "ratio" | "product" (Zhou et al. 2005, the paper)
    bsv_gradient: str = "auto"  # "auto" | "raycast" | "image" | "scanline" (the BSV derivative's visibility)
    self_visibility: str = "field"  # "field" | "rays" | "light_rays" | "maps": at an occluder's own vertices
    self_visibility_grid: tuple[int, int] = (12, 48)  # θ × φ rays over each vertex's normal hemisphere
    light_visibility: str = "sh"  # "sh" | "images": how mesh occluders shadow sphere lights
    light_cap: tuple[int, int] = (4, 8)  # rings × sectors of light-cap directions for "images"
    light_images: str = "samples"  # "samples" | "coverage": the images "images" reads (see above)
    bsv_images: str = "samples"  # "samples" | "coverage": the images a mesh's BSV is projected from
    environment_lights: int = 0  # K distant lights split off a lat-long map's bright part (0: none)
    # the split's radiance threshold over the map's mean: 2 (was 4) puts 88 % of the studio map's
    # energy into its lamps (83 % at 4) and leaves a dimmer rest to the n-band SH: the studio bunny
    # 0.94 -> 0.60 % (max 8.6 -> 5.2 %), the animated bunny 0.94 -> 0.69 %, spot_sunset 0.95 ->
    # 0.79 %, the airplanes under the studio map 0.44 / 0.39 -> 0.44 / 0.43 %; not smooth in it (2.5:
    # the animated bunny 1.47 %, a median-cut region 64 degrees wide; BENCHMARKS.md "The default
    # against the paper, every scene in one run", fifth run)
    environment_threshold: float = 2.0
    lamp_images: int = 0  # R: orthographic R × R images per environment light (0: the shell's)
    self_maps_grid: tuple[int, int] = (8, 16)  # "maps": the transfer's θ × φ sphere grid
    self_maps_resolution: int = 64  # "maps": pixels per side of the transfer's depth images
    contact_visibility: str = "field"  # "field" | "rays": at fixed receivers next to a mesh (above)
    lamp_penumbrae: str = "none"  # "none" | "region": lamp lookups widened to their regions' penumbrae

    @classmethod
    def paper(cls, **options) -> Method:
        """The deformable-shadow-fields paper's method: shell 1, square-silhouette f_k, BSV in the
        lighting's bands, SH products (Zhou et al. 2005). ``options`` override any field."""
        sh_bands = options.get("sh_bands", cls.sh_bands)
        base = dict(shell=1.0, model="paper", bsv_bands=sh_bands, shading="product", bsv_center="box")
        return cls(**{**base, **options})

    @property
    def field_bands(self) -> int:
        """Bands in which visibility is sampled and extrapolated (see ``bsv_bands``)."""
        return min(self.sh_bands + 1, 8) if self.bsv_bands is None else self.bsv_bands

    def __post_init__(self):
        if not (1 <= self.sh_bands <= 8):
            raise ValueError(f"method.sh_bands must be in 1..8, got {self.sh_bands}")
        for name in ("bsv_grid", "directions"):
            v = getattr(self, name)
            if len(v) != 2 or min(v) < 2:
                raise ValueError(f"method.{name} must be two integers >= 2, got {v}")
        if self.dtype not in ("float32", "float64"):
            raise ValueError(f"method.dtype must be 'float32' or 'float64', got {self.dtype!r}")
        if not self.shell >= 1.0:
            raise ValueError(
                f"method.shell must be >= 1 (a multiple of the bounding radius), got {self.shell}"
            )
        if self.radial_samples < 2:
            raise ValueError(f"method.radial_samples must be >= 2, got {self.radial_samples}")
        if not (0 < self.d_range[0] < self.d_range[1]):
            raise ValueError(f"method.d_range must be two increasing positive distances, got {self.d_range}")
        if self.bsv_bands is not None and not (self.sh_bands <= self.bsv_bands <= 8):
            raise ValueError(
                f"method.bsv_bands must be in sh_bands..8 = {self.sh_bands}..8, got {self.bsv_bands}"
            )
        if self.shading not in SHADINGS:
            raise ValueError(f"method.shading must be one of {SHADINGS}, got {self.shading!r}")
        if self.bsv_method not in ("auto", "brute", "edgescan"):
            raise ValueError(f"method.bsv_method must be auto, brute or edgescan, got {self.bsv_method!r}")
        if self.bsv_center not in BSV_CENTERS:
            raise ValueError(f"method.bsv_center must be one of {BSV_CENTERS}, got {self.bsv_center!r}")
        if self.bsv_gradient not in BSV_GRADIENTS:
            raise ValueError(f"method.bsv_gradient must be one of {BSV_GRADIENTS}, got {self.bsv_gradient!r}")
        if self.self_visibility not in SELF_VISIBILITIES:
            raise ValueError(
                f"method.self_visibility must be one of {SELF_VISIBILITIES}, got {self.self_visibility!r}"
            )
        g = self.self_visibility_grid
        if len(g) != 2 or min(g) < 2:
            raise ValueError(f"method.self_visibility_grid must be two integers >= 2, got {g}")
        if self.light_visibility not in LIGHT_VISIBILITIES:
            raise ValueError(
                f"method.light_visibility must be one of {LIGHT_VISIBILITIES}, got {self.light_visibility!r}"
            )
        if self.light_images not in LIGHT_IMAGES:
            raise ValueError(f"method.light_images must be one of {LIGHT_IMAGES}, got {self.light_images!r}")
        if self.bsv_images not in BSV_IMAGES:
            raise ValueError(f"method.bsv_images must be one of {BSV_IMAGES}, got {self.bsv_images!r}")
        if self.bsv_images == "coverage" and not self.shell > 1.0:
            raise ValueError(
                "method.bsv_images = 'coverage' needs the edge-scan, which samples a shell outside the "
                f"bounding sphere: shell > 1, got {self.shell}"
            )
        if self.bsv_images == "coverage" and self.bsv_gradient != "auto":
            raise ValueError(
                "method.bsv_gradient does not apply with bsv_images = 'coverage' (the coverage BSV's "
                f"derivative is JAX's own): leave it 'auto', got {self.bsv_gradient!r}"
            )
        c = self.light_cap
        if len(c) != 2 or min(c) < 1:
            raise ValueError(f"method.light_cap must be two integers >= 1 (rings, sectors), got {c}")
        k = self.environment_lights
        if int(k) != k or k < 0 or (k & (k - 1)):
            raise ValueError(f"method.environment_lights must be 0 or a power of two, got {k}")
        if k and self.light_visibility != "images":
            raise ValueError(
                "method.environment_lights > 0 shadows the map's bright part through the occlusion "
                f"images: it needs light_visibility = 'images' (got {self.light_visibility!r})"
            )
        r = self.lamp_images
        if int(r) != r or r < 0 or 0 < r < 8:
            raise ValueError(f"method.lamp_images must be 0 or an integer >= 8, got {r}")
        g = self.self_maps_grid
        if len(g) != 2 or min(g) < 2:
            raise ValueError(f"method.self_maps_grid must be two integers >= 2, got {g}")
        r = self.self_maps_resolution
        if int(r) != r or r < 8:
            raise ValueError(f"method.self_maps_resolution must be an integer >= 8, got {r}")
        if self.lamp_penumbrae not in LAMP_PENUMBRAE:
            raise ValueError(
                f"method.lamp_penumbrae must be one of {LAMP_PENUMBRAE}, got {self.lamp_penumbrae!r}"
            )
        if self.contact_visibility not in CONTACT_VISIBILITIES:
            raise ValueError(
                f"method.contact_visibility must be one of {CONTACT_VISIBILITIES}, "
                f"got {self.contact_visibility!r}"
            )
        if not (math.isfinite(self.environment_threshold) and self.environment_threshold > 0):
            raise ValueError(f"method.environment_threshold must be > 0, got {self.environment_threshold}")
        if self.light_visibility == "images" and (self.shell <= 1.0 or self.bsv_method == "brute"):
            raise ValueError(
                "method.light_visibility = 'images' looks rays up in the edge-scan's images: it needs "
                f"shell > 1 and bsv_method 'auto' or 'edgescan' (got shell {self.shell}, {self.bsv_method!r})"
            )
        if self.bsv_gradient in ("image", "scanline") and (self.shell <= 1.0 or self.bsv_method == "brute"):
            raise ValueError(
                f"method.bsv_gradient = {self.bsv_gradient!r} reads visibility off the edge-scan's images: "
                "it needs "
                f"shell > 1 and bsv_method 'auto' or 'edgescan' (got shell {self.shell}, {self.bsv_method!r})"
            )


class SphereOccluder(eqx.Module):
    center: Float[Array, "3"]
    radius: Float[Array, ""]


class MeshOccluder(eqx.Module):
    """A (possibly deforming) triangle mesh.

    ``unit_vertices`` is the rest pose normalised so that its bounding sphere (AABB centre, radius to
    the farthest vertex) is the unit sphere at the origin. The world-space vertices at time t are
    ``center + radius · deform(unit_vertices, t)``; ``deform`` is ``None`` for a rigid mesh.

    Constructing one with concrete arrays remembers it per topology (:func:`remembered_rest_shape`):
    a later trace of the same faces with a traced rest pose measures its edge-scan sizes on it.
    """

    unit_vertices: Float[Array, "V 3"]
    faces: Int[Array, "F 3"]
    center: Float[Array, "3"]
    radius: Float[Array, ""]
    deform: Callable | None = None  # an eqx.Module (x: (V,3), t: scalar) -> (V,3), or None
    name: str = eqx.field(static=True, default="mesh")

    def __check_init__(self):
        _remember_rest_shape(self)

    @property
    def deforms(self) -> bool:
        return self.deform is not None

    def unit_pose(self, t: Float[Array, ""] | float = 0.0) -> Float[Array, "V 3"]:
        """The deformed unit-frame vertices (V, 3) at time t (the rest pose for a rigid mesh)."""
        return self.unit_vertices if self.deform is None else self.deform(self.unit_vertices, t)

    def vertices(self, t: Float[Array, ""] | float = 0.0) -> Float[Array, "V 3"]:
        return self.center + self.radius * self.unit_pose(t)


_REST_SHAPES: dict = {}  # _faces_key(faces) -> the last concrete MeshOccluder constructed with them


def shape_is_static(occ) -> bool:
    """True if the occluder's shape is the same at every animation time (its BSV can be reused);
    False for a deformation whose amounts are traced (they may differ)."""
    if not isinstance(occ, MeshOccluder) or occ.deform is None:
        return True
    raw = [getattr(occ.deform, name) for name in ("amount_start", "amount_end") if hasattr(occ.deform, name)]
    if any(isinstance(x, jax.core.Tracer) for x in raw):
        return False
    leaves = [np.asarray(x) for x in raw]
    if len(leaves) == 2 and not getattr(occ.deform, "periodic", False):
        return bool(np.array_equal(leaves[0], leaves[1]))
    return False


def _faces_key(faces) -> tuple:
    """A hashable key of a concrete face array (its shape and bytes)."""
    f = np.ascontiguousarray(np.asarray(faces), np.int64)
    return (f.shape, hash(f.tobytes()))


def _remember_rest_shape(occ: MeshOccluder) -> None:
    """Keep the last :class:`MeshOccluder` constructed with concrete arrays per topology.

    Sizes that the BSV's edge-scan and its derivative need are measured on concrete poses
    (``jshadow.scene``); a function whose rest pose is traced (fitting per-vertex offsets, a user's
    ``jax.grad`` with respect to ``unit_vertices``) cannot measure them and reads them from a
    concrete shape of the same topology. Remembering the occluder when it is built (``build_scene``
    or by hand) makes such a function fast on its first call too, without a render first (the
    airplane's frame gradient: 1.6 s with generous default sizes, 0.16 s with measured ones;
    ``benchmarks/bench_first_grad.py``).
    """
    if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(occ)):
        return  # built inside a trace: nothing to measure on
    if len(_REST_SHAPES) >= 16:  # topologies are few per process; bound the references anyway
        _REST_SHAPES.clear()
    _REST_SHAPES[_faces_key(occ.faces)] = occ


def remembered_rest_shape(faces) -> MeshOccluder | None:
    """The last concrete :class:`MeshOccluder` constructed with ``faces`` (concrete), or None."""
    return _REST_SHAPES.get(_faces_key(faces))


class SphereLight(eqx.Module):
    center: Float[Array, "3"]
    radius: Float[Array, ""]
    radiance: Float[Array, "3"]  # linear RGB, constant over the sphere


def latlong_to_dir(u: Float[Array, "..."], v: Float[Array, "..."]) -> Float[Array, "... 3"]:
    """World direction of lat-long image coordinates u, v in [0, 1].

    v = 0 is the zenith (+y) and v = 1 the nadir; u runs once around in azimuth:
    ``θ = π v``, ``φ = 2π u``, direction ``(sin θ cos φ, cos θ, −sin θ sin φ)`` (so u increases
    counter-clockwise seen from above, starting at +x). Pixel (row i, column j) of an H×W image
    covers v ∈ [i/H, (i+1)/H), u ∈ [j/W, (j+1)/W).
    """
    theta, phi = jnp.pi * v, 2.0 * jnp.pi * u
    st = jnp.sin(theta)
    return jnp.stack([st * jnp.cos(phi), jnp.cos(theta), -st * jnp.sin(phi)], axis=-1)


def dir_to_latlong(d: Float[Array, "... 3"]) -> tuple[Float[Array, "..."], Float[Array, "..."]]:
    """Inverse of :func:`latlong_to_dir`: (u, v) in [0, 1) × [0, 1] of unit directions."""
    v = safe_acos(d[..., 1]) / jnp.pi
    u = jnp.mod(safe_atan2(-d[..., 2], d[..., 0]) / (2.0 * jnp.pi), 1.0)
    return u, v


def sky_radiance(d: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """Analytic sky: the CIE overcast sky L(θ) = (1 + 2 cos θ)/3 above the horizon (zenith = 1,
    horizon = 1/3; θ from +y), and a black ground below. Unitless; scaled by the radiance colour.
    """
    cy = d[..., 1]
    return jnp.where(cy > 0, (1.0 + 2.0 * cy) / 3.0, 0.0)


class Environment(eqx.Module):
    """Distant lighting.

    ``kind`` is "constant" (radiance only), "hdr" (lat-long ``image`` of shape (H, W, 3), see
    :func:`latlong_to_dir`, times ``radiance``) or "sky" (:func:`sky_radiance` times ``radiance``).
    """

    radiance: Float[Array, "3"]
    image: Float[Array, "H W 3"] | None = None
    kind: str = eqx.field(static=True, default="constant")

    def radiance_at(self, d: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
        """Radiance arriving from unit world directions d (piecewise constant per pixel for "hdr")."""
        if self.kind == "constant":
            return jnp.broadcast_to(self.radiance, (*d.shape[:-1], 3))
        if self.kind == "sky":
            return sky_radiance(d)[..., None] * self.radiance
        if self.kind == "hdr":
            h, w = self.image.shape[:2]
            u, v = dir_to_latlong(d)
            i = jnp.clip(jnp.floor(v * h).astype(jnp.int32), 0, h - 1)
            j = jnp.clip(jnp.floor(u * w).astype(jnp.int32), 0, w - 1)
            return self.image[i, j] * self.radiance
        raise ValueError(f"unknown environment kind {self.kind!r}; expected constant, hdr or sky")


class Receivers(eqx.Module):
    """Receiver vertices of the plane (or any fixed set of points), with normals and albedo."""

    points: Float[Array, "N 3"]
    normals: Float[Array, "N 3"]
    albedo: Float[Array, "3"]
    grid_shape: tuple[int, int] | None = eqx.field(static=True, default=None)  # plane: (rows, cols)


class Scene(eqx.Module):
    method: Method = eqx.field(static=True)
    receivers: Receivers
    occluders: tuple = ()  # SphereOccluder | MeshOccluder
    lights: tuple = ()  # SphereLight
    environment: Environment | None = None
    self_shadow: bool = eqx.field(static=True, default=False)
    n_frames: int = eqx.field(static=True, default=1)

    @property
    def dtype(self):
        return jnp.dtype(self.method.dtype)


def frame_time(frame: int, n_frames: int) -> float:
    """Animation time t in [0, 1] of ``frame`` (0-based) out of ``n_frames``."""
    if not (0 <= frame < max(n_frames, 1)):
        raise ValueError(f"frame {frame} out of range for an animation of {n_frames} frames")
    return 0.0 if n_frames <= 1 else frame / (n_frames - 1)


def surface_offset(scene: Scene, t, points: Float[Array, "N 3"] | None = None) -> Float[Array, ""]:
    """The lift ε of a receiver that lies on a surface (an occluder's own vertex): its rays start ε
    along its normal and ignore hits closer than ε, ``ε = eps(dtype, 100) · extent`` with the
    extent the largest side of the box around the scene at time t — receivers, mesh vertices, the
    sphere occluders' balls and the lights' centres (about 1.2e-4 of it in float32).

    One convention for the reference renderer and the shadow field's own-vertex rays, so that
    they see the same surface: where a vertex normal disagrees with an adjacent face (creases,
    sliver faces) the grazing rays it blocks are counted alike. ``points``: the receivers at t
    (:func:`receivers_at_time`, computed here when None). A scalar of the scene's dtype; traceable.
    """
    dtype = scene.dtype
    if points is None:
        points, _ = receivers_at_time(scene, t)
    pts = [jnp.reshape(jnp.asarray(points, dtype), (-1, 3))]
    for occ in scene.occluders:
        if isinstance(occ, SphereOccluder):
            c, r = jnp.asarray(occ.center, dtype), jnp.asarray(occ.radius, dtype)
            pts += [(c - r)[None], (c + r)[None]]
        elif isinstance(occ, MeshOccluder):
            pts.append(jnp.asarray(occ.vertices(t), dtype))
    for light in scene.lights:
        pts.append(jnp.reshape(jnp.asarray(light.center, dtype), (1, 3)))
    allp = jnp.concatenate(pts, 0)
    extent = jnp.max(jnp.max(allp, 0) - jnp.min(allp, 0))
    return eps(dtype, 100.0) * jnp.maximum(extent, jnp.asarray(1e-30, dtype))


def receivers_at(scene: Scene, frame: int = 0) -> tuple[Float[Array, "N 3"], Float[Array, "N 3"]]:
    """All receiver points and unit normals of ``scene`` at ``frame`` (see :func:`receivers_at_time`)."""
    return receivers_at_time(scene, frame_time(frame, scene.n_frames))


def receivers_at_time(scene: Scene, t) -> tuple[Float[Array, "N 3"], Float[Array, "N 3"]]:
    """All receiver points and unit normals of ``scene`` at animation time t ∈ [0, 1].

    The plane's receivers come first (in the order of ``scene.receivers``); when
    ``scene.self_shadow`` is set, the deformed vertices of every mesh occluder follow, occluder by
    occluder, with area-weighted vertex normals. Renderer and reference both call this, so their
    outputs line up receiver by receiver.
    """
    points, normals = [scene.receivers.points], [scene.receivers.normals]
    if scene.self_shadow:
        from .geometry import vertex_normals  # imported lazily: geometry is optional for sphere scenes

        for occ in scene.occluders:
            if isinstance(occ, MeshOccluder):
                v = occ.vertices(t)
                points.append(v)
                normals.append(vertex_normals(v, occ.faces))
    return jnp.concatenate(points, axis=0), jnp.concatenate(normals, axis=0)
