"""Fresh frames of a deforming config: the default, the default settling only the pairs whose four
pixel centres disagree (no slivers), the default without settling the own vertices' ambiguous
lamp pairs exactly, and the paper's method, in one process.

    python benchmarks/bench_own_maps.py [--config configs/bunny_animated.toml] [--frames 16]
        [--blocks 3] [--json out.json]

Every pose is rendered once per setting first (each new pose can bring new padded shapes to
compile: the lamp images' face groups, the settled pairs' entries), then ``--blocks`` blocks of the
``--frames`` poses per setting, alternating, the per-pose caches cleared before each frame, so every
timed frame makes its own-vertex visibility, lamp images and BSVs again as a deforming mesh's next
frame does. Medians per stage (the renderer's timings) and the ratios to the paper's.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time
import tomllib

import numpy as np
from bench_render import METHODS  # the same "paper" settings (this folder is on sys.path as a script)

import jshadow.scene as scene_mod
import jshadow.visibility._own_exact as own_exact
from jshadow.config import build_scene, config_from_dict
from jshadow.runner import Renderer

ROOT = pathlib.Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "bunny_animated.toml"))
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--blocks", type=int, default=3)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    path = pathlib.Path(args.config)
    doc = tomllib.loads(path.read_text())

    def renderer(extra: dict) -> Renderer:
        d = {**doc, "method": {**doc.get("method", {}), **extra}}
        return Renderer(build_scene(config_from_dict(d, source=str(path), root=path.parent)))

    # (renderer, settle the ambiguous pairs, pixels searched for slivers beyond the four centres)
    settings = {
        "default": (renderer({}), True, own_exact.REACH),
        "four": (renderer({}), True, 0),
        "unsettled": (renderer({}), False, 0),
        "paper": (renderer(METHODS["paper"]), True, own_exact.REACH),
    }
    reach = own_exact.REACH
    poses = range(min(args.frames, max(settings["default"][0].scene.n_frames, 1)))
    t0 = time.perf_counter()
    for rend, settle, sliver in settings.values():  # every pose's shapes compiled first
        scene_mod.MAPS_EXACT_AMBIGUOUS, own_exact.REACH = settle, sliver
        for f in poses:
            scene_mod.clear_pose_caches()
            rend.frame(f)
    compile_s = time.perf_counter() - t0
    rows: dict[str, list[dict]] = {k: [] for k in settings}
    for _ in range(args.blocks):
        for name, (rend, settle, sliver) in settings.items():
            scene_mod.MAPS_EXACT_AMBIGUOUS, own_exact.REACH = settle, sliver
            for f in poses:
                scene_mod.clear_pose_caches()
                rows[name].append(rend.frame(f)[1])
    scene_mod.MAPS_EXACT_AMBIGUOUS, own_exact.REACH = True, reach
    out = {
        "config": str(path),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "first_pass_s": compile_s,
        "frames_timed": {k: len(v) for k, v in rows.items()},
        "median_ms": {k: {s: float(np.median([r[s] for r in v])) for s in v[0]} for k, v in rows.items()},
    }
    paper = out["median_ms"]["paper"]["total_ms"]
    out["ratio_to_paper"] = {k: v["total_ms"] / paper for k, v in out["median_ms"].items()}
    for k, v in out["median_ms"].items():
        stages = "  ".join(f"{s} {x:7.1f}" for s, x in v.items())
        print(f"{k:10s} {stages}  ({out['ratio_to_paper'][k]:.2f}x the paper)", flush=True)
    print(f"first pass (every pose once per setting, compiling) {compile_s:.1f} s")
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
