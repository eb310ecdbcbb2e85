"""The bend fit's loss and gradient along the bend amount, for the samples' and the coverage BSV.

Why the bend fit of ``configs/fit_bend_coverage.toml`` reaches its target with the coverage BSV and
stalls with the samples' (BENCHMARKS.md, "Fitting"): this evaluates, on a grid of bend amounts, the
loss the fit minimises (relative MSE of the plane radiance against the target rendered at 0.8 by
the same method) and the gradient the fit follows, both from the jitted ``value_and_grad`` that
:func:`jshadow.optim.fit_params` runs (sizes grown with :func:`jshadow.scene.grow_slots` where a
traced pose overflows them), and compares the gradient with central differences of the loss curve.

Usage (repository root, project environment active)::

    python experiments/fit_bend_landscape.py [--config configs/fit_bend_coverage.toml]
        [--directions N] [--points 141]

Writes ``experiments/results/fit_bend_landscape[_N].json`` and
``experiments/figures/fit_bend_landscape[_N].png``.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import pathlib
import platform

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from jshadow.config import build_scene, load_config, set_param  # noqa: E402
from jshadow.optim import jit_growing, plane_radiance, relative_mse  # noqa: E402
from jshadow.scene import grow_slots  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]


def landscape(cfg, path: str, truth: float, amounts: np.ndarray) -> dict:
    """Loss and its derivative at each amount, as the fit computes them (jitted value_and_grad)."""

    def make_scene(a):
        return build_scene(set_param(cfg, path, a))

    target = plane_radiance(make_scene(jnp.float32(truth)))

    def loss(a):
        return relative_mse(plane_radiance(make_scene(a)), target)

    vag = jit_growing(jax.value_and_grad(loss), lambda a: grow_slots(make_scene(a)))
    values, grads = [], []
    for a in amounts:
        v, g = vag(jnp.float32(a))
        values.append(float(v))
        grads.append(float(g))
    values, grads = np.asarray(values), np.asarray(grads)
    h = amounts[1] - amounts[0]
    fd = (values[2:] - values[:-2]) / (2 * h)  # central differences of the loss curve
    g_mid = grads[1:-1]
    # the derivative's sign against the sign of the loss curve's differences, where they are clear
    clear = np.abs(fd) > 0.05 * np.abs(fd).max()
    return {
        "bsv_images": make_scene(jnp.float32(truth)).method.bsv_images,
        "loss": values.tolist(),
        "gradient": grads.tolist(),
        "central_differences": fd.tolist(),
        "sign_agreement": float(np.mean(np.sign(fd[clear]) == np.sign(g_mid[clear]))),
        "gradient_vs_differences_relative_rms": float(
            np.sqrt(np.mean((g_mid - fd) ** 2)) / np.sqrt(np.mean(fd**2))
        ),
        "loss_local_minima": int(np.sum((values[1:-1] < values[:-2]) & (values[1:-1] < values[2:]))),
        "size_growths": vag.retraces,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "fit_bend_coverage.toml"))
    ap.add_argument("--directions", type=int, default=None, help="replace [method] directions by N x N")
    ap.add_argument("--points", type=int, default=141, help="bend amounts from 0.3 to 1.0")
    args = ap.parse_args()

    cfg = load_config(args.config)
    if args.directions is not None:
        n = args.directions
        cfg = dataclasses.replace(cfg, method=dataclasses.replace(cfg.method, directions=(n, n)))
    path = cfg.fit.params[0]
    truth = float(np.asarray(cfg.fit.target_values[0]))
    amounts = np.linspace(0.3, 1.0, args.points)
    rows = {}
    for images in ("samples", "coverage"):
        c = dataclasses.replace(cfg, method=dataclasses.replace(cfg.method, bsv_images=images))
        rows[images] = landscape(c, path, truth, amounts)
        r = rows[images]
        print(
            f"{images:8s}: loss local minima {r['loss_local_minima']}, gradient sign = differences' sign "
            f"{r['sign_agreement']:.0%}, gradient vs differences rel. RMS "
            f"{r['gradient_vs_differences_relative_rms']:.2f}, size growths {r['size_growths']}",
            flush=True,
        )
    suffix = "" if args.directions is None else f"_{args.directions}"
    summary = {
        "experiment": "fit_bend_landscape",
        "command": "python experiments/fit_bend_landscape.py"
        + (f" --directions {args.directions}" if args.directions else "")
        + (f" --points {args.points}" if args.points != 141 else ""),
        "config": str(pathlib.Path(args.config).resolve().relative_to(ROOT)),
        "directions": list(build_scene(cfg).method.directions),
        "param": path,
        "target": truth,
        "amounts": amounts.tolist(),
        "rows": rows,
        "machine": f"{platform.machine()} {platform.processor() or platform.platform()}",
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
    }
    out_json = ROOT / "experiments" / "results" / f"fit_bend_landscape{suffix}.json"
    out_json.write_text(json.dumps(summary, indent=1) + "\n")

    fig, ax = plt.subplots(1, 2, figsize=(11, 3.6))
    mid = amounts[1:-1]
    for images, color in (("samples", "C3"), ("coverage", "C0")):
        r = rows[images]
        ax[0].semilogy(amounts, np.maximum(r["loss"], 1e-16), color=color, label=f"{images} BSV")
        ax[1].plot(amounts, r["gradient"], color=color, label=f"{images}: gradient")
        ax[1].plot(mid, r["central_differences"], color=color, ls=":", label=f"{images}: differences")
    for a in ax:
        a.axvline(truth, color="k", ls="--", lw=0.8)
        a.set_xlabel(path)
    ax[0].set(title=f"loss (relative MSE), {build_scene(cfg).method.directions[0]}² directions")
    ax[1].set(title="d loss / d amount")
    ax[1].axhline(0.0, color="k", lw=0.5)
    ax[0].legend(fontsize=7)
    ax[1].legend(fontsize=7)
    fig.tight_layout()
    out_png = ROOT / "experiments" / "figures" / f"fit_bend_landscape{suffix}.png"
    fig.savefig(out_png, dpi=80)
    print(f"wrote {out_json.relative_to(ROOT)} and {out_png.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
