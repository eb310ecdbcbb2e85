"""Self-shadowing: what limits the error on an occluder's own vertices, and what would remove it.

Receivers on an occluder's own surface lie inside its sampling shell, so the field expands the
shell's visibility inward (k = R/d > 1) — a model made for receivers outside the occluder. The
default's self-shadowing error was 24 % relative RMSE on the studio bunny's vertices
(BENCHMARKS.md, "Accuracy beyond the paper"). Candidates: the shell radius and the visibility bands
(if the inward expansion is the limit), the lighting bands (if the band limit of sharp lighting is),
or the model itself. This script renders two scenes of ``experiments/models.py`` with the bunny's
1901 vertices as receivers besides a 32² plane — ``bunny_studio`` (the shipped config, studio HDR
map) and ``bunny_self_sky`` (the calibration bunny under a constant sky) — with the default method
at several shell radii and band counts, and once more with the field's rows at the bunny's own
vertices replaced by a direct computation: each vertex's visibility of the mesh by rays
(:func:`jshadow.visibility.ray_fan_any_hit` on a 24 × 48 Gauss–Legendre × uniform sphere grid; an
origin on the surface ignores its own faces) projected to the lighting's bands, then the same
combination. Errors are against the cached Monte Carlo references
(``experiments/results/refs/<case>.npz``; ``models.py --cases <case>`` computes a missing one), for
the vertices and the plane separately.

Usage (repository root, project environment active)::

    python experiments/self_shadow.py

Writes ``experiments/results/self_shadow.json``.
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

from jshadow import sh  # noqa: E402
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
RAY_GRID = (24, 48)


def vertex_rays(scene, n_plane: int):
    """Irradiance with the first occluder's field replaced by ray-cast visibility at its vertices,
    and the warm seconds of the ray cast and projection (compiled once beforehand)."""
    t = jnp.float32(0.0)
    pts, nrm = receivers_at_time(scene, t)
    vis, dist = occluder_visibilities(scene, scene_bsvs(scene, t), pts)
    occ = scene.occluders[0]
    v, f = occ.vertices(t), jnp.asarray(occ.faces)
    dirs, w = sh.sphere_grid(*RAY_GRID, jnp.float32)
    n = scene.method.sh_bands

    @jax.jit
    def own(o):
        return sh.project((~ray_fan_any_hit(o, dirs, v, f)).astype(jnp.float32), dirs, w, n)

    own(pts[n_plane:]).block_until_ready()
    t0 = time.perf_counter()
    vv = own(pts[n_plane:]).block_until_ready()
    secs = time.perf_counter() - t0
    vis = [vis[0].at[n_plane:].set(vv), *vis[1:]]
    e = combine(scene, pts, nrm, vis, dist, scene_lighting(scene), True, n_plane)
    return np.asarray(e, np.float64), secs


def main() -> None:
    results = {"ray_grid": list(RAY_GRID)}
    for case in ("bunny_studio", "bunny_self_sky"):
        build, frame, sphere_path, _ = models._cases()[case]
        base = build(models.VARIANTS["paper"], 32)
        ref = models.reference(case, base, frame, 1e-3, 32768)
        n_plane = int(np.prod(base.receivers.grid_shape))
        rows = []
        default = dict(models.VARIANTS[models.DEFAULT_VARIANT])
        runs = [(label, dict(default, **keys), None) for label, keys in SETTINGS]
        runs.append(("default, rays at the own vertices", default, "rays"))
        for label, method, kind in runs:
            scene = build(method, 32)
            if kind == "rays":
                approx, secs = vertex_rays(scene, n_plane)
                timing = {"ray_cast_ms": 1e3 * secs}
            else:
                approx, _, warm = models.timed(scene, frame, sphere_path, runs=3)
                timing = {"warm_ms": warm}
            e = models.errors(approx, ref, n_plane)
            keep = ("vertices_rel_rmse_pct", "vertices_max_rel_err_pct", "plane_rel_rmse_pct")
            rows.append(dict(setting=label, method=method, **{k: e[k] for k in keep}, **timing))
            print(
                f"{case:15s} {label:34s} vertices {e['vertices_rel_rmse_pct']:6.2f} %"
                f" (max {e['vertices_max_rel_err_pct']:6.1f} %)"
                f"  plane {e['plane_rel_rmse_pct']:6.2f} %  {timing}",
                flush=True,
            )
        results[case] = {"reference_spp": int(ref["spp"]), "vertices": int(ref["mean"].shape[0]) - n_plane}
        results[case]["rows"] = rows
    out = models.RESULTS / "self_shadow.json"
    out.write_text(json.dumps(results, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
