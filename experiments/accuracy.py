"""Accuracy of the shipped scenes: shadow-field render vs the Monte Carlo reference (DESIGN.md §5).

For every shipped config except the fit configs — ``sphere``, ``bunny_studio``, ``spot_sunset``,
``airplane_bend`` (frame 0 and the last frame), ``egg_breathing`` (frame 0) — the receiver plane is
reduced to ``--res``² vertices (default 48², from 128²/160², for time; everything else as shipped)
and the scene is rendered with :class:`jshadow.runner.Renderer` (the shadow-field method of the
deformable-shadow-fields paper on top of Zhou et al. 2005 "Precomputed shadow fields") and
integrated by :func:`jshadow.reference` (exact visibility; projected-spherical-cap sampling of the
sphere lights, Peters & Dachsbacher 2019).

Samples: a pilot reference at ``--pilot`` spp gives the error and the reference's standard error;
the spp needed for ``stderr_rms ≤ --target × RMSE`` is then added with an independent seed (capped
at ``--max-spp``; the two runs are merged, weighted by their spp). The stderr ratio actually
reached is reported for every case.

Figures per case (irradiance, all channels and receivers, relative to the reference's mean):
relative RMSE, max error, max pointwise relative error, the fraction of plane receivers brighter
than the *unoccluded* irradiance by more than 1 % (unoccluded = the reference of the scene with its
occluders removed; only counted where the excess also exceeds 3 standard errors of that reference),
the stderr ratio, times (render: median of 5 warm frames on fresh renderers, BSV included; compile
separately; reference: wall time). For self-shadowing scenes the plane-only errors are given too.
Diagnostics against the same reference: the scene rendered with ``shell = 1.5`` and with
``model = "sphere"``; the unoccluded render's error; a sphere-proxy scene (see :func:`proxy_scene`).

Usage (repository root, project environment active)::

    python experiments/accuracy.py [--res 48] [--pilot 1024] [--target 0.1] [--max-spp 16384]

Writes ``experiments/results/accuracy.json`` and ``experiments/figures/accuracy_<case>.png``
(signed relative error on the plane's grid, one diverging scale shared by all cases).
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import pathlib
import platform
import time
import tomllib

import jax
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import jshadow  # noqa: E402
from jshadow.compare import frame_errors  # noqa: E402
from jshadow.config import build_scene, config_from_dict  # noqa: E402
from jshadow.runner import Renderer  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
RESULTS = ROOT / "experiments" / "results"
FIGURES = ROOT / "experiments" / "figures"

# (case name, config file, frame; None = the last frame)
CASES = [
    ("sphere", "sphere.toml", 0),
    ("bunny_studio", "bunny_studio.toml", 0),
    ("spot_sunset", "spot_sunset.toml", 0),
    ("airplane_bend_f0", "airplane_bend.toml", 0),
    ("airplane_bend_last", "airplane_bend.toml", None),
    ("egg_breathing_f0", "egg_breathing.toml", 0),
]


# method variants rendered beside the shipped setting (same reference): (label, [method] keys)
VARIANTS = [("shell1.5", {"shell": 1.5}), ("sphere_model", {"model": "sphere"})]


def load_scene(file: str, res: int, method: dict | None = None):
    """The shipped config with the receiver plane at res × res vertices and ``method`` keys
    overriding its ``[method]`` table; (scene, config dict, path)."""
    path = CONFIGS / file
    d = copy.deepcopy(tomllib.loads(path.read_text()))
    d.setdefault("receiver", {})["resolution"] = [res, res]
    d.setdefault("method", {}).update(method or {})
    return build_scene(config_from_dict(d, source=str(path), root=path.parent)), d, path


def proxy_scene(d: dict, path: pathlib.Path, scale: float):
    """Diagnostic: the same scene (plane receivers only) with every mesh occluder replaced by a
    sphere of ``scale`` × its bounding radius at its centre (sphere occluders stay as they are),
    rendered on the analytic sphere path. Its error is the part of the method's error that the
    occluder model does not cause (lighting and visibility truncated to n bands, their truncated
    product)."""
    d = copy.deepcopy(d)
    d["occluder"] = [
        {
            "type": "sphere",
            "center": o["center"],
            "radius": o["radius"] * (1.0 if o.get("type") == "sphere" else scale),
        }
        for o in d.get("occluder", [])
    ]
    d["receiver"]["self_shadow"] = False
    d.pop("animation", None)
    return build_scene(config_from_dict(d, source=str(path), root=path.parent))


def render_timed(scene, frame: int, runs: int = 5):
    t0 = time.perf_counter()
    res, _ = Renderer(scene).frame(frame)
    first = time.perf_counter() - t0
    stages = [Renderer(scene).frame(frame)[1] for _ in range(runs)]
    med = {k: float(np.median([s[k] for s in stages])) for k in stages[0]}
    return res, 1e3 * first, med


def merge(a, b):
    """Merge two independent reference runs ((spp, mean, stderr), ...) weighted by spp."""
    (n1, m1, s1), (n2, m2, s2) = a, b
    n = n1 + n2
    return n, (n1 * m1 + n2 * m2) / n, np.sqrt((n1 * s1) ** 2 + (n2 * s2) ** 2) / n


def reference_to_target(scene, frame, pilot, target, max_spp, seed, rendered):
    """Reference irradiance with stderr_rms ≤ target · RMSE(rendered) where max_spp allows."""
    t0 = time.perf_counter()
    r = jshadow.reference(scene, pilot, jax.random.PRNGKey(seed), frame=frame)
    acc = (pilot, np.asarray(r.irradiance, np.float64), np.asarray(r.irradiance_stderr, np.float64))
    rmse = frame_errors(rendered, acc[1])["rmse"]
    ratio = float(np.sqrt(np.mean(acc[2] ** 2))) / rmse
    if ratio > target and pilot < max_spp:
        extra = int(math.ceil(pilot * ((ratio / target) ** 2 - 1.0) * 1.1 / 64.0)) * 64
        extra = max(512, min(extra, max_spp - pilot))
        r2 = jshadow.reference(scene, extra, jax.random.PRNGKey(seed + 1000), frame=frame)
        acc = merge(acc, (extra, np.asarray(r2.irradiance, np.float64), np.asarray(r2.irradiance_stderr)))
    return acc, time.perf_counter() - t0


def bare_scene(scene):
    """The scene's plane receivers and lights without any occluder."""
    return type(scene)(
        method=scene.method,
        receivers=scene.receivers,
        occluders=(),
        lights=scene.lights,
        environment=scene.environment,
        self_shadow=False,
        n_frames=scene.n_frames,
    )


def unoccluded(scene, frame, spp, seed):
    """Reference irradiance of the plane receivers with every occluder removed (mean, stderr)."""
    r = jshadow.reference(bare_scene(scene), spp, jax.random.PRNGKey(seed + 2000), frame=frame)
    return np.asarray(r.irradiance, np.float64), np.asarray(r.irradiance_stderr, np.float64)


def save_maps(cases: list[dict], maps: dict, lim: float) -> list[str]:
    paths = []
    for c in cases:
        fig, ax = plt.subplots(figsize=(4.8, 4.2), dpi=100)
        im = ax.imshow(
            100 * maps[c["case"]],
            cmap="RdBu_r",
            vmin=-100 * lim,
            vmax=100 * lim,
            origin="lower",
            extent=c["plane_extent"],
            interpolation="nearest",
        )
        ax.set_xlabel("x")
        ax.set_ylabel("z")
        ax.set_title(
            f"{c['case']} (frame {c['frame']}): rel. RMSE {c['rel_rmse_pct']:.2f} %, "
            f"max {c['max_rel_err_pct']:.1f} %",
            fontsize=8,
        )
        fig.colorbar(im, ax=ax, label="(render − ref) / mean ref, RGB mean  [%]")
        fig.tight_layout()
        p = FIGURES / f"accuracy_{c['case']}.png"
        fig.savefig(p)
        plt.close(fig)
        paths.append(str(p.relative_to(ROOT)))
    return paths


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--res", type=int, default=48, help="receiver plane resolution (res × res)")
    ap.add_argument("--pilot", type=int, default=1024, help="pilot reference spp")
    ap.add_argument("--target", type=float, default=0.1, help="wanted stderr_rms / RMSE")
    ap.add_argument("--max-spp", type=int, default=16384, help="cap on the reference's total spp")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--proxy-scale", type=float, default=0.6, help="sphere proxy radius / bounding radius")
    ap.add_argument("--only", nargs="*", default=None, help="case names to run (default: all)")
    args = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    FIGURES.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    rows, maps = [], {}
    for name, file, frame in CASES:
        if args.only and name not in args.only:
            continue
        scene, d, path = load_scene(file, args.res)
        frame = scene.n_frames - 1 if frame is None else frame
        res, first_ms, stage_ms = render_timed(scene, frame)
        a = np.asarray(res.irradiance, np.float64)
        (spp, ref, se), ref_s = reference_to_target(
            scene, frame, args.pilot, args.target, args.max_spp, args.seed, a
        )
        e = frame_errors(a, ref)
        n_plane = scene.receivers.points.shape[0]
        t0 = time.perf_counter()
        free, free_se = unoccluded(scene, frame, args.pilot, args.seed)
        free_s = time.perf_counter() - t0
        bare = Renderer(bare_scene(scene)).frame(frame)[0]
        e_bare = frame_errors(np.asarray(bare.irradiance, np.float64), free)
        proxy = proxy_scene(d, path, args.proxy_scale)
        e_proxy = {}
        if frame == 0:  # the proxy is undeformed: compare at the rest pose only
            p_ref = jshadow.reference(proxy, args.pilot, jax.random.PRNGKey(args.seed + 3000))
            p_img = np.asarray(Renderer(proxy).frame(0)[0].irradiance, np.float64)
            e_proxy = frame_errors(p_img, np.asarray(p_ref.irradiance, np.float64))
        variants = {}
        for label, opts in VARIANTS:
            v_scene = load_scene(file, args.res, opts)[0]
            v_img, _, v_ms = render_timed(v_scene, frame, runs=3)
            v_err = frame_errors(np.asarray(v_img.irradiance, np.float64), ref)
            variants[label] = {
                "method": opts,
                "rel_rmse_pct": 100 * v_err["rel_rmse"],
                "max_rel_err_pct": 100 * v_err["max_rel_err"],
                "render_warm_ms": v_ms["total_ms"],
            }
        excess = a[:n_plane] - 1.01 * free
        brighter = np.any((excess > 0) & (excess > 3.0 * free_se), axis=1)
        row = {
            "case": name,
            "config": f"configs/{file}",
            "frame": frame,
            "n_frames": scene.n_frames,
            "receivers": int(a.shape[0]),
            "plane_receivers": int(n_plane),
            "plane_resolution": [args.res, args.res],
            "spp": int(spp),
            "rel_rmse_pct": 100 * e["rel_rmse"],
            "max_err": e["max_err"],
            "max_rel_err_pct": 100 * e["max_rel_err"],
            "max_pointwise_rel_err_pct": 100 * e["max_pointwise_rel_err"],
            "mean_irradiance_ref": e["mean_irradiance_b"],
            "ref_stderr_ratio": float(np.sqrt(np.mean(se**2))) / e["rmse"],
            "frac_plane_brighter_than_unoccluded_1pct": float(np.mean(brighter)),
            "max_plane_excess_over_unoccluded_pct": 100 * float(np.max(a[:n_plane] / free - 1.0)),
            "unoccluded_render_rel_rmse_pct": 100 * e_bare["rel_rmse"],
            "unoccluded_render_max_rel_err_pct": 100 * e_bare["max_rel_err"],
            "sphere_proxy_rel_rmse_pct": 100 * e_proxy["rel_rmse"] if e_proxy else None,
            "sphere_proxy_max_rel_err_pct": 100 * e_proxy["max_rel_err"] if e_proxy else None,
            "variants": variants,
            "render_first_call_ms": first_ms,
            "render_warm_ms": stage_ms,
            "reference_s": ref_s,
            "unoccluded_reference_s": free_s,
        }
        if a.shape[0] > n_plane:  # self-shadow receivers appended after the plane
            p = frame_errors(a[:n_plane], ref[:n_plane])
            v = frame_errors(a[n_plane:], ref[n_plane:])
            row["plane_rel_rmse_pct"] = 100 * p["rel_rmse"]
            row["plane_max_rel_err_pct"] = 100 * p["max_rel_err"]
            row["vertices_rel_rmse_pct"] = 100 * v["rel_rmse"]
            row["vertices_max_rel_err_pct"] = 100 * v["max_rel_err"]
        size = d["receiver"].get("size", [4.0, 4.0])
        cen = d["receiver"].get("center", [0.0, 0.0, 0.0])
        row["plane_extent"] = [
            cen[0] - size[0] / 2,
            cen[0] + size[0] / 2,
            cen[2] - size[1] / 2,
            cen[2] + size[1] / 2,
        ]
        grid = scene.receivers.grid_shape
        maps[name] = (np.mean(a[:n_plane] - ref[:n_plane], axis=1) / e["mean_irradiance_b"]).reshape(grid)
        rows.append(row)
        print(
            f"{name:>20} f{frame:<3} spp {spp:6d}: rel RMSE {row['rel_rmse_pct']:6.2f} %  "
            f"max {row['max_rel_err_pct']:6.2f} %  stderr ratio {row['ref_stderr_ratio']:.3f}  "
            f"brighter {row['frac_plane_brighter_than_unoccluded_1pct']:.3f}  "
            f"bare {row['unoccluded_render_rel_rmse_pct']:.2f} %  "
            f"proxy {row['sphere_proxy_rel_rmse_pct'] or 0:.2f} %  "
            f"render {stage_ms['total_ms']:.1f} ms  ref {ref_s:.1f} s  "
            + "  ".join(f"{k} {v['rel_rmse_pct']:.2f} %" for k, v in variants.items()),
            flush=True,
        )
    lim = max(float(np.max(np.abs(m))) for m in maps.values())
    pngs = save_maps(rows, maps, lim)
    out = {
        "settings": vars(args),
        "rows": rows,
        "figures": pngs,
        "map_scale_pct": 100 * lim,
        "total_s": time.perf_counter() - t_start,
        "machine": f"{platform.processor() or platform.machine()}, {jax.devices()[0].platform}",
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    }
    suffix = "" if not args.only else "_" + "_".join(args.only)
    (RESULTS / f"accuracy{suffix}.json").write_text(json.dumps(out, indent=2))
    print(f"total {out['total_s']:.0f} s")


if __name__ == "__main__":
    main()
