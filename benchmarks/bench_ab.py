"""Shading time of the working tree against an earlier commit, in one process, calls alternating.

    python benchmarks/bench_ab.py --base 0aecdf5 --calls 300 configs/airplane_bend.toml ... spheres:16

This VM's speed drifts by up to 2.5x between days and by +-40 % within minutes, so figures from
different runs (or from two processes run one after the other) do not compare. Here the package at
``--base`` is exported (``git archive``) into a temporary folder under another name (jshadow's
imports are relative, so it runs as ``jshadow_base``) and both versions' one-call shading
(``Renderer._shade_once``, or ``runner._place_and_shade`` before it existed; BSVs done, the
renderer's own arguments) are called in turn
``--calls`` times each; the ratio of medians is the figure to quote. Shading only: the BSV stage is
not timed.
"""

from __future__ import annotations

import argparse
import importlib
import io
import pathlib
import subprocess
import sys
import tarfile
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]


def export_base(commit: str, folder: pathlib.Path) -> None:
    """The ``jshadow`` package at ``commit`` as ``folder/jshadow_base``."""
    cmd = ["git", "archive", commit, "jshadow"]
    tar = subprocess.run(cmd, cwd=ROOT, check=True, capture_output=True).stdout
    with tarfile.open(fileobj=io.BytesIO(tar)) as tf:
        tf.extractall(folder, filter="data")
    (folder / "jshadow").rename(folder / "jshadow_base")


def shading_call(pkg: str, cfg: str):
    """A zero-argument function running one frame's shading of ``cfg`` with package ``pkg``;
    ``cfg = "spheres:K"`` is ``bench_render.many_spheres`` (the spheres through the BSV path),
    ``"spheres:K:F"`` the same with the last F of them beyond every receiver's range."""
    js = importlib.import_module(pkg)
    runner = importlib.import_module(f"{pkg}.runner")
    if cfg.startswith("spheres:"):
        k, far = (int(x) for x in (cfg.split(":")[1:] + ["0"])[:2])
        from bench_render import many_spheres  # the same scene, built from package pkg

        scene = many_spheres(k, far=far, ent=importlib.import_module(f"{pkg}.entities"))
        r = runner.Renderer(scene, sphere_path="bsv")
    else:
        scene = js.build_scene(js.load_config(cfg))
        r = runner.Renderer(scene)
    r.frame(0)
    bsvs = jax.block_until_ready(r._bsvs(0.3))
    t = jnp.asarray(0.3, scene.receivers.points.dtype)
    args = (scene, bsvs, t, r._lighting, True, r._shared_normal)

    def call():
        if hasattr(r, "_shade_once"):  # the renderer's own one-call shading (since 2026-12-03)
            return jax.block_until_ready(r._shade_once(bsvs, t))
        return jax.block_until_ready(runner._place_and_shade(*args))

    call()
    return call


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "configs",
        nargs="+",
        help="config files, or spheres:K[:F] (K sphere occluders, BSV path, F of them far away)",
    )
    ap.add_argument("--base", required=True, help="the commit to compare the working tree with")
    ap.add_argument("--calls", type=int, default=300)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        export_base(args.base, pathlib.Path(tmp))
        sys.path.insert(0, tmp)
        sys.path.insert(0, str(ROOT))
        for cfg in args.configs:
            calls = {"base": shading_call("jshadow_base", cfg), "tree": shading_call("jshadow", cfg)}
            times = {k: [] for k in calls}
            for _ in range(args.calls):
                for k, f in calls.items():
                    t = time.perf_counter()
                    f()
                    times[k].append(time.perf_counter() - t)
            med = {k: float(np.median(v)) for k, v in times.items()}
            low = {k: min(v) for k, v in times.items()}
            row = "  ".join(f"{k}: fastest {1e3 * low[k]:.3f} median {1e3 * med[k]:.3f} ms" for k in calls)
            print(f"{cfg:<30} {row}  tree/base median {med['tree'] / med['base']:.2f}")


if __name__ == "__main__":
    main()
