"""Self-shadowing: what limits the error on an occluder's own vertices, and what would remove it.

Receivers on an occluder's own surface lie inside its sampling shell, so the field expands the
shell's visibility inward (k = R/d > 1) — a model made for receivers outside the occluder. The
default's self-shadowing error was 24 % relative RMSE on the studio bunny's vertices
(BENCHMARKS.md, "Accuracy beyond the paper"). Candidates: the shell radius and the visibility bands
(if the inward expansion is the limit), the lighting bands (if the band limit of sharp lighting is),
or the model itself. This script renders three scenes of ``experiments/models.py`` with the bunny's
1901 vertices as receivers besides a 32² plane — ``bunny_studio`` (the shipped config, studio HDR
map), ``bunny_self_sky`` (the calibration bunny under a constant sky) and ``bunny_self_sky_twist``
(the same bunny twisted by 1.2 rad about its vertical axis) — with the default method at several
shell radii and band counts, and with the field's rows at the bunny's own vertices replaced by a
direct computation, the library's ``[method] self_visibility = "rays"``: each vertex's visibility of
the mesh by rays (:func:`jshadow.visibility.vertex_visibility_sh`: a Gauss–Legendre × uniform grid
of 6 × 24 to 16 × 64 directions over the hemisphere about the vertex normal, V = 0 below it; an
origin on the surface ignores its own faces) projected to the lighting's bands, then the same
combination, through :class:`jshadow.Renderer` (the cast's warm time is that of a second renderer,
the first one having compiled it). Once more with this script's own substitution, rays over the
whole sphere (24 × 48, as dense as the hemisphere's 12 × 48) by :func:`ray_fan_any_hit`. For the
twisted bunny also with that visibility cast on the *rest* pose, as it is and rotated by each
vertex's tangent-frame change: can a deforming mesh reuse one precomputation?
Errors are against the cached Monte Carlo references (``experiments/results/refs/<case>.npz``;
``models.py --cases <case>`` computes a missing one), for the vertices and the plane separately.

Usage (repository root, project environment active)::

    python experiments/self_shadow.py

Writes ``experiments/results/self_shadow.json`` and ``experiments/figures/self_shadow_vertices.png``
(the error of every vertex with the field, the rays, and the rays with 6 lighting bands).
"""

from __future__ import annotations

import json
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import models  # noqa: E402

from jshadow import Renderer, sh  # noqa: E402
from jshadow.entities import receivers_at_time  # noqa: E402
from jshadow.scene import combine, occluder_visibilities, scene_bsvs, scene_lighting  # noqa: E402
from jshadow.visibility import ray_fan_any_hit  # noqa: E402

# (label, [method] keys over the default variant)
SETTINGS = [
    ("default (shell 1.5, BSV 5 bands)", {}),
    ("shell 1.25", {"shell": 1.25}),
    ("shell 1.1", {"shell": 1.1}),
    ("BSV 7 bands", {"bsv_bands": 7}),
    ("shell 1.1, BSV 7 bands", {"shell": 1.1, "bsv_bands": 7}),
    ("6 lighting bands, BSV 7", {"sh_bands": 6, "bsv_bands": 7}),
]
RAY_GRID = (24, 48)  # whole-sphere rays of vertex_rays(): the density of the hemisphere's 12 x 48
RAY_GRIDS = [(6, 24), (8, 32), (12, 48), (16, 64)]  # self_visibility_grid (hemisphere); default 12 x 48


def _frames(v, normals, faces):
    """(V, 3, 3) orthonormal frames [tangent, bitangent, normal] as columns: the tangent is each
    vertex's first incident edge in face order, made orthogonal to the normal."""
    f = np.asarray(faces)
    first = np.full(v.shape[0], -1)
    for a, b in ((0, 1), (1, 2), (2, 0)):
        todo = first[f[:, a]] < 0
        first[f[todo, a]] = f[todo, b]
    e = v[jnp.asarray(first)] - v
    t = e - jnp.sum(e * normals, -1, keepdims=True) * normals
    t = t / jnp.linalg.norm(t, axis=-1, keepdims=True)
    return jnp.stack([t, jnp.cross(normals, t), normals], -1)


def vertex_rays(scene, n_plane: int, pose: str = "current"):
    """Irradiance with the first occluder's field replaced by ray-cast visibility at its vertices,
    and the warm seconds of the ray cast and projection (compiled once beforehand).

    ``pose``: "current" casts from the frame's own vertices against the frame's mesh; "rest" uses
    the visibility cast on the undeformed mesh as it is; "rest, rotated" rotates it by each vertex's
    frame change (rest → current tangent frame), as a deforming mesh could reuse a rest-pose
    precomputation."""
    from jshadow.geometry import vertex_normals

    t = jnp.float32(0.0)
    pts, nrm = receivers_at_time(scene, t)
    vis, dist = occluder_visibilities(scene, scene_bsvs(scene, t), pts)
    occ = scene.occluders[0]
    f = jnp.asarray(occ.faces)
    v = occ.vertices(t) if pose == "current" else occ.center + occ.radius * occ.unit_vertices
    dirs, w = sh.sphere_grid(*RAY_GRID, jnp.float32)
    n = scene.method.sh_bands

    @jax.jit
    def own(o):
        return sh.project((~ray_fan_any_hit(o, dirs, v, f)).astype(jnp.float32), dirs, w, n)

    own(v).block_until_ready()
    t0 = time.perf_counter()
    vv = own(v).block_until_ready()
    secs = time.perf_counter() - t0
    if pose == "rest, rotated":
        rest = _frames(v, vertex_normals(v, f), occ.faces)
        now = _frames(pts[n_plane:], nrm[n_plane:], occ.faces)
        vv = sh.rotate(vv, now @ jnp.swapaxes(rest, -1, -2))
    vis = [vis[0].at[n_plane:].set(vv), *vis[1:]]
    e = combine(scene, pts, nrm, vis, dist, scene_lighting(scene), True, n_plane)
    return np.asarray(e, np.float64), secs


def library_rays(scene, frame: int, sphere_path: str):
    """Irradiance with ``self_visibility = "rays"`` through the Renderer, and its timings in ms:
    ``ray_cast_ms``, the cast of a second renderer (the first one compiled it); ``warm_ms``, that
    renderer's first frame without the cast (BSV + shading: what the field rows' ``warm_ms``, a new
    renderer's frame, measures); ``reused_frame_ms``, its second frame, which reuses the BSV and the
    cast of the shape (it does not change)."""
    Renderer(scene, sphere_path).frame(frame)  # compiles the cast and the shading
    rend = Renderer(scene, sphere_path)
    res, first = rend.frame(frame)
    _, again = rend.frame(frame)
    assert rend.self_visibility_computations == 1
    timing = {
        "ray_cast_ms": first["self_visibility_ms"],
        "warm_ms": first["bsv_ms"] + first["shading_ms"],
        "reused_frame_ms": again["total_ms"],
    }
    return np.asarray(res.irradiance, np.float64), timing


def main() -> None:
    results = {"ray_grid": list(RAY_GRID), "ray_grids": [list(g) for g in RAY_GRIDS]}
    maps: dict = {}  # case -> (reference, plane receivers, scene, {setting: irradiance}) for plot()
    maps_now: dict = {}
    for case in ("bunny_studio", "bunny_self_sky", "bunny_self_sky_twist"):
        build, frame, sphere_path, _ = models._cases()[case]
        base = build(models.VARIANTS["paper"], 32)
        ref = models.reference(case, base, frame, 1e-3, 32768)
        n_plane = int(np.prod(base.receivers.grid_shape))
        rows = []
        default = dict(models.VARIANTS[models.DEFAULT_VARIANT])
        runs = [(label, dict(default, **keys), None) for label, keys in SETTINGS]
        for grid in RAY_GRIDS:
            keys = dict(self_visibility="rays", self_visibility_grid=grid)
            runs.append((f"self_visibility rays {grid[0]}x{grid[1]}", dict(default, **keys), "library"))
        for grid in ((6, 24), (12, 48)):
            keys = dict(self_visibility="rays", self_visibility_grid=grid, sh_bands=6, bsv_bands=7)
            label = f"self_visibility rays {grid[0]}x{grid[1]}, 6 lighting bands, BSV 7"
            runs.append((label, dict(default, **keys), "library"))
        runs.append(("default, whole-sphere rays 24x48 (vertex_rays)", default, "current"))
        if base.occluders[0].deform is not None:
            runs.append(("default, rays at the rest pose", default, "rest"))
            runs.append(("default, rays at the rest pose, rotated", default, "rest, rotated"))
        for label, method, kind in runs:
            scene = build(method, 32)
            if kind == "library":
                approx, timing = library_rays(scene, frame, sphere_path)
            elif kind is not None:
                approx, secs = vertex_rays(scene, n_plane, kind)
                timing = {"ray_cast_ms": 1e3 * secs}
            else:
                approx, _, warm = models.timed(scene, frame, sphere_path, runs=3)
                timing = {"warm_ms": warm}
            e = models.errors(approx, ref, n_plane)
            if label in MAPPED:
                maps_now[label] = approx
            keep = (
                "vertices_rel_rmse_pct",
                "vertices_max_rel_err_pct",
                "plane_rel_rmse_pct",
                "rel_rmse_pct",
                "max_rel_err_pct",
                "max_excess_over_unoccluded_pct",
            )
            rows.append(dict(setting=label, method=method, **{k: e[k] for k in keep}, **timing))
            print(
                f"{case:15s} {label:34s} vertices {e['vertices_rel_rmse_pct']:6.2f} %"
                f" (max {e['vertices_max_rel_err_pct']:6.1f} %)"
                f"  plane {e['plane_rel_rmse_pct']:6.2f} %  all {e['rel_rmse_pct']:6.2f} %"
                f" (max {e['max_rel_err_pct']:6.1f} %)  {timing}",
                flush=True,
            )
        results[case] = {"reference_spp": int(ref["spp"]), "vertices": int(ref["mean"].shape[0]) - n_plane}
        results[case]["rows"] = rows
        maps[case] = (ref, n_plane, build(default, 32), dict(maps_now))
        maps_now.clear()
    out = models.RESULTS / "self_shadow.json"
    out.write_text(json.dumps(results, indent=1))
    print(f"wrote {out}")
    print(f"wrote {plot(maps)}")


MAPPED = {  # settings drawn as vertex error maps, and their panel titles
    "default (shell 1.5, BSV 5 bands)": "field (default)",
    "self_visibility rays 12x48": 'self_visibility = "rays"',
    "self_visibility rays 12x48, 6 lighting bands, BSV 7": '"rays", 6 lighting bands',
}


def plot(maps: dict) -> pathlib.Path:
    """Signed error of every vertex's irradiance, averaged over the colour channels, in % of the
    vertices' mean reference (the titles' RMSE is ``vertices_rel_rmse_pct``), the bunny seen from
    the front (+z) and from the side (+x), per scene and mapped setting."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = [(label, view) for label in MAPPED for view in ("front", "side")]
    fig, axes = plt.subplots(
        len(maps),
        len(cols),
        figsize=(2.0 * len(cols) + 1, 2.4 * len(maps)),
        squeeze=False,
        layout="constrained",
    )
    for r, (case, (ref, n_plane, scene, approx)) in enumerate(maps.items()):
        v = np.asarray(scene.occluders[0].vertices(0.0))
        mean = ref["mean"][n_plane:]  # (V, 3): the errors as in models.errors, over the channels
        for c, (label, view) in enumerate(cols):
            ax = axes[r, c]
            err_rgb = 100 * (approx[label][n_plane:] - mean) / mean.mean()
            err = err_rgb.mean(axis=1)  # drawn: the vertex's error averaged over the channels
            x = v[:, 0] if view == "front" else -v[:, 2]
            depth = v[:, 2] if view == "front" else v[:, 0]
            order = np.argsort(depth)  # far vertices first, so the near side is drawn on top
            im = ax.scatter(x[order], v[order, 1], c=err[order], s=3, cmap="RdBu_r", vmin=-20, vmax=20)
            rmse = float(np.sqrt(np.mean(err_rgb**2)))  # = vertices_rel_rmse_pct
            ax.set_title(f"{MAPPED[label]}, {view}\nRMSE {rmse:.2f} %", fontsize=7)
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            if c == 0:
                ax.set_ylabel(case, fontsize=8)
    fig.colorbar(im, ax=axes, shrink=0.8, fraction=0.02, label="vertex irradiance error, % of the mean")
    models.FIGURES.mkdir(parents=True, exist_ok=True)
    out = models.FIGURES / "self_shadow_vertices.png"
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


if __name__ == "__main__":
    main()
