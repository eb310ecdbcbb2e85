"""The default method against the paper's, on every shipped scene and the untuned ones, in one run.

The default is what a config without ``[method]`` keys renders: shell 1.5 r, the concentric-sphere
model, n + 1 visibility bands, ratio shading, and ``light_visibility = "auto"``, which shadows
sphere lights and a lat-long map's lamps (32 distant lights) through the BSV's occlusion images
wherever they apply (:func:`jshadow.config.auto_light_path`). For each case of
``experiments/models.py`` and ``experiments/light_field.py`` (the shipped configs at a 32² plane,
the calibration scenes at 40², and the untuned scenes), three settings are rendered against the
same cached Monte Carlo reference (``experiments/results/refs/``; ``models.reference`` makes one
that is missing):

* ``paper``: ``preset = "paper"`` (shell r, the paper's f_k, 4 bands, Zhou et al.'s products);
* ``n-band``: the default with every light through the n-band path (the default until
  ``light_visibility = "auto"``);
* ``default``: the default, with the light path ``auto`` takes for that scene (the same as
  ``n-band`` where it takes the n-band path: no sphere light and no lat-long map, which is not
  rendered twice).

Figures per case and setting (``models.errors``): relative RMSE and max error over all receivers
(divided by the mean reference irradiance), the plane's, the own vertices' where they are receivers,
the largest excess over the unoccluded reference; time per frame: the median frame of fresh
renderers (``models.timed``: BSV, images, own-vertex casts and shading made for the frame, 32²
plane), and the median of a renderer's frames after its first (``reshaded``: what a shape that
does not change makes once is reused); each median over ``--runs`` frames or as many more as
take 200 ms in all (``models.sampled_ms``: sub-millisecond frames take hundreds).

Usage (repository root, project environment active)::

    python experiments/defaults.py [--cases ...] [--runs 3]

Writes ``experiments/results/defaults.json``, ``experiments/figures/defaults_maps.png`` (signed
error on the plane, ±10 % of the mean, per case and setting) and
``experiments/figures/defaults_pareto.png`` (error against time per frame, per case).
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys
import time

import jax
import matplotlib
import matplotlib.ticker
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import light_field  # noqa: E402
import models  # noqa: E402
from _common import git_state  # noqa: E402

from jshadow.config import auto_light_path  # noqa: E402
from jshadow.entities import shape_is_static  # noqa: E402

CASES = [
    # shipped configs
    "sphere",
    "bunny_studio",
    "spot_sunset",
    "airplane_bend_last",
    "egg_breathing",
    "bunny_animated_last",
    # calibration scenes (DESIGN.md §2)
    "calib_sphere_bsv",
    "calib_bunny",
    # untuned
    "spot_sky_light",
    "twisted_airplane_sky",
    "three_occluders",
    "bunny_self_sky",
    "bunny_self_sky_twist",
    "airplane_studio_twist",
    "bunny_studio_low",
    "spot_light_low",
    # untuned, deforming: a map's lamps in images made every frame, a mesh's own vertices by "maps"
    "airplane_studio_bend_last",
    "spot_twist_low_last",
    "spot_self_sky_bend_last",
    "bunny_self_sky_bend_last",
]
SETTINGS = ("paper", "n-band", "default")
N_BAND = ("sh", 0, "field")  # light_visibility, environment_lights, self_visibility of the n-band path


def reshaded(scene, frame, sphere_path, runs) -> float:
    """Median ms of a renderer's frames after its first: what a shape that does not change makes
    once (its BSV, occlusion images, own-vertex casts, and for a scene that does not change at all
    the visible fractions) is reused; a deforming shape's frames make everything again."""
    rend = models.Renderer(scene, sphere_path)
    rend.frame(frame)
    static = all(shape_is_static(o) for o in scene.occluders)

    def sample():
        if not static:  # a deforming shape's next frame is another pose: nothing kept for it
            models.clear_pose_caches()
        return rend.frame(frame)[1]["total_ms"]

    return models.sampled_ms(sample, runs)


def auto_keys(scene) -> dict:
    """The ``[method]`` keys the "auto" options give this scene (built with the n-band light path):
    ``light_visibility``, ``environment_lights``, ``self_visibility``, ``directions``,
    ``light_cap``."""
    m = scene.method
    hdr = scene.environment is not None and scene.environment.kind == "hdr"
    env = scene.environment is not None
    return auto_light_path(
        scene.occluders,
        bool(scene.lights),
        hdr,
        scene.self_shadow,
        m.shell,
        m.bsv_method,
        environment=env,
        receivers=scene.receivers.points,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="*", default=CASES)
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    results = {"git": git_state(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "cases": {}}
    out = models.RESULTS / "defaults.json"
    maps = {}
    t_start = time.perf_counter()
    cases = light_field._cases()
    for name in args.cases:
        build, frame, sphere_path, tuned = cases[name]
        res = 40 if name.startswith("calib") else 32
        nband = dict(models.VARIANTS[models.DEFAULT_VARIANT])
        base = build(nband, res)
        ref = models.reference(name, build(models.VARIANTS["paper"], res), frame, 1e-3, 32768)
        n_plane = int(np.prod(base.receivers.grid_shape))
        auto = auto_keys(base)
        methods = {"paper": models.VARIANTS["paper"], "n-band": nband}
        if tuple(auto[k] for k in ("light_visibility", "environment_lights", "self_visibility")) != N_BAND:
            methods["default"] = dict(nband, **auto)
        rows, got = {}, {}
        for label, method in methods.items():
            scene = build(method, res)
            approx, first, warm = models.timed(scene, frame, sphere_path, args.runs)
            err = models.errors(approx, ref, n_plane)
            again = reshaded(scene, frame, sphere_path, args.runs)
            err.update(first_ms=first, warm_ms=warm, reshaded_ms=again)
            rows[label], got[label] = err, approx
            print(
                f"{name:22s} {label:8s} rmse {err['rel_rmse_pct']:6.2f} %"
                f"  max {err['max_rel_err_pct']:6.1f} %"
                f"  excess {err['max_excess_over_unoccluded_pct']:5.2f} %  {warm:7.1f} ms"
                f" (re-shaded {err['reshaded_ms']:6.1f} ms)",
                flush=True,
            )
        if "default" not in rows:  # auto takes the n-band path here: the same render
            rows["default"], got["default"] = rows["n-band"], got["n-band"]
        results["cases"][name] = {
            "tuned": tuned,
            "ref_spp": int(ref["spp"]),
            "default_light_path": auto,
            "settings": rows,
        }
        maps[name] = (ref["mean"][:n_plane], {s: got[s][:n_plane] for s in SETTINGS})
        out.write_text(json.dumps(results, indent=1))
        jax.clear_caches()  # each case compiles its own programs (light_field.py: LLVM out of memory)
    results["seconds"] = time.perf_counter() - t_start
    fig, axes = plt.subplots(
        len(SETTINGS), len(maps), figsize=(2.1 * len(maps), 2.2 * len(SETTINGS)), dpi=100, squeeze=False
    )
    im = None
    for j, (name, (ref, rows)) in enumerate(maps.items()):
        side = int(round(math.sqrt(ref.shape[0])))
        for i, label in enumerate(SETTINGS):
            ax = axes[i, j]
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(name, fontsize=7)
            if j == 0:
                ax.set_ylabel(label, fontsize=9)
            err = ((rows[label] - ref).mean(1) / ref.mean()).reshape(side, side)
            im = ax.imshow(100 * err, cmap="RdBu_r", vmin=-10, vmax=10, origin="lower")
            e = results["cases"][name]["settings"][label]["plane_rel_rmse_pct"]
            ax.set_xlabel(f"plane {e:.2f} %", fontsize=7)
    fig.colorbar(im, ax=axes, shrink=0.8, label="(render − reference) / mean [%]")
    path = models.FIGURES / "defaults_maps.png"
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)
    results["figure"] = str(path.relative_to(models.ROOT))
    results["pareto_figure"] = pareto(results)
    out.write_text(json.dumps(results, indent=1))
    print(f"wrote {out}, {path} and {results['pareto_figure']} in {results['seconds']:.0f} s")


def pareto(results: dict) -> str:
    """Error against time per frame, one panel per scene: paper, n-band and default as points (the
    default filled; the issue's 1 % RMSE and 1.5× the paper's time as dashed lines)."""
    names = list(results["cases"])
    cols = 5
    rows = -(-len(names) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(2.6 * cols, 2.4 * rows), dpi=100, squeeze=False)
    style = {"paper": ("s", "tab:red"), "n-band": ("o", "tab:blue"), "default": ("*", "tab:green")}
    for ax, name in zip(axes.flat, names, strict=False):
        rows_ = results["cases"][name]["settings"]
        for label, (marker, colour) in style.items():
            r = rows_[label]
            size = 9 if label == "default" else 6
            ax.loglog(r["warm_ms"], r["rel_rmse_pct"], marker, color=colour, ms=size)
        ax.axhline(1.0, color="grey", ls="--", lw=0.8)
        ax.axvline(1.5 * rows_["paper"]["warm_ms"], color="grey", ls=":", lw=0.8)
        ax.set_title(name, fontsize=8)
        ax.tick_params(labelsize=7)
        for axis in (ax.xaxis, ax.yaxis):  # decades only: the minor labels overlap on short ranges
            axis.set_minor_formatter(matplotlib.ticker.NullFormatter())
            axis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
    for ax in axes.flat[len(names) :]:
        ax.set_visible(False)
    for ax in axes[-1]:
        ax.set_xlabel("ms per frame (fresh)", fontsize=8)
    for ax in axes[:, 0]:
        ax.set_ylabel("relative RMSE [%]", fontsize=8)
    handles = [plt.Line2D([], [], ls="", marker=m, color=c, label=lb) for lb, (m, c) in style.items()]
    fig.legend(handles=handles, loc="lower right", fontsize=9)
    fig.tight_layout()
    path = models.FIGURES / "defaults_pareto.png"
    fig.savefig(path)
    plt.close(fig)
    return str(path.relative_to(models.ROOT))


if __name__ == "__main__":
    main()
