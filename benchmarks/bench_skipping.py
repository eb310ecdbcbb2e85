"""The image lookups with and without skipping the receivers that cannot be shadowed, in one run.

    python benchmarks/bench_skipping.py [--runs 15] [--json benchmarks/results/skipping.json]

``[method] light_visibility = "images"`` looks every receiver up in the occluders' occlusion images,
toward each sphere light (``jshadow.scene.light_visible_fractions``) and each fan of environment
lights (``jshadow.scene.environment_visible_fraction``). Receivers from which no ray toward the
light (or fan) can meet an occluder's bounding sphere have visible fraction 1 and need no lookup
(``jshadow.geometry.cone_may_meet_sphere`` / ``fan_may_meet_sphere``; ``jshadow._active.over_active``
runs the lookups on chunks of the others only). For each config, two ``jax.jit`` functions of the
frame's irradiance (``render_at`` at t = 0.5, BSVs and images included), traced with ``cull=False``
and ``cull=True``: compile times, warm medians (calls alternating) and their ratio, and the largest
difference of the irradiance relative to its maximum. A machine probe before and after places the
run among this VM's phases.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import bench_render  # noqa: E402

import jshadow.scene as S  # noqa: E402
from jshadow.config import build_scene, load_config  # noqa: E402

CASES = [  # config, [method] changes on top of light_visibility = "images"
    ("configs/spot_sunset.toml", {}),
    ("configs/airplane_bend.toml", {}),
    ("configs/egg_breathing.toml", {}),
    ("configs/bunny_studio.toml", {"environment_lights": 32}),
    ("configs/bunny_animated.toml", {"environment_lights": 32}),
]


def _frame_fns(scene) -> dict:
    """``{False: f, True: f}``: the frame's irradiance as a jitted function of t, traced without and
    with the skipping (the two lookups' ``cull`` argument, set while tracing)."""
    light, env = S.light_visible_fractions, S.environment_visible_fraction
    fns = {}
    try:
        for cull in (False, True):
            S.light_visible_fractions = functools.partial(light, cull=cull)
            S.environment_visible_fraction = functools.partial(env, cull=cull)
            fns[cull] = jax.jit(lambda t: S.render_at(scene, t).irradiance)
            fns[cull](0.5).block_until_ready()  # traced now, under this setting
    finally:
        S.light_visible_fractions, S.environment_visible_fraction = light, env
    return fns


def bench(path: str, changes: dict, runs: int) -> dict:
    base = build_scene(load_config(path))
    scene = dataclasses.replace(
        base,
        method=dataclasses.replace(
            base.method, light_visibility="images", **{"environment_lights": 0, **changes}
        ),
    )
    t0 = time.perf_counter()
    fns = _frame_fns(scene)
    compile_s = time.perf_counter() - t0
    full, skip = fns[False](0.5), fns[True](0.5)
    diff = float(jnp.max(jnp.abs(skip - full)) / jnp.max(jnp.abs(full)))
    times = {c: [] for c in fns}
    for _ in range(runs):
        for c, f in fns.items():
            t = time.perf_counter()
            f(0.5).block_until_ready()
            times[c].append(time.perf_counter() - t)
    med = {c: 1e3 * float(np.median(v)) for c, v in times.items()}
    row = dict(
        changes=changes,
        receivers=int(full.shape[0]),
        compile_both_s=compile_s,
        all_ms=med[False],
        skipping_ms=med[True],
        ratio=med[True] / med[False],
        max_rel_diff=diff,
    )
    print(
        f"{path:30s} {row['receivers']:6d} receivers: {med[False]:7.2f} -> {med[True]:7.2f} ms "
        f"({row['ratio']:.2f}x), max rel. difference {diff:.1e}",
        flush=True,
    )
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=15)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    out = {
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "probe_start": bench_render.machine_probe(),
    }
    for path, changes in CASES:
        out[pathlib.Path(path).stem] = bench(path, changes, args.runs)
    out["probe_end"] = bench_render.machine_probe()
    print("machine probe", out["probe_start"], out["probe_end"])
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
