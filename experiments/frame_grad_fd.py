"""Whole-frame directional derivatives of the BSV gradient settings against finite differences.

For a shipped deforming config at its middle frame: the loss is a weighted sum of the frame's
irradiance (fixed random weights), the direction a smooth random motion of the mesh's rest-pose
vertices. Central differences use a fine forward pass (``--fine`` directions per BSV point), at eight
steps (0.025 … 0.2 of the motion), and a cubic is fitted through all seventeen values: the forward's
visibility is binary, so a small step averages few pixel flips, and a large one sees the loss's
curvature; the fit's residuals give the forward's noise and the slope's standard error. The derivatives of
``[method] bsv_gradient = "raycast"``, ``"image"`` and ``"scanline"`` are taken at the config's own
resolution (32²) with ``jax.grad``; ``coverage`` is ``[method] bsv_images = "coverage"`` (the BSV
projected from the scan lines' coverage images, JAX's own derivative of that forward pass).

Usage (repository root, project environment active)::

    python experiments/frame_grad_fd.py [--configs configs/egg_breathing.toml ...] [--fine 256]
                                        [--gradients raycast image scanline]

Writes ``experiments/results/frame_grad_fd.json`` and prints a table.
"""

from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import tomllib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jshadow.config import build_scene, config_from_dict
from jshadow.entities import frame_time
from jshadow.scene import render_at

ROOT = pathlib.Path(__file__).resolve().parents[1]
DEFAULT = ["configs/egg_breathing.toml", "configs/bunny_animated.toml"]


def _scene(path: str, gradient: str, directions: int | None = None):
    d = tomllib.loads((ROOT / path).read_text())
    # the n-band light path, as a fit's default (light_visibility = "auto" keeps it for [fit] configs)
    d.setdefault("method", {}).update(light_visibility="sh", environment_lights=0)
    if gradient == "coverage":  # the BSV projected from coverage images, JAX's own derivative
        d.setdefault("method", {})["bsv_images"] = "coverage"
    else:
        d.setdefault("method", {})["bsv_gradient"] = gradient
    if directions is not None:
        d["method"]["directions"] = [directions, directions]
    return build_scene(config_from_dict(d, source=path, root=(ROOT / path).parent))


def _smooth_motion(rng, x, scale):
    """A smooth random vector field on the vertices (sum of four sinusoids), max |·| = scale."""
    d = np.zeros_like(x)
    for _ in range(4):
        d += rng.normal(size=3) * np.sin(x @ (rng.normal(size=3) * 2.0) + rng.uniform(0, 2 * np.pi))[:, None]
    return scale * d / np.abs(d).max()


STEPS = tuple(round(0.025 * k, 3) for k in range(1, 9))  # 0.025 ... 0.2


def check(path: str, fine: int, gradients, steps=STEPS) -> dict:
    base = _scene(path, "raycast")
    occ = base.occluders[0]
    t = frame_time(base.n_frames // 2, base.n_frames)
    n_rec = base.receivers.points.shape[0]
    weights = jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, (n_rec, 3)), base.dtype)
    motion = jnp.asarray(
        _smooth_motion(np.random.default_rng(3), np.asarray(occ.unit_vertices), 0.05), base.dtype
    )

    def loss_of(scene):
        def loss(a):
            s = eqx.tree_at(lambda s: s.occluders[0].unit_vertices, scene, occ.unit_vertices + a * motion)
            return jnp.sum(weights * render_at(s, t).irradiance[:n_rec])

        return loss

    fine_loss = loss_of(_scene(path, "raycast", fine))
    fine_loss(jnp.float32(0.0))  # concrete rest pose once: slot sizes are measured on it
    fine_jit = jax.jit(fine_loss)
    values = {h: (float(fine_jit(jnp.float32(h))), float(fine_jit(jnp.float32(-h)))) for h in steps}
    fd = {h: (p - m) / (2 * h) for h, (p, m) in values.items()}
    # the slope at 0 of a cubic through all 2·len(steps) + 1 values
    a = np.asarray([0.0, *steps, *(-h for h in steps)])
    y = [
        float(fine_jit(jnp.float32(0.0))),
        *(p for p, _ in values.values()),
        *(m for _, m in values.values()),
    ]
    y = np.asarray(y)
    x = np.vander(a, 4)
    coef, *_ = np.linalg.lstsq(x, y, rcond=None)
    resid = y - x @ coef
    noise = float(np.sqrt(np.sum(resid**2) / (len(y) - 4)))  # the forward's pixel-flip noise
    row = {
        "config": path,
        "fine_directions": fine,
        "loss_at": dict(zip(map(float, a), map(float, y), strict=True)),
        "finite_differences": fd,
        "cubic_fit_slope": float(coef[2]),
        "cubic_fit_slope_se": float(noise * np.sqrt(np.linalg.inv(x.T @ x)[2, 2])),
        "forward_noise": noise,
    }
    for gradient in gradients:
        loss = loss_of(_scene(path, gradient))
        loss(jnp.float32(0.0))
        row[gradient] = float(jax.jit(jax.grad(loss))(jnp.float32(0.0)))
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", nargs="*", default=DEFAULT)
    ap.add_argument("--fine", type=int, default=256)
    ap.add_argument(
        "--gradients",
        nargs="*",
        default=["raycast", "image", "scanline"],
        choices=["raycast", "image", "scanline", "coverage"],
    )
    ap.add_argument(
        "--out", default=None, help="file name in experiments/results (default frame_grad_fd.json)"
    )
    args = ap.parse_args(argv)
    rows = []
    for c in args.configs:
        r = check(c, args.fine, args.gradients)
        rows.append(r)
        fds = "  ".join(f"h={h}: {v:8.2f}" for h, v in r["finite_differences"].items())
        fds += f"  cubic fit: {r['cubic_fit_slope']:8.2f} ± {r['cubic_fit_slope_se']:.2f}"
        grads = "   ".join(f"{g} {r[g]:10.2f}" for g in args.gradients)
        print(f"{c:32s} FD ({args.fine}²) {fds}   {grads}", flush=True)
    out = ROOT / "experiments" / "results" / (args.out or "frame_grad_fd.json")
    meta = {
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "device": str(jax.devices()[0]),
    }
    out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
