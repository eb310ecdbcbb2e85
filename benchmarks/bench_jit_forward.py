"""First call (trace + compile + run) of a forward-only ``jax.jit`` frame and of ``jax.jit(jax.grad)``.

Usage::

    python benchmarks/bench_jit_forward.py [--configs configs/egg_breathing.toml ...] [--runs 5]
                                           [--grad] [--json out.json]

For each config, ``f(t) = render_at(scene, t).irradiance`` with the scene built outside and closed
over and the animation time ``t`` the traced argument (so the deforming mesh's vertices are traced):
what a user who jits a frame compiles. Reports the first call (seconds; each config in a fresh
process, so nothing is cached from another config) and the warm median (ms) of ``--runs`` calls with
``block_until_ready``. With ``--grad`` also ``jax.jit(jax.grad(Σ f(t)))`` (derivative with respect to
the time, through the deformation and the BSV's silhouette term). float32, default method.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import subprocess
import sys
import time

ROOT = pathlib.Path(__file__).resolve().parents[1]
DEFAULT = ["configs/egg_breathing.toml", "configs/bunny_animated.toml", "configs/airplane_bend.toml"]


def _first_and_warm(fn, x, runs):
    import jax

    t0 = time.perf_counter()
    jax.block_until_ready(fn(x))
    first = time.perf_counter() - t0
    warm = []
    for _ in range(runs):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(x))
        warm.append(time.perf_counter() - t0)
    return first, 1e3 * sorted(warm)[len(warm) // 2]


def one(config: str, runs: int, grad: bool) -> dict:
    """Time one config in this process."""
    import dataclasses

    import jax
    import jax.numpy as jnp

    from jshadow.config import build_scene, load_config
    from jshadow.scene import render_at

    scene = build_scene(load_config(ROOT / config))
    # the n-band light path (light_visibility = "auto" would take the occlusion images here)
    scene = dataclasses.replace(
        scene, method=dataclasses.replace(scene.method, light_visibility="sh", environment_lights=0)
    )

    def frame(t):
        return render_at(scene, t).irradiance

    t = jnp.float32(0.5)
    row = {"config": config, "bsv_gradient": scene.method.bsv_gradient}
    row["forward_first_s"], row["forward_warm_ms"] = _first_and_warm(jax.jit(frame), t, runs)
    if grad:
        g = jax.jit(jax.grad(lambda t: jnp.sum(frame(t))))
        row["grad_first_s"], row["grad_warm_ms"] = _first_and_warm(g, t, runs)
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", nargs="*", default=DEFAULT)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--grad", action="store_true", help="also time jax.jit(jax.grad(...))")
    ap.add_argument("--json", type=pathlib.Path)
    ap.add_argument("--one", help=argparse.SUPPRESS)  # internal: time this config in this process
    args = ap.parse_args(argv)
    if args.one:
        print("ROW " + json.dumps(one(args.one, args.runs, args.grad)))
        return 0
    rows = []
    for c in args.configs:  # a fresh process per config: nothing compiled for one helps another
        cmd = [sys.executable, __file__, "--one", c, "--runs", str(args.runs)]
        cmd += ["--grad"] if args.grad else []
        p = subprocess.run(cmd, capture_output=True, text=True, check=True)
        row = json.loads([x for x in p.stdout.splitlines() if x.startswith("ROW ")][-1][4:])
        rows.append(row)
        first, warm = row["forward_first_s"], row["forward_warm_ms"]
        line = f"{c:32s} forward: first {first:6.2f} s, warm {warm:7.2f} ms"
        if args.grad:
            line += f"   grad: first {row['grad_first_s']:6.2f} s, warm {row['grad_warm_ms']:7.2f} ms"
        print(line)
    meta = {
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "runs": args.runs,
    }
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
