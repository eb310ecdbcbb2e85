"""Frame times of the shipped configs with a sphere light or a lat-long map: the default,
``light_visibility = "images"`` (reading the 0/1 samples, and ``light_images = "coverage"``; with
``environment_lights`` for the maps) and the paper's method, in one run.

    python benchmarks/bench_light_images.py [--frames 20] [--json benchmarks/results/light_images.json]

For each of ``airplane_bend`` (bending every frame), ``egg_breathing`` (breathing every frame),
``spot_sunset`` and ``bunny_studio`` (static) and ``bunny_animated`` (twisting every frame, 160²
plane and the bunny's own vertices) at their shipped sizes, one :class:`jshadow.Renderer` per
method renders frame 0 (compile: ``first_s``), then ``--frames`` frames; the medians of their
per-stage timings (``bsv_ms``, ``light_images_ms``, ``shading_ms``, ``total_ms``) are reported,
and ``fresh_frame_ms``, the median frame 0 of five fresh renderers (a frame with its BSV and images
made for it: the whole cost of a static scene's one frame). A
machine probe (``bench_render.machine_probe``) before and after places the run among this VM's
phases. The error each setting buys is measured by ``experiments/light_field.py``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import bench_render  # noqa: E402

from jshadow import Renderer  # noqa: E402
from jshadow.config import build_scene, load_config  # noqa: E402
from jshadow.entities import Method  # noqa: E402

CONFIGS = [
    "configs/airplane_bend.toml",
    "configs/egg_breathing.toml",
    "configs/spot_sunset.toml",
    "configs/bunny_studio.toml",
    "configs/bunny_animated.toml",
]


def _methods(base) -> dict:
    """The settings timed on a config: the default (``light_visibility = "auto"``: the images where
    they apply), every light through the n-band path, the images for its sphere lights (if any), the
    images with environment lights (lat-long maps only; also at the finer grid and images that
    ``experiments/light_field.py`` measures), and the paper's method."""
    m = base.method
    out = {"default": m}  # light_visibility = "auto": the images where they apply
    m = dataclasses.replace(m, light_visibility="sh", environment_lights=0)
    out["n-band"] = m  # every light through the n-band path (the default until "auto")
    if base.lights:
        out["images"] = dataclasses.replace(m, light_visibility="images")
        out["images, coverage"] = dataclasses.replace(m, light_visibility="images", light_images="coverage")
    if base.environment is not None and base.environment.kind == "hdr":
        env = dataclasses.replace(m, light_visibility="images", environment_lights=32)
        out["images + 32 env lights"] = env
        out["images + 64 env lights, 24x40, 64²"] = dataclasses.replace(
            env, environment_lights=64, bsv_grid=(24, 40), directions=(64, 64), light_cap=(8, 16)
        )
    out["paper"] = Method.paper(sh_bands=m.sh_bands)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    out = {
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "probe_start": bench_render.machine_probe(),
    }
    for cfg in CONFIGS:
        base = build_scene(load_config(cfg))
        for label, m in _methods(base).items():
            scene = dataclasses.replace(base, method=m)
            r = Renderer(scene)
            t0 = time.perf_counter()
            r.frame(0)
            first = time.perf_counter() - t0
            ts = [r.frame(f % scene.n_frames)[1] for f in range(1, args.frames + 1)]
            med = {k: float(np.median([t[k] for t in ts])) for k in ts[0]}
            # a static scene renders its frame once: what that costs, BSV and images included, is a
            # fresh renderer's frame 0 (compiled by the first renderer)
            fresh = float(np.median([Renderer(scene).frame(0)[1]["total_ms"] for _ in range(5)]))
            out[f"{pathlib.Path(cfg).stem} {label}"] = dict(first_s=first, fresh_frame_ms=fresh, **med)
            print(
                f"{cfg:28s} {label:36s} first {first:5.1f} s fresh {fresh:6.1f} ms",
                {k: round(v, 2) for k, v in med.items()},
                flush=True,
            )
    out["probe_end"] = bench_render.machine_probe()
    print("machine probe", out["probe_start"], out["probe_end"])
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
