"""Recover a sphere light's position from the shadow it makes (the fit issue, "Fitting").

Scene: ``configs/fit_light.toml`` — a rigid egg (162 vertices, bounding radius 0.8) above a 32×32
receiver plane, one sphere light (radius 0.3) and a dim constant environment. The target is the
plane radiance with the light at the config's ``target_values``; the fit starts at ``init`` and runs
Adam at the config's learning rate on :func:`jshadow.optim.relative_mse`. The light's position
enters through its SH radiance at each receiver (Zhou et al. 2005's source radiance field of a
sphere light, evaluated in closed form) and the distance mask that decides which occluders are in
front of it; both are smooth in the position, so no visibility-boundary term is needed here.

``configs/fit_light_images.toml`` is the same scene and fit with the default method and the light
shadowed through the occlusion images (``light_visibility = "images"``): its shadow is sharp, and the
position's gradient then carries the motion of the shadow's edge (the images' derivative).

Usage (repository root, project environment active)::

    python experiments/fit_light.py [--config configs/fit_light.toml] [--steps N]

Writes ``experiments/results/<config name>.json`` and ``experiments/figures/<config name>.png``
(loss curve, the three coordinates' trajectories, before/target/after shading of the plane), prints a
summary.
"""

from __future__ import annotations

import argparse
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
    ap.add_argument("--config", default=str(ROOT / "configs" / "fit_light.toml"))
    ap.add_argument("--steps", type=int, default=None)
    args = ap.parse_args()

    cfg = load_config(args.config)
    path = cfg.fit.params[0]
    steps = args.steps or cfg.fit.steps
    lr = float(cfg.fit.learning_rate)
    truth = np.asarray(cfg.fit.target_values[0], np.float64)
    init = np.asarray(cfg.fit.init[0], np.float64)

    def make_scene(p):
        return build_scene(set_param(cfg, path, p[0]))

    target_scene = make_scene([jnp.asarray(truth, jnp.float32)])
    target = plane_radiance(target_scene)
    x0 = [jnp.asarray(init, jnp.float32)]
    t0 = time.perf_counter()
    res = fit_params(make_scene, x0, target, steps=steps, optimizer=optax.adam(lr))
    wall = time.perf_counter() - t0
    final = np.asarray(res.params[0], np.float64)
    traj = np.asarray([h[0] for h in res.history] + [final.tolist()])

    def dist(x):
        return float(np.linalg.norm(x - truth))

    before = plane_radiance(make_scene(x0))
    after = plane_radiance(make_scene(res.params))
    grid = target_scene.receivers.grid_shape
    config_rel = pathlib.Path(args.config).resolve().relative_to(ROOT)
    summary = {
        "experiment": "fit_light",
        "command": f"python experiments/fit_light.py --config {config_rel}",
        "config": str(config_rel),
        "param": path,
        "init": init.tolist(),
        "target": truth.tolist(),
        "final": final.tolist(),
        "distance_initial": dist(init),
        "distance_final": dist(final),
        "relative_error": dist(final) / dist(init),  # distance to the truth / initial distance
        "loss_initial": res.loss[0],
        "loss_final": float(res.loss[-1]),
        "loss_min": float(min(res.loss)),
        "steps": steps,
        "optimizer": f"adam, learning rate {lr}",
        "wall_s": wall,
        "first_step_s": res.first_step_s,
        "ms_per_step": res.ms_per_step,
        "loss": res.loss,
        "trajectory": traj.tolist(),
        "machine": f"{platform.machine()} {platform.processor() or platform.platform()}",
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
    }
    stem = pathlib.Path(args.config).stem
    out_json = ROOT / "experiments" / "results" / f"{stem}.json"
    out_json.write_text(json.dumps(summary, indent=1) + "\n")

    imgs = [luminance_image(x, grid) for x in (before, target, after)]
    vmax = max(float(i.max()) for i in imgs)
    fig, ax = plt.subplots(1, 5, figsize=(15, 3.0))
    ax[0].semilogy(res.loss)
    ax[0].set(title="loss (relative MSE)", xlabel="step")
    for k, (name, col) in enumerate(zip("xyz", ("C0", "C1", "C2"), strict=True)):
        ax[1].plot(traj[:, k], color=col, label=name)
        ax[1].axhline(truth[k], color=col, ls="--", lw=0.8)
    ax[1].set(title=f"{path} (dashed: target)", xlabel="step")
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
        f"{stem}: {path} {np.round(init, 4).tolist()} -> {np.round(final, 4).tolist()} "
        f"(target {np.round(truth, 4).tolist()}; distance {dist(init):.3f} -> {dist(final):.4f}); "
        f"loss {res.loss[0]:.3e} -> {res.loss[-1]:.3e} in {steps} steps; wall {wall:.1f} s "
        f"(first step {res.first_step_s:.1f} s, {res.ms_per_step:.1f} ms/step)"
    )
    print(f"wrote {out_json.relative_to(ROOT)} and {out_png.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
