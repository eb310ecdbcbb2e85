"""Pictures a person wants to look at: the shaded receiver plane in perspective with the occluders.

The plane is drawn by casting one camera ray per pixel onto it and looking up the per-receiver
radiance bilinearly; occluder and light meshes are drawn on top back to front (painter's
algorithm), mesh occluders with their own self-shadowed vertex radiance when the scene computed it
and with a plain headlight shading otherwise. Colours are tone-mapped with a fixed exposure (pass
the same ``exposure`` for every frame of an animation so frames are comparable) and encoded as sRGB.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence

import numpy as np

__all__ = ["Camera", "default_camera", "tonemap", "draw_frame", "draw_scene", "exposure_for"]


class Camera:
    """Pinhole camera: position, look-at target, vertical field of view (degrees), image size."""

    def __init__(self, eye, target, fov_deg=40.0, width=640, height=480):
        self.eye = np.asarray(eye, float)
        self.target = np.asarray(target, float)
        self.width, self.height = int(width), int(height)
        f = self.target - self.eye
        self.forward = f / np.linalg.norm(f)
        right = np.cross(self.forward, [0.0, 1.0, 0.0])
        self.right = right / np.linalg.norm(right)
        self.up = np.cross(self.right, self.forward)
        self.focal = 0.5 * self.height / math.tan(math.radians(fov_deg) / 2)

    def project(self, p):
        """World points (..., 3) → pixel coordinates (..., 2) and depth (...)."""
        q = np.asarray(p, float) - self.eye
        z = q @ self.forward
        zs = np.where(z > 1e-9, z, 1e-9)
        x = self.width / 2 + self.focal * (q @ self.right) / zs
        y = self.height / 2 - self.focal * (q @ self.up) / zs
        return np.stack([x, y], -1), z

    def rays(self):
        """Unit ray directions (H, W, 3) through pixel centres."""
        j, i = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        d = (
            self.forward[None, None] * self.focal
            + self.right[None, None] * (j - self.width / 2)[..., None]
            - self.up[None, None] * (i - self.height / 2)[..., None]
        )
        return d / np.linalg.norm(d, axis=-1, keepdims=True)


def default_camera(plane_center, plane_size, width=640, height=480) -> Camera:
    """A camera above and in front of the plane (+z side), looking at a point a little above it."""
    c = np.asarray(plane_center, float)
    s = float(max(plane_size))
    eye = c + np.array([0.4 * s, 1.0 * s, 1.55 * s])
    return Camera(eye, c + np.array([0.0, 0.22 * s, 0.0]), 40.0, width, height)


def exposure_for(radiance: np.ndarray) -> float:
    """Exposure that maps the 95th percentile of luminance to 0.7 (before tone mapping)."""
    lum = np.asarray(radiance) @ np.array([0.2126, 0.7152, 0.0722])
    p = float(np.percentile(lum, 95)) if lum.size else 1.0
    return 0.7 / p if p > 0 and np.isfinite(p) else 1.0


def tonemap(rgb: np.ndarray, exposure: float) -> np.ndarray:
    """Linear RGB → 8-bit sRGB with exposure and a gentle Reinhard shoulder."""
    x = np.clip(np.asarray(rgb, float) * exposure, 0.0, None)
    x = x / (1.0 + 0.25 * x)
    x = np.clip(x * 1.25, 0.0, 1.0)  # 1.25: the shoulder's value at x = 4 is 1
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return (np.clip(srgb, 0, 1) * 255 + 0.5).astype(np.uint8)


def _icosphere(level=2):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=level)
    return np.asarray(m.vertices), np.asarray(m.faces)


def draw_frame(
    path,  # a file name or a binary file object
    camera: Camera,
    plane: dict | None,
    meshes: Sequence[dict] = (),
    exposure: float = 1.0,
    title: str | None = None,
) -> None:
    """Write a PNG of one frame.

    Args:
        plane: ``{"center": (3,), "size": (w, d), "grid_shape": (rows, cols), "radiance": (rows·cols, 3)}``
            (rows along z, columns along x, row-major, as the config builds them) or None.
        meshes: dicts with ``vertices`` (V, 3), ``faces`` (F, 3) and either ``vertex_radiance``
            (V, 3) (drawn with the same exposure as the plane), ``color`` (3,) in [0, 1] for a plain
            shaded surface, or ``emit`` (3,) for a light drawn in a flat bright colour.
    """
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import PolyCollection
    from matplotlib.figure import Figure

    h, w = camera.height, camera.width
    img = np.zeros((h, w, 3), np.uint8)
    # background: a dark vertical gradient
    img[...] = (np.linspace(70, 25, h)[:, None, None] * np.ones((1, w, 3))).astype(np.uint8)
    if plane is not None:
        d = camera.rays()
        c = np.asarray(plane["center"], float)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (c[1] - camera.eye[1]) / d[..., 1]
        hit = np.isfinite(t) & (t > 0)
        p = camera.eye + np.where(hit, t, 0.0)[..., None] * d
        rows, cols = plane["grid_shape"]
        sx, sz = plane["size"]
        fx = (p[..., 0] - (c[0] - sx / 2)) / sx * (cols - 1)
        fz = (p[..., 2] - (c[2] - sz / 2)) / sz * (rows - 1)
        inside = hit & (fx >= 0) & (fx <= cols - 1) & (fz >= 0) & (fz <= rows - 1)
        rad = np.asarray(plane["radiance"], float).reshape(rows, cols, 3)
        x0 = np.clip(np.floor(fx).astype(int), 0, max(cols - 2, 0))
        z0 = np.clip(np.floor(fz).astype(int), 0, max(rows - 2, 0))
        ax_, az_ = np.clip(fx - x0, 0, 1)[..., None], np.clip(fz - z0, 0, 1)[..., None]
        x1, z1 = np.minimum(x0 + 1, cols - 1), np.minimum(z0 + 1, rows - 1)
        col = (1 - az_) * ((1 - ax_) * rad[z0, x0] + ax_ * rad[z0, x1]) + az_ * (
            (1 - ax_) * rad[z1, x0] + ax_ * rad[z1, x1]
        )
        img[inside] = tonemap(col[inside], exposure)

    fig = Figure(figsize=(w / 100, h / 100), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0, 0, 1, 1))
    ax.imshow(img, extent=(0, w, h, 0), interpolation="nearest")
    polys, colors, depths = [], [], []
    for m in meshes:
        v, f = np.asarray(m["vertices"], float), np.asarray(m["faces"])
        xy, z = camera.project(v)
        tri = v[f]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-30)
        centroid = tri.mean(1)
        view = camera.eye - centroid
        view /= np.linalg.norm(view, axis=-1, keepdims=True)
        front = np.sum(n * view, -1) > 0
        if "vertex_radiance" in m:
            rgb = tonemap(np.asarray(m["vertex_radiance"], float)[f].mean(1), exposure) / 255.0
        elif "emit" in m:
            rgb = np.broadcast_to(np.asarray(m["emit"], float), (len(f), 3))
        else:
            key = np.array([0.3, 0.8, 0.5]) / np.linalg.norm([0.3, 0.8, 0.5])
            shade = 0.25 + 0.75 * np.clip(n @ key, 0, 1)
            rgb = np.clip(np.asarray(m.get("color", (0.75, 0.7, 0.65)))[None] * shade[:, None], 0, 1)
        keep = front & np.all(z[f] > 1e-6, axis=1)
        polys.extend(xy[f][keep])
        colors.extend(np.asarray(rgb)[keep])
        depths.extend(z[f].mean(1)[keep])
    if polys:
        order = np.argsort(-np.asarray(depths))
        pc = PolyCollection(
            [polys[i] for i in order],
            facecolors=[colors[i] for i in order],
            edgecolors="none",
            antialiased=False,
        )
        ax.add_collection(pc)
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.axis("off")
    if title:
        ax.text(8, 18, title, color="white", fontsize=10, family="monospace")
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    if hasattr(path, "write"):
        path.write(buf.getvalue())
    else:
        with open(path, "wb") as fh:
            fh.write(buf.getvalue())


def draw_scene(path, scene, result, t: float = 0.0, exposure: float = 1.0, title: str | None = None) -> None:
    """Write a PNG of one rendered frame of ``scene`` (what ``jshadow render`` writes per frame).

    Args:
        path: a file name or a binary file object.
        scene: the :class:`jshadow.entities.Scene` that was rendered.
        result: its ``RenderResult`` (``radiance`` (N, 3): the plane's receivers first, then, with
            self-shadowing, each mesh occluder's own vertices in order).
        t: the animation time in [0, 1] at which the meshes are drawn (the frame's time).
        exposure, title: as for :func:`draw_frame`.

    The plane is drawn when the receivers form a grid (``grid_shape``), with a camera framing it;
    mesh occluders with their self-shadowed vertex radiance when the scene computed it, sphere
    occluders as shaded icospheres, sphere lights in their colour.
    """
    from .entities import MeshOccluder, SphereOccluder

    rec = scene.receivers
    n_plane = rec.points.shape[0]
    radiance = np.asarray(result.radiance)
    plane = None
    if rec.grid_shape is not None:
        pts = np.asarray(rec.points)
        lo, hi = pts.min(0), pts.max(0)
        plane = {
            "center": (lo + hi) / 2,
            "size": (hi[0] - lo[0], hi[2] - lo[2]),
            "grid_shape": rec.grid_shape,
            "radiance": radiance[:n_plane],
        }
        camera = default_camera(plane["center"], plane["size"])
    else:
        camera = default_camera(np.zeros(3), (4.0, 4.0))
    meshes, offset = [], n_plane
    for occ in scene.occluders:
        if isinstance(occ, MeshOccluder):
            v = np.asarray(occ.vertices(t))
            m = {"vertices": v, "faces": np.asarray(occ.faces)}
            if scene.self_shadow:
                m["vertex_radiance"] = radiance[offset : offset + len(v)]
                offset += len(v)
            meshes.append(m)
        elif isinstance(occ, SphereOccluder):
            v, f = sphere_mesh(np.asarray(occ.center), float(occ.radius), 3)
            meshes.append({"vertices": v, "faces": f})
    for light in scene.lights:
        v, f = sphere_mesh(np.asarray(light.center), float(light.radius), 2)
        c = np.asarray(light.radiance, float)
        meshes.append({"vertices": v, "faces": f, "emit": np.clip(c / max(c.max(), 1e-12), 0, 1)})
    draw_frame(path, camera, plane, meshes, exposure=exposure, title=title)


def sphere_mesh(center, radius, level=2):
    """Vertices/faces of a sphere for drawing."""
    v, f = _icosphere(level)
    return np.asarray(center, float) + float(radius) * v, f
