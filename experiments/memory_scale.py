"""Peak memory and time of one frame with 1,000,000 receivers and 8 deforming mesh occluders.

Scene: a 1000 × 1000 receiver plane (4 × 4 units) under a constant environment and one sphere
light; eight copies of ``assets/bunny_small.obj`` (1000 faces each) on a ring, each twisting, so
every frame samples eight BSVs (12 × 20 points × 32² directions, edge-scan on a 1.5 r shell).
The frame is rendered by :class:`jshadow.runner.Renderer` in pieces of ``chunk`` receivers, with
its progress bar.

Each chunk size runs in a fresh process, so that the peak resident set size (``VmHWM`` of
``/proc/self/status``, the high-water mark of the whole process: Python, JAX, compiled code,
scene, outputs) belongs to that setting alone. Reported per setting: peak RSS, the time of the
first frame (compilation included) and the median of 3 warm frames.

Run: ``python experiments/memory_scale.py`` (writes ``experiments/results/memory_scale.json``);
``--chunks 32768 131072`` chooses the settings, ``--side 1000`` the plane resolution.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import subprocess
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
RESULTS = ROOT / "experiments" / "results" / "memory_scale.json"
LIMIT_GIB = 8.0


def _peak_rss_gib() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024 / 2**30
    import resource  # fallback: ru_maxrss is in KiB on Linux

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 2**30


def _config(side: int) -> dict:
    import math

    occluders = []
    for i in range(8):
        a = 2 * math.pi * i / 8
        occluders.append(
            {
                "type": "mesh",
                "file": str(ROOT / "assets" / "bunny_small.obj"),
                "center": [1.3 * math.cos(a), 0.6, 1.3 * math.sin(a)],
                "radius": 0.35,
                "deform": {"type": "twist", "amount": [0.0, 0.6], "axis": "y"},
            }
        )
    return {
        "method": {"shell": 1.5, "light_visibility": "sh"},  # the n-band light path, as recorded
        "environment": {"type": "constant", "radiance": [0.5, 0.55, 0.6]},
        "occluder": occluders,
        "light": [
            {"type": "sphere", "center": [1.0, 3.0, 0.5], "radius": 0.3, "radiance": [20.0, 20.0, 20.0]}
        ],
        "receiver": {
            "type": "plane",
            "center": [0.0, 0.0, 0.0],
            "size": [4.0, 4.0],
            "resolution": [side, side],
            "albedo": [0.8, 0.8, 0.8],
        },
        "animation": {"frames": 4},
    }


def child(chunk: int, side: int) -> dict:
    import jax
    import numpy as np

    import jshadow
    from jshadow.config import config_from_dict
    from jshadow.runner import Renderer

    scene = jshadow.build_scene(config_from_dict(_config(side), source="memory_scale"))
    rss_scene = _peak_rss_gib()
    rend = Renderer(scene, chunk=chunk, progress=True)
    t0 = time.perf_counter()
    res, _ = rend.frame(0)
    first_s = time.perf_counter() - t0
    warm = [rend.frame(f)[1] for f in (1, 2, 3)]
    e = np.asarray(res.irradiance)
    return {
        "chunk": chunk,
        "receivers": int(e.shape[0]),
        "receivers_per_piece": rend.piece_size(e.shape[0]),
        "occluders": len(scene.occluders),
        "faces_per_occluder": int(scene.occluders[0].faces.shape[0]),
        "peak_rss_gib": _peak_rss_gib(),
        "rss_after_scene_gib": rss_scene,
        "first_frame_s_incl_compile": first_s,
        "warm_frame_s_median": float(np.median([w["total_ms"] for w in warm]) / 1e3),
        "warm_stage_ms_median": {k: float(np.median([w[k] for w in warm])) for k in warm[0]},
        "finite": bool(np.all(np.isfinite(e))),
        "load_average_1min": os.getloadavg()[0],
        "mean_irradiance": float(e.mean()),
        "device": str(jax.devices()[0]),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--chunks", type=int, nargs="+", default=[32768, 131072])
    ap.add_argument("--side", type=int, default=1000)
    ap.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child is not None:
        print("RESULT " + json.dumps(child(args.child, args.side)), flush=True)
        return
    rows = []
    for c in args.chunks:
        p = subprocess.run(
            [sys.executable, __file__, "--child", str(c), "--side", str(args.side)],
            capture_output=True,
            text=True,
            env=dict(os.environ, JAX_PLATFORMS=os.environ.get("JAX_PLATFORMS", "cpu")),
        )
        line = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
        if p.returncode != 0 or not line:
            rows.append(
                {"chunk": c, "failed": True, "returncode": p.returncode, "stderr_tail": p.stderr[-2000:]}
            )
            print(f"chunk {c}: failed (exit {p.returncode})")
            continue
        row = json.loads(line[0][len("RESULT ") :])
        row["within_8_gib"] = row["peak_rss_gib"] <= LIMIT_GIB
        rows.append(row)
        print(
            f"chunk {c:>8}: {row['receivers']} receivers x {row['occluders']} occluders, peak RSS "
            f"{row['peak_rss_gib']:.2f} GiB, first frame {row['first_frame_s_incl_compile']:.1f} s, "
            f"warm {row['warm_frame_s_median']:.2f} s/frame"
        )
    out = {
        "what": "one frame, 1000x1000 receiver plane, 8 twisting bunny_small occluders (BSV every frame), "
        "constant environment + 1 sphere light; peak RSS = VmHWM of a fresh process",
        "machine": f"{os.cpu_count()}-core CPU",
        "load_average_1min_at_end": os.getloadavg()[0],
        "date": time.strftime("%Y-%m-%d"),
        "command": "python experiments/memory_scale.py " + " ".join(sys.argv[1:]),
        "rows": rows,
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(out, indent=2) + "\n")
    print(f"-> {RESULTS}")


if __name__ == "__main__":
    main()
