"""A user's first frame gradient in a fresh process, with no render before it.

    python benchmarks/bench_first_grad.py [configs/airplane_bend.toml ...] [--runs 5]

Each config runs in its own fresh Python process (the library's size caches are per process), which
builds the scene and at once jit-compiles ``L(δ) = Σ w · irradiance`` of the middle frame, with
per-vertex offsets δ added to the first occluder's rest pose (so the rest pose is traced), and
``jax.value_and_grad(L)``: the code a user writes first. Reported: each first call (trace, compile,
run; the gradient's includes measuring the derivative's sizes) and warm medians of ``--runs``
calls. ``benchmarks/bench_frame_grad.py`` times the same loss after a render of the frame.

To time an earlier commit the same way, export its package and put it first on the path::

    git archive COMMIT jshadow | tar -x -C /tmp/base
    PYTHONPATH=/tmp/base python benchmarks/bench_first_grad.py
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys
import tempfile

DEFAULT = ["configs/egg_breathing.toml", "configs/bunny_animated.toml", "configs/airplane_bend.toml"]

_CHILD = r"""
import json, pathlib, sys, time, tomllib
import equinox as eqx, jax, jax.numpy as jnp, numpy as np
import jshadow
from jshadow.config import build_scene, config_from_dict
from jshadow.entities import frame_time
from jshadow.scene import render_at

path, runs = sys.argv[1], int(sys.argv[2])
d = tomllib.loads(pathlib.Path(path).read_text())
d.setdefault("method", {}).update(light_visibility="sh", environment_lights=0)  # the n-band light path
scene = build_scene(config_from_dict(d, source=path, root=pathlib.Path(path).resolve().parent))
occ = scene.occluders[0]
t = frame_time(scene.n_frames // 2, scene.n_frames)
n_rec = scene.receivers.points.shape[0]
w = jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, (n_rec, 3)), scene.dtype)


def loss(delta):
    s = eqx.tree_at(lambda s: s.occluders[0].unit_vertices, scene, occ.unit_vertices + delta)
    return jnp.sum(w * render_at(s, t).irradiance[:n_rec])


delta = jnp.zeros_like(occ.unit_vertices)
out = {"config": path, "package": jshadow.__file__}
for name, f in (("forward", jax.jit(loss)), ("value_and_grad", jax.jit(jax.value_and_grad(loss)))):
    t0 = time.perf_counter()
    jax.block_until_ready(f(delta))
    out[f"{name}_first_s"] = time.perf_counter() - t0
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        jax.block_until_ready(f(delta))
        times.append(time.perf_counter() - t0)
    out[f"{name}_ms"] = 1e3 * float(np.median(times))
print(json.dumps(out))
"""


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("configs", nargs="*", default=DEFAULT)
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--json", default=None, help="write the rows here")
    args = p.parse_args(argv)
    rows = []
    for cfg in args.configs:
        # run outside the checkout: `python -c` puts the working folder first on the path, ahead of
        # PYTHONPATH, and the checkout's jshadow would shadow an exported one
        cmd = [sys.executable, "-c", _CHILD, str(pathlib.Path(cfg).resolve()), str(args.runs)]
        r = subprocess.run(cmd, capture_output=True, text=True, cwd=tempfile.gettempdir())
        if r.returncode:
            raise SystemExit(f"{cfg}: {r.stderr[-2000:]}")
        row = json.loads(r.stdout.strip().splitlines()[-1])
        row["backward_over_forward"] = (row["value_and_grad_ms"] - row["forward_ms"]) / row["forward_ms"]
        rows.append(row)
        print(
            f"{cfg}: first calls forward {row['forward_first_s']:.1f} s, value_and_grad "
            f"{row['value_and_grad_first_s']:.1f} s; warm forward {row['forward_ms']:.1f} ms, "
            f"value_and_grad {row['value_and_grad_ms']:.1f} ms "
            f"(backward / forward {row['backward_over_forward']:.1f}x)  [{row['package']}]",
            flush=True,
        )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=2)


if __name__ == "__main__":
    main()
