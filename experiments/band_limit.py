"""How much of each scene's error any extrapolation model could remove: the band limit, measured.

The shadow field approximates, at every receiver, the occluders' n-band visibility SH; everything
after that (products with the lighting and the transfer, the ratio shading) is fixed by the
lighting's n bands. So no extrapolation model, however good, can do better than the same
combination fed with the *exact* n-band visibility of every occluder at every receiver — the
"oracle" here. Its error against the Monte Carlo reference is the floor of the method at n bands;
the default's error above that floor is what the extrapolation (shell, rescaling model, BSV
bands, grid interpolation) costs.

For every case of ``experiments/models.py`` (the calibration scenes, every shipped config, the
untuned scenes), at n = 4 (the shipped setting), 6 and 8 lighting bands (BSV n + 1 bands, as the
default; 7 / 8 for n = 6 / 8 as in ``models.py``'s ``default n6`` / ``default n8``), this script
renders

* ``default``: the library's default method (``Renderer``'s computation: BSV, field, combination);
* ``oracle``: the same combination (:func:`jshadow.scene.combine`, same lighting, same shading,
  same exact handling of sphere occluders and sphere lights) with each mesh occluder's visibility
  replaced by its exact visibility at the receiver, projected to n bands: rays over the whole
  sphere from plane receivers (``_common.exact_visibility_sh``, ``--dirs``² Gauss–Legendre ×
  uniform directions per hemisphere) and over the normal hemisphere from the occluder's own
  vertices (:func:`jshadow.visibility.vertex_visibility_sh`, ``--own-grid``). Sphere occluders keep
  their analytic rows, which are exact already.

Errors are against the cached references of ``models.py`` (``experiments/results/refs/<case>.npz``;
run ``models.py --cases <case>`` to compute a missing one) with its ``errors()``: relative RMSE and
max error of irradiance over the mean reference irradiance.

Usage (repository root, project environment active)::

    python experiments/band_limit.py [--cases ...] [--bands 4 6 8] [--dirs 48] [--own-grid 24 96]

Writes ``experiments/results/band_limit.json`` and ``experiments/figures/band_limit.png``.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import models  # noqa: E402
from _common import exact_visibility_sh, git_state  # noqa: E402

from jshadow.entities import MeshOccluder, frame_time, receivers_at_time  # noqa: E402
from jshadow.field import sphere_visibility_sh  # noqa: E402
from jshadow.scene import (  # noqa: E402
    combine,
    occluder_visibilities,
    scene_bsvs,
    scene_lighting,
    shared_normal_count,
)
from jshadow.visibility import vertex_visibility_sh  # noqa: E402

# lighting bands -> the models.py variant of the default method at those bands
BAND_VARIANTS = {4: models.DEFAULT_VARIANT, 6: "default n6", 8: "default n8"}
# 8-band SH products of several occluders compile for more than 20 minutes (BENCHMARKS.md)
SKIP = {("three_occluders", 8)}


def oracle_rows(scene, t, points, n_plane: int, n: int, dirs: int, own_grid: tuple[int, int]) -> list:
    """Exact n-band visibility (N, n²) of every occluder at every receiver (see module docstring)."""
    rows = []
    own_start = n_plane
    for occ in scene.occluders:
        if not isinstance(occ, MeshOccluder):
            rows.append(sphere_visibility_sh(occ.center, occ.radius, points, n))
            continue
        v = occ.vertices(jnp.asarray(t, occ.unit_vertices.dtype))
        f = jnp.asarray(occ.faces)
        if not scene.self_shadow:
            rows.append(exact_visibility_sh(points, v, f, n=n, directions=(dirs, dirs)))
            continue
        # this occluder's own vertices: hemisphere rays with its own faces edge-on; the rest: whole sphere
        end = own_start + v.shape[0]
        rest = jnp.concatenate([points[:own_start], points[end:]])
        r = exact_visibility_sh(rest, v, f, n=n, directions=(dirs, dirs))
        own = vertex_visibility_sh(v, f, n, own_grid)
        rows.append(jnp.concatenate([r[:own_start], own, r[own_start:]]))
        own_start = end
    return rows


def run_case(name: str, n: int, dirs: int, own_grid) -> dict:
    build, frame, sphere_path, tuned = models._cases()[name]
    base = build(models.VARIANTS["paper"], 32)
    ref = models.reference(name, base, frame, 1e-3, 32768)
    n_plane = int(np.prod(base.receivers.grid_shape))
    scene = build(models.VARIANTS[BAND_VARIANTS[n]], 32)
    t = frame_time(frame, scene.n_frames)
    points, normals = receivers_at_time(scene, t)
    shared = shared_normal_count(scene.receivers.normals)
    lighting = scene_lighting(scene)
    analytic = sphere_path == "analytic"
    vis, dist = occluder_visibilities(scene, scene_bsvs(scene, t, sphere_path), points)
    default = combine(scene, points, normals, vis, dist, lighting, analytic, shared)
    t0 = time.perf_counter()
    exact = oracle_rows(scene, t, points, n_plane, n, dirs, own_grid)
    cast_s = time.perf_counter() - t0
    oracle = combine(scene, points, normals, exact, dist, lighting, analytic, shared)
    row = {"tuned": tuned, "bands": n, "ref_spp": int(ref["spp"]), "oracle_cast_s": cast_s}
    for label, e in (("default", default), ("oracle", oracle)):
        err = models.errors(np.asarray(e, np.float64), ref, n_plane)
        row[label] = {k: err[k] for k in err if k != "ref_stderr_pct"}
    row["ref_stderr_pct"] = 100 * float(np.sqrt(np.mean(ref["stderr"] ** 2)) / np.mean(ref["mean"]))
    # the visibility rows themselves: how far the field is from the exact n-band visibility
    diff = [float(jnp.sqrt(jnp.mean((a - b) ** 2))) for a, b in zip(vis, exact, strict=True)]
    row["visibility_rms_difference"] = diff
    return row


def plot(results: dict) -> str:
    cases = list(results["cases"])
    bands = results["bands"]
    fig, ax = plt.subplots(figsize=(12.0, 4.2), dpi=110)
    width = 0.8 / (2 * len(bands))
    colors = {4: ("#1f77b4", "#aec7e8"), 6: ("#2ca02c", "#98df8a"), 8: ("#d62728", "#ff9896")}
    for b_i, n in enumerate(bands):
        for k, label in enumerate(("default", "oracle")):
            xs, ys = [], []
            for c_i, name in enumerate(cases):
                row = results["cases"][name].get(str(n))
                if row is None:
                    continue
                xs.append(c_i + (2 * b_i + k - len(bands) + 0.5) * width)
                ys.append(row[label]["rel_rmse_pct"])
            ax.bar(xs, ys, width, color=colors[n][k], label=f"{label}, {n} bands", edgecolor="k", lw=0.3)
    ax.axhline(1.0, color="0.4", lw=0.8, ls="--")
    ax.set_yscale("log")
    ax.set_xticks(range(len(cases)))
    ax.set_xticklabels(cases, rotation=30, ha="right", fontsize=7)
    ax.set_ylabel("relative RMSE of irradiance [%]", fontsize=8)
    ax.set_title(
        "default method against exact n-band visibility (oracle): the floor of any extrapolation", fontsize=9
    )
    ax.legend(fontsize=6, ncol=len(bands), loc="upper left")
    ax.tick_params(axis="y", labelsize=7)
    fig.tight_layout()
    path = models.FIGURES / "band_limit.png"
    models.FIGURES.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
    return str(path.relative_to(models.ROOT))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="*", default=None)
    ap.add_argument("--bands", nargs="*", type=int, default=[4, 6, 8], choices=sorted(BAND_VARIANTS))
    ap.add_argument("--dirs", type=int, default=48, help="exact visibility: directions² per hemisphere")
    ap.add_argument("--own-grid", nargs=2, type=int, default=[24, 96], help="own vertices: hemisphere grid")
    ap.add_argument("--plot-only", action="store_true")
    args = ap.parse_args()
    out = models.RESULTS / "band_limit.json"
    if args.plot_only:
        results = json.loads(out.read_text())
        results["figure"] = plot(results)
        out.write_text(json.dumps(results, indent=1))
        return
    names = args.cases or list(models._cases())
    results = {
        "bands": args.bands,
        "dirs": args.dirs,
        "own_grid": args.own_grid,
        "git": git_state(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "cases": {},
    }
    t_start = time.perf_counter()
    for name in names:
        for n in args.bands:
            if (name, n) in SKIP:
                print(f"{name:22s} n={n}: skipped (compile time)", flush=True)
                continue
            t0 = time.perf_counter()
            row = run_case(name, n, args.dirs, tuple(args.own_grid))
            row["seconds"] = time.perf_counter() - t0
            results["cases"].setdefault(name, {})[str(n)] = row
            d, o = row["default"], row["oracle"]
            extra = ""
            if "vertices_rel_rmse_pct" in d:
                extra = (
                    f"  vertices {d['vertices_rel_rmse_pct']:5.2f} / {o['vertices_rel_rmse_pct']:5.2f} %"
                    f"  plane {d['plane_rel_rmse_pct']:5.2f} / {o['plane_rel_rmse_pct']:5.2f} %"
                )
            print(
                f"{name:22s} n={n}: default {d['rel_rmse_pct']:6.2f} % (max {d['max_rel_err_pct']:6.1f} %)"
                f"  oracle {o['rel_rmse_pct']:6.2f} % (max {o['max_rel_err_pct']:6.1f} %){extra}"
                f"  [{row['seconds']:.0f} s]",
                flush=True,
            )
            out.write_text(json.dumps(results, indent=1))  # after every row: a crash keeps the rest
    results["seconds"] = time.perf_counter() - t_start
    results["figure"] = plot(results)
    out.write_text(json.dumps(results, indent=1))
    print(f"wrote {out} and {results['figure']} in {results['seconds']:.0f} s")


if __name__ == "__main__":
    main()
