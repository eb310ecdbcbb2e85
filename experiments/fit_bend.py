"""Recover a bend amount from the shadow it casts (the fit issue, "Fitting"; DESIGN.md §1.6).

Scene: ``configs/fit_bend.toml`` — an egg (162 vertices) bent along y toward x under one sphere
light and a dim constant environment, a 32×32 receiver plane. The target is the plane radiance
rendered at the config's ``target_values`` (0.8); the fit starts at ``init`` (0.4, 50 % off) and
runs Adam on :func:`jshadow.optim.relative_mse` through the visibility-correct mesh BSV gradient
(the silhouette term of the deformable-shadow-fields paper's per-frame BSV resampling).
Adam runs at the config's constant learning rate (as ``jshadow fit`` does). The forward loss is a
staircase in the amount (binary visibility sampled on a finite direction grid), so near the optimum
the gradient of the smooth silhouette model and the sampled loss disagree at the level of one
direction sample; the script reports the final iterate and the iterate with the lowest loss seen.

Usage (repository root, project environment active)::

    python experiments/fit_bend.py [--config configs/fit_bend.toml] [--steps N]
        [--bsv-images auto|samples|coverage] [--directions N]

Writes ``experiments/results/<config stem>.json`` and ``experiments/figures/<config stem>.png`` (loss curve,
parameter trajectory, before/target/after shading of the plane) and prints a summary.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import pathlib
import platform
import time

import jax.numpy as jnp
import matplotlib
import numpy as np
import optax

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from jshadow.config import build_scene, load_config, set_param  # noqa: E402
from jshadow.optim import fit_params, plane_radiance  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]


def luminance_image(radiance, grid_shape):
    """(rows, cols) mean-of-RGB image of the plane radiance (rows along z, columns along x)."""
    return np.asarray(radiance).mean(-1).reshape(grid_shape)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "fit_bend.toml"))
    ap.add_argument("--steps", type=int, default=None)
    ap.add_argument(
        "--bsv-images",
        choices=("auto", "samples", "coverage"),
        default=None,
        help="replace the config's [method] bsv_images (results named <config stem>_<value>, and so on)",
    )
    ap.add_argument("--directions", type=int, default=None, help="replace [method] directions by N x N")
    args = ap.parse_args()

    cfg = load_config(args.config)
    changes = {}
    if args.bsv_images is not None:
        changes["bsv_images"] = args.bsv_images
    if args.directions is not None:
        changes["directions"] = (args.directions, args.directions)
    cfg = dataclasses.replace(cfg, method=dataclasses.replace(cfg.method, **changes))
    path = cfg.fit.params[0]
    steps = args.steps or cfg.fit.steps
    lr = float(cfg.fit.learning_rate)
    truth = float(np.asarray(cfg.fit.target_values[0]))
    init = float(np.asarray(cfg.fit.init[0]))

    def make_scene(p):
        return build_scene(set_param(cfg, path, p[0]))

    target_scene = make_scene([jnp.asarray(truth, jnp.float32)])
    target = plane_radiance(target_scene)
    t0 = time.perf_counter()
    x0 = [jnp.asarray(init, jnp.float32)]
    res = fit_params(make_scene, x0, target, steps=steps, optimizer=optax.adam(lr))
    wall = time.perf_counter() - t0
    final = float(np.asarray(res.params[0]))
    traj = [h[0] for h in res.history] + [final]
    best = float(traj[int(np.argmin(res.loss))])  # the iterate with the lowest loss seen

    before = plane_radiance(make_scene([jnp.asarray(init, jnp.float32)]))
    after = plane_radiance(make_scene(res.params))
    grid = target_scene.receivers.grid_shape
    rel = str(pathlib.Path(args.config).resolve().relative_to(ROOT))
    stem = pathlib.Path(args.config).stem  # results and figure named after the config (and changes)
    stem += "".join(f"_{v[0] if isinstance(v, tuple) else v}" for v in changes.values())
    stem += f"_{args.steps}steps" if args.steps else ""
    command = "python experiments/fit_bend.py"
    command += f" --config {rel}" if rel != "configs/fit_bend.toml" else ""
    command += (f" --steps {args.steps}" if args.steps else "") + (
        f" --bsv-images {args.bsv_images}" if args.bsv_images else ""
    )
    command += f" --directions {args.directions}" if args.directions else ""
    summary = {
        "experiment": "fit_bend",
        "command": command,
        "bsv_images": target_scene.method.bsv_images,
        "directions": list(target_scene.method.directions),
        "config": rel,
        "param": path,
        "init": init,
        "target": truth,
        "final": final,
        "relative_error": abs(final - truth) / abs(truth),
        "initial_relative_error": abs(init - truth) / abs(truth),
        "loss_initial": res.loss[0],
        "loss_final": float(res.loss[-1]),
        "loss_min": float(min(res.loss)),
        "best_loss_value": best,
        "best_loss_relative_error": abs(best - truth) / abs(truth),
        "steps": steps,
        "optimizer": f"adam, learning rate {lr}",
        "wall_s": wall,
        "first_step_s": res.first_step_s,
        "ms_per_step": res.ms_per_step,
        "retraced": res.retraced,
        "loss": res.loss,
        "trajectory": traj,
        "machine": f"{platform.machine()} {platform.processor() or platform.platform()}",
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
    }
    out_json = ROOT / "experiments" / "results" / f"{stem}.json"
    out_json.write_text(json.dumps(summary, indent=1) + "\n")

    imgs = [luminance_image(x, grid) for x in (before, target, after)]
    vmax = max(float(i.max()) for i in imgs)
    fig, ax = plt.subplots(1, 5, figsize=(15, 3.0))
    ax[0].semilogy(res.loss)
    ax[0].set(title="loss (relative MSE)", xlabel="step")
    ax[1].plot(traj, label="fit")
    ax[1].axhline(truth, color="k", ls="--", lw=0.8, label="target")
    ax[1].set(title=path, xlabel="step")
    ax[1].legend(fontsize=7)
    half = np.asarray(cfg.receiver.size, float) / 2
    c = np.asarray(cfg.receiver.center, float)
    extent = (c[0] - half[0], c[0] + half[0], c[2] - half[1], c[2] + half[1])
    for a, im, name in zip(ax[2:], imgs, ("before", "target", "after"), strict=True):
        a.imshow(im, origin="lower", extent=extent, cmap="gray", vmin=0, vmax=vmax)
        a.set(title=f"{name}: plane radiance", xlabel="x", ylabel="z")
    fig.tight_layout()
    out_png = ROOT / "experiments" / "figures" / f"{stem}.png"
    fig.savefig(out_png, dpi=70)
    print(
        f"{stem}: {path} {init:.4g} -> {final:.4f} (target {truth:.4g}, "
        f"rel. error {summary['relative_error']:.2%}; lowest-loss iterate {best:.4f}); "
        f"loss {res.loss[0]:.3e} -> {res.loss[-1]:.3e} in {steps} steps; wall {wall:.1f} s "
        f"(first step {res.first_step_s:.1f} s, {res.ms_per_step:.1f} ms/step)"
    )
    print(f"wrote {out_json.relative_to(ROOT)} and {out_png.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
