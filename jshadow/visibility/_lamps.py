"""Orthographic coverage and depth images of a mesh along fixed directions: exact shadows of distant lamps.

A distant light (one of a lat-long map's lamps, :mod:`jshadow.envlights`) is seen along one
direction d from every receiver, so the rays toward it are parallel and one orthographic image of
the occluder along d holds all of them: the ray ``x + t·d`` (t > 0) from a receiver x off the mesh
meets it iff the line through x along d meets the mesh ahead of x, i.e. iff the front-most depth
toward the lamp in x's pixel lies ahead of x's depth (outside the bounding sphere that is "x's
projection in the silhouette and the sphere ahead"; within it, under a low mesh or between its
parts, the depth decides). Looked up in the pixels about x this is exact up to the pixel size,
with no extrapolation and none of the parallax between the BSV shell's grid points that limits
the shell images' lookups (:mod:`._images`): on the untuned twisted airplane under the studio map
the lamps' exact visibility (by rays) takes the plane from 2.84 to 0.47 % relative RMSE with 128
lamps, and these images at 128² to 0.53 % looked up at the nearest pixel, where the shell images
stay at 2.2–2.8 % for any number of lamps (BENCHMARKS.md, "Lamp images"); read bilinearly
(:func:`lamp_visibility`), 0.44 % (BENCHMARKS.md, "The default against the paper, every scene in
one run", fourth run).

The images are a per-shape quantity (they move with the occluder, not with the receivers or the
lights' energies), made once for a mesh that keeps its shape and every frame for one that deforms.

Coverage is the union of the projected triangles, tested at pixel centres: for each (direction,
triangle) the centres of a fixed ``stamp × stamp`` window from the corner of the triangle's
bounding box are tested against its three edges (inclusive, so a centre on a shared edge is never
missed), and the face's depth there is scattered into the image with a maximum, one window per
face (XLA's CPU scatter takes a window about 7× faster than its pixels one by one), the faces of
every window size into the same image in one pass over the directions. Each pixel thus
holds the front-most depth of the faces imaged; with ``entry_only`` only the faces the line toward
the lamp enters the mesh through (about half, each direction rasterising its own), which for a
closed mesh cover the same pixels and give the depth a point on its own surface is tested against
(:mod:`._own_maps`). Cost: K·F·stamp² tests (the bunny's 3798 faces at 128² pixels: windows of
4–32 pixels per side, a power of two, 14 % of the faces in windows of 16 or more, grouped by size,
each group's count padded to one of four sizes per octave so that a deforming mesh compiles few
shapes): its 128 images took 80 ms of all faces and 76 ms of the entry faces (101 ms of the entry
faces with windows of 4, 6, 8, 12, ... pixels in the same run; in another run 87 ms with those
sizes against 97 ms with each window a pixel wider than needed; the same images); the spot cow's
288 at 128², 130 ms of the entry faces (147 ms with sizes 4, 6, 8, 12, ... in the same run; 126
against 174 ms in another for the narrower windows), each size group then a pass over the
directions with an image of its own, their maximum taken after. In one pass (the same images,
BENCHMARKS.md "Lamp images in one pass"): the bunny's 256 at 128² 109 against 152 ms of the entry
faces, 122 against 170 ms of all; the spot cow's 288 at 160² 157 against 185 ms, 195 against
224 ms. Two faces that share an edge tested in one window (fewer scatters, twice the tests per
window) were faster on some meshes and slower on others, and are not used.

Limitations: receivers off the mesh (an occluder's own vertices need a margin and their own
nearby faces, :mod:`._own_maps`; :func:`jshadow.scene.environment_visible_fraction` routes them
elsewhere); binary images, so no derivative with respect to the geometry; the stamp is
sized from concrete vertices (traced vertices need ``stamp``).
"""

from __future__ import annotations

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._numerics import safe_sqrt
from ..geometry import bounding_sphere
from ._raycast import _onb

__all__ = ["LampImages", "lamp_images", "lamp_visibility", "image_coords", "stamp_groups"]


class LampImages(eqx.Module):
    """Orthographic images of one occluder along K directions (see the module docstring).

    Attributes:
        front: (K, R, R) float; pixel (i, j) of image k is centred at ``c + u_j·e1_k + u_i·e2_k``
            with ``u_j = −r + (j + ½)·2r/R``; its value is the largest depth ``(x − c)·d_k`` (world
            units, toward the lamp) at which the line through the pixel centre along ``d_k`` meets
            an imaged face, −∞ where it meets none. With ``entry_only`` the imaged faces are those
            the line enters the mesh through (``n_f·d_k < 0``): for a closed mesh they cover the
            same pixels, and the value is then the front-most entry, what a point on the surface
            needs (:func:`jshadow.visibility.vertex_lamp_visibility`).
        directions: (K, 3) unit directions d_k toward the lamps.
        e1, e2: (K, 3) unit vectors spanning each image plane (a frame with d_k).
        center: (3,) bounding-sphere centre c; radius: () its radius r (world units).
        entry_only: whether only entry faces were imaged (static).
    """

    front: Float[Array, "K R R"]
    directions: Float[Array, "K 3"]
    e1: Float[Array, "K 3"]
    e2: Float[Array, "K 3"]
    center: Float[Array, "3"]
    radius: Float[Array, ""]
    entry_only: bool = eqx.field(static=True, default=False)

    @property
    def covered(self) -> Bool[Array, "K R R"]:
        """(K, R, R) True where the line through the pixel centre meets the mesh."""
        return self.front > -jnp.inf


def _pixel_coords(vertices, directions, resolution):
    """Bounding sphere, unit directions, frames, and the (K, V) pixel coordinates of the vertices
    (pixel j's centre at coordinate j, all within [−½, R − ½])."""
    center, radius = bounding_sphere(vertices)
    d = directions / jnp.linalg.norm(directions, axis=-1, keepdims=True)
    e1, e2 = _onb(d)
    rel = vertices - center
    scale = resolution / (2.0 * radius)
    px = (rel @ e1.T).T * scale + (0.5 * resolution - 0.5)  # (K, V)
    py = (rel @ e2.T).T * scale + (0.5 * resolution - 0.5)
    return center, radius, d, e1, e2, px, py


# powers of two: a window of 6 or 12 pixels per side is slower per face than one of 8 or 16
# (BENCHMARKS.md "The default against the paper, every scene in one run", fifth run)
_BUCKETS = (4, 8, 16, 32, 64, 128, 256)


def _orientation(vertices, faces):
    """+1 for outward normals (positive enclosed volume), −1 for inward, over the whole mesh; a
    face ``f`` is entered by a line along d where ``n_f·d · orientation < 0``."""
    tri = vertices[faces]
    volume6 = jnp.sum(tri[:, 0] * jnp.cross(tri[:, 1], tri[:, 2]))
    return jnp.where(volume6 < 0, -1.0, 1.0).astype(vertices.dtype)


def stamp_groups(vertices: ArrayLike, faces: ArrayLike, resolution: int) -> list[tuple[np.ndarray, int]]:
    """Faces grouped by the window (pixels per side) that holds every pixel centre their
    projection can cover, whatever the direction: 1 + the longest edge in pixels, floored (no
    projection of a triangle is wider than its longest edge L, and a closed interval of width L
    holds at most ⌊L⌋ + 1 integers; 10⁻³ pixel is added against rounding), rounded up to one of a
    few sizes. Returns ``[(face indices, stamp), ...]``; concrete input only."""
    v = np.asarray(vertices)
    f = np.asarray(faces)
    _, r = bounding_sphere(jnp.asarray(v))
    tri = v[f].astype(np.float64)
    longest = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=-1).max(-1)
    need = np.floor(longest * resolution / (2.0 * float(r)) + 1e-3).astype(np.int64) + 1
    need = np.minimum(need, resolution + 1)
    sizes = np.asarray([b for b in _BUCKETS if b < resolution + 1] + [resolution + 1])
    which = np.searchsorted(sizes, need)
    return [(np.flatnonzero(which == i), int(sizes[i])) for i in np.unique(which)]


def _padded_count(n: int) -> int:
    """n rounded up to a multiple of a quarter of its octave (at most 25 % more, 4 sizes per octave)."""
    step = max(1, 1 << max(int(n).bit_length() - 3, 0))
    return -(-int(n) // step) * step


# one (stamp × stamp) window per face scattered as a block: XLA's CPU scatter costs about 0.4 ns
# per element that way against 3 ns one element at a time (2 cores, float32, 3.9 M elements)
_WINDOW = jax.lax.ScatterDimensionNumbers(
    update_window_dims=(1, 2), inserted_window_dims=(), scatter_dims_to_operand_dims=(0, 1)
)


@partial(jax.jit, static_argnames=("resolution", "stamps", "entry_only"))
def _rasterise(vertices, groups, directions, orientation, orders, *, resolution, stamps, entry_only):
    """Images of the faces of ``groups``, a tuple of (G, 3) face arrays, each face tested in a
    window of ``stamps[i]`` pixels from the corner of its bounding box (degenerate faces, covering
    nothing, pad them), every group scattered into the same image in one pass over the directions
    (against a pass and an image per group: the bunny's 256 entry-face images at 128² in 109
    instead of 152 ms, BENCHMARKS.md "Lamp images in one pass"); ``orders``: per group None or (K, cap), the
    faces each direction rasterises (its entry faces first)."""
    center, radius, d, e1, e2, px, py = _pixel_coords(vertices, directions, resolution)
    pz = ((vertices - center) @ d.T).T  # (K, V) depth toward each lamp
    size = resolution + max(stamps)  # windows start in [0, R] (pixel coordinates lie in [−½, R − ½])
    per_group = []
    for faces, order in zip(groups, orders, strict=True):
        if not entry_only:  # every face imaged: no entry bits to carry through the pass
            per_group.append((None, order))
            continue
        tri = vertices[faces]  # (G, 3, 3)
        normal = jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # (G, 3), unnormalised
        enters = (normal @ d.T).T * orientation < 0  # (K, G): a line toward the lamp enters there
        per_group.append((enters if order is None else jnp.take_along_axis(enters, order, axis=1), order))

    def one(args):
        x, y, z, rest = args  # (V,) pixel coordinates and depths along this direction
        img = jnp.full((size, size), -jnp.inf, x.dtype)
        for faces, stamp, (ent, order) in zip(groups, stamps, rest, strict=True):
            faces_k = faces if order is None else faces[order]  # (G, 3)
            img = _scatter_windows(img, x, y, z, faces_k, ent, stamp, resolution, entry_only)
        return img[:resolution, :resolution]

    front = jax.lax.map(one, (px, py, pz, tuple(per_group)))
    return LampImages(front, d, e1, e2, center, radius, entry_only)


def _scatter_windows(img, x, y, z, faces_k, ent, stamp, resolution, entry_only):
    """``img`` with the ``stamp``-pixel windows of the faces ``faces_k`` (G, 3) scattered in (a
    maximum of their depths at the pixel centres they cover); ``ent`` (G,) their entry bits."""
    offs = jnp.arange(stamp, dtype=jnp.int32)
    ax, ay, az = x[faces_k[:, 0]], y[faces_k[:, 0]], z[faces_k[:, 0]]
    bx, by, bz = x[faces_k[:, 1]], y[faces_k[:, 1]], z[faces_k[:, 1]]
    cx, cy, cz = x[faces_k[:, 2]], y[faces_k[:, 2]], z[faces_k[:, 2]]
    area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    sgn = jnp.sign(area)
    inv = jnp.where(area != 0, 1.0 / jnp.where(area != 0, area, 1.0), 0.0)
    j0 = jnp.clip(jnp.ceil(jnp.minimum(jnp.minimum(ax, bx), cx)).astype(jnp.int32), 0, resolution)
    i0 = jnp.clip(jnp.ceil(jnp.minimum(jnp.minimum(ay, by), cy)).astype(jnp.int32), 0, resolution)
    qx = (j0[:, None, None] + offs[None, None, :]).astype(x.dtype)  # (G, 1, S)
    qy = (i0[:, None, None] + offs[None, :, None]).astype(x.dtype)  # (G, S, 1)

    def edge(x0, y0, x1, y1):  # twice the signed area of (p0, p1, q)
        e = (x1 - x0)[:, None, None] * (qy - y0[:, None, None])
        return e - (y1 - y0)[:, None, None] * (qx - x0[:, None, None])

    wa, wb, wc = edge(bx, by, cx, cy), edge(cx, cy, ax, ay), edge(ax, ay, bx, by)
    sg = sgn[:, None, None]
    inside = (sg * wa >= 0) & (sg * wb >= 0) & (sg * wc >= 0)  # inclusive: shared edges never missed
    keep = sgn != 0  # an edge-on triangle covers nothing
    if entry_only:
        keep = keep & ent
    inside = inside & keep[:, None, None]
    depth = wa * az[:, None, None] + wb * bz[:, None, None] + wc * cz[:, None, None]
    depth = depth * inv[:, None, None]  # the face's plane at the pixel centre (barycentric)
    vals = jnp.where(inside, depth, -jnp.inf)
    return jax.lax.scatter_max(img, jnp.stack([i0, j0], -1), vals, _WINDOW, mode="promise_in_bounds")


def lamp_images(
    vertices: Float[ArrayLike, "V 3"],
    faces: Int[ArrayLike, "F 3"],
    directions: Float[ArrayLike, "K 3"],
    resolution: int = 128,
    stamp: int | None = None,
    entry_only: bool = False,
) -> LampImages:
    """Orthographic images of a mesh along K directions (see the module docstring).

    Args:
        vertices: (V, 3) world vertices; faces: (F, 3) indices (any mesh: the coverage of its
            projected triangles is what is imaged, closed or not).
        directions: (K, 3) directions toward the lamps (normalised here).
        resolution: R, pixels per side of each image, over the bounding sphere's diameter.
        stamp: pixels per side of every triangle's test window; None: windows per group of
            faces, :func:`stamp_groups` of the concrete vertices (traced ones need a stamp).
        entry_only: image only the faces a line toward the lamp enters through (``n_f·d < 0``
            for outward normals; the orientation is read from the sign of the enclosed volume):
            for a *closed*, consistently oriented mesh the same coverage, and the depth a point on
            the surface is tested against; for an open mesh coverage is then lost.

    Returns:
        :class:`LampImages`; no derivative with respect to the vertices (binary coverage).
    """
    resolution = int(resolution)
    if resolution < 2:
        raise ValueError(f"resolution must be >= 2, got {resolution}")
    directions = jnp.asarray(directions)
    if directions.ndim != 2 or directions.shape[-1] != 3:
        raise ValueError(f"directions must be (K, 3), got {directions.shape}")
    faces = np.asarray(faces)  # concrete: faces are grouped by size
    v = jax.lax.stop_gradient(jnp.asarray(vertices))
    d = directions.astype(v.dtype)
    if stamp is not None:
        groups = [(np.arange(faces.shape[0]), int(stamp))]
    elif isinstance(vertices, jax.core.Tracer):
        raise ValueError("lamp_images: traced vertices need an explicit stamp (see stamp_groups)")
    else:
        groups = stamp_groups(vertices, faces, resolution)
    orientation = _orientation(v, jnp.asarray(faces))
    entry_only = bool(entry_only)
    enters = None
    if entry_only and not isinstance(vertices, jax.core.Tracer):  # count each direction's entry faces
        vn, dn = np.asarray(vertices, np.float64), np.asarray(d, np.float64)
        t = vn[faces]
        normal = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        enters = (normal @ dn.T) * np.sign(np.sum(t[:, 0] * np.cross(t[:, 1], t[:, 2])) or 1.0) < 0  # (F, K)
    arrays, orders, stamps = [], [], []
    for idx, size in groups:
        # degenerate padding (covers nothing) to a few counts per octave: a deforming mesh's groups
        # change size from pose to pose, and each new shape would compile again
        f = np.zeros((_padded_count(idx.shape[0]), 3), faces.dtype)
        f[: idx.shape[0]] = faces[idx]
        # with entry faces only, each direction rasterises its own (about half), padded likewise
        order = None
        if enters is not None:
            held = enters[idx]  # (G, K)
            eighth = -(-f.shape[0] // 8)  # caps in eighths of the group: few shapes to compile
            cap = min(-(-int(held.sum(0).max()) // eighth) * eighth, f.shape[0])
            order = jnp.asarray(np.argsort(~held.T, axis=1, kind="stable")[:, :cap].astype(np.int32))
        arrays.append(jnp.asarray(f))
        orders.append(order)
        stamps.append(int(size))
    return _rasterise(
        v,
        tuple(arrays),
        d,
        orientation,
        tuple(orders),
        resolution=resolution,
        stamps=tuple(stamps),
        entry_only=entry_only,
    )


def image_coords(
    images: LampImages, points: Float[Array, "N 3"], lamps: slice = slice(None)
) -> tuple[Float[Array, "N k"], Float[Array, "N k"], Float[Array, "N k"], Float[Array, ""]]:
    """Where ``points`` fall in the images of lamps ``lamps``: their pixel coordinates (u, w)
    along e1 and e2, pixel (i, j)'s centre at (u, w) = (j, i); their depth ``(x − c)·d_k`` toward
    each lamp (world units, as :attr:`LampImages.front`); and the pixel's width (world units)."""
    dt = points.dtype
    res = images.front.shape[-1]
    rel = points - images.center.astype(dt)
    pixel = 2.0 * images.radius.astype(dt) / res
    u = (rel @ images.e1[lamps].T.astype(dt)) / pixel + (0.5 * res - 0.5)
    w = (rel @ images.e2[lamps].T.astype(dt)) / pixel + (0.5 * res - 0.5)
    return u, w, rel @ images.directions[lamps].T.astype(dt), pixel


def _front_at(images: LampImages, i, j, lamps: slice = slice(None)):
    """(N, k) depth ``front`` of pixel (i, j) (integer (N, k) indices) of each image of lamps
    ``lamps`` (a static slice), −∞ outside the image: what every lookup of the images compares."""
    front = images.front[lamps]
    k, res = front.shape[0], front.shape[-1]
    inside = (i >= 0) & (i < res) & (j >= 0) & (j < res)
    flat = (jnp.arange(k, dtype=jnp.int32) * (res * res))[None, :] + jnp.clip(i, 0, res - 1) * res
    return jnp.where(inside, front.reshape(-1)[flat + jnp.clip(j, 0, res - 1)], -jnp.inf)


AHEAD_EPS = 1e-4  # × the bounding radius: a face must lie this far ahead of a point to block it
PENUMBRA_SEARCH = 3  # nearest-pixel taps per side looking for blockers (lamp_visibility with spread)
PENUMBRA_TAPS = 4  # bilinear taps per side averaged over a lamp's penumbra
PENUMBRA_MAX_HALF_WIDTH = 0.5  # radians: a wider region's box is cut to this (small-angle offsets)


def lamp_visibility(
    images: LampImages,
    points: Float[Array, "N 3"],
    lamps: slice = slice(None),
    spread: Float[ArrayLike, "K 3 3"] | None = None,
) -> Float[Array, "N k"]:
    """Visibility in [0, 1] of lamps ``lamps`` (a static slice of the K) from each point: one minus
    the blocking of their images interpolated bilinearly between the four pixel centres around the
    point's projection (0 or 1 at a pixel centre; fractional within a pixel of the silhouette),
    a pixel blocking where the mesh meets its line ahead of the point (its depth ``front`` more
    than :data:`AHEAD_EPS` × the radius ahead). Exact up to the pixel size for points outside the
    mesh, inside its bounding sphere too (between the ears, beside the feet): the last face the
    line meets toward the lamp lies ahead of such a point iff the mesh lies between it and the
    lamp (for images of the entry faces, the last entry; the last exit otherwise), where a test
    of the coverage alone needs the point outside the sphere (see the module docstring; receivers
    within the sphere took the n-band path before, :func:`jshadow.scene.environment_visible_fraction`:
    the untuned bunny 0.05 above its floor 9.36 → 0.70 % relative RMSE, BENCHMARKS.md "The default
    against the paper, every scene in one run", seventh run). Bilinear rather than the nearest
    pixel: a lamp stands for a region of the map, whose shadow edge is soft, and the nearest pixel
    puts every edge on the pixel grid (the studio scenes' planes 0.53–0.76 → 0.44–0.66 % relative
    RMSE and their largest errors 5.6–12.1 → 4.6–8.6 %; BENCHMARKS.md "The default against the
    paper, every scene in one run", fourth run, "Bilinear lamp lookups"). No derivative.

    With ``spread`` (K, 3, 3), the regions' angular second moments
    (:attr:`jshadow.envlights.EnvironmentLights.spread`, all K), each lookup is widened to the
    penumbra of the map region its lamp stands for (``method.lamp_penumbrae = "region"``): a
    region of half-width ``a`` (radians: the box of the same variance along the image's axes, at
    most :data:`PENUMBRA_MAX_HALF_WIDTH`) behind a blocker ``t`` ahead of the point casts an edge
    ``2·a·t`` wide. ``t`` is the mean distance to the blockers met at :data:`PENUMBRA_SEARCH`²
    nearest pixels over the widest such box (blockers up to the bounding sphere's far side); the
    blocking is the mean of :data:`PENUMBRA_TAPS`² bilinear lookups spread over the box ``a·t``
    (as percentage-closer soft shadows do). Where no blocker is met it is the plain lookup.
    Why: a lamp is a point, and 64 of them on a compact key light are a staircase of hard edges.
    On the animated bunny's last pose under the studio map, at a plane receiver 1.6 units behind
    it, 64 point lamps by exact rays are 5.0 % of the mean irradiance off the map's own shadow
    (its pixels sampled 4 × 4 by exact rays, ``experiments/max_errors.py --parts pixels``), and the
    plain lookups 10.1 %; with the penumbrae the plane's largest error is 4.7 % of its mean
    against 7.1 % (BENCHMARKS.md "Lamp penumbrae"). Cost: 73 gathers a pair against 4, about 9×
    the plain lookups (70–77 against 7.7–7.8 ms for 160² × 64 pairs,
    ``benchmarks/bench_lamp_penumbra.py``). Limitations: one blocker depth per lookup
    (a planar blocker); a region's shape is its box; a blocker nearer than a pixel's worth of
    penumbra keeps the pixel-wide edge; the taps are a staircase of 4 steps where the penumbra
    spans many pixels."""
    u, w, z, pixel = image_coords(images, jax.lax.stop_gradient(points), lamps)
    dt = u.dtype
    thr = z + AHEAD_EPS * images.radius.astype(dt)

    def ahead(uu, ww):  # bilinear blocking at fractional pixel coordinates (N, k)
        j0, i0 = jnp.floor(uu), jnp.floor(ww)
        fx, fy = uu - j0, ww - i0
        j0, i0 = j0.astype(jnp.int32), i0.astype(jnp.int32)

        def at(i, j):  # whether pixel (i, j) of each lamp's image meets the mesh ahead, 0 outside it
            return (_front_at(images, i, j, lamps) > thr).astype(dt)

        top = (1.0 - fx) * at(i0, j0) + fx * at(i0, j0 + 1)
        bottom = (1.0 - fx) * at(i0 + 1, j0) + fx * at(i0 + 1, j0 + 1)
        return (1.0 - fy) * top + fy * bottom

    if spread is None:
        return 1.0 - ahead(u, w)
    s = jax.lax.stop_gradient(jnp.asarray(spread, dt))[lamps]  # (k, 3, 3)
    e1, e2 = images.e1[lamps].astype(dt), images.e2[lamps].astype(dt)

    def half_width(e):  # (k,) pixels of edge per world unit of blocker distance
        var = jnp.einsum("ki,kij,kj->k", e, s, e)
        return jnp.minimum(safe_sqrt(3.0 * var), PENUMBRA_MAX_HALF_WIDTH)[None, :] / pixel

    a1, a2 = half_width(e1), half_width(e2)
    reach = jnp.maximum(images.radius.astype(dt) - z, 0.0)  # the farthest blocker: the sphere's far side
    offsets = [(2 * i + 1) / PENUMBRA_SEARCH - 1.0 for i in range(PENUMBRA_SEARCH)]
    count = jnp.zeros_like(u)
    total = jnp.zeros_like(u)
    for ox in offsets:
        for oy in offsets:
            i = jnp.round(w + oy * a2 * reach).astype(jnp.int32)
            j = jnp.round(u + ox * a1 * reach).astype(jnp.int32)
            front = _front_at(images, i, j, lamps)
            hit = front > thr
            count = count + hit.astype(dt)
            total = total + jnp.where(hit, front - z, 0.0)
    t = total / jnp.maximum(count, 1.0)  # 0 where none: every tap the point's own bilinear lookup
    taps = [(2 * i + 1) / PENUMBRA_TAPS - 1.0 for i in range(PENUMBRA_TAPS)]
    blocked = jnp.zeros_like(u)
    for ox in taps:
        for oy in taps:
            blocked = blocked + ahead(u + ox * a1 * t, w + oy * a2 * t)
    return 1.0 - blocked / PENUMBRA_TAPS**2
