"""Per-vertex whole-frame gradients of the BSV gradient settings against converged ones.

``experiments/frame_grad_fd.py`` checks one directional derivative per config against finite
differences; this checks every vertex. For a shipped deforming config at its middle frame, the loss
is a weighted sum of the frame's irradiance (fixed random weights, as ``benchmarks/bench_frame_grad.py``)
and the gradient is taken with respect to per-vertex offsets (V, 3) of the rest pose. The derivative
of binary visibility is a boundary integral; both silhouette settings, ``[method] bsv_gradient =
"image"`` (Gauss nodes on every projected silhouette edge) and ``"scanline"`` (a Riemann sum over the
edge-scan's pixel columns and rows), are quadratures of it that converge as the BSV's direction grid
is refined. The reference is each setting at ``--fine`` directions per BSV point (128² by default;
their agreement with each other says how converged they are); the shipped resolution (the config's
32²) is compared with both. Reports the relative difference ``|g − g_ref| / |g_ref|``, the cosine and
the norm ratio.

Usage (repository root, project environment active)::

    python experiments/frame_grad_converged.py [--configs configs/egg_breathing.toml ...] [--fine 128]

Writes ``experiments/results/frame_grad_converged.json`` (or ``--json``) and prints a table.
"""

from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from frame_grad_fd import _scene  # the script's folder is on sys.path

from jshadow.entities import frame_time
from jshadow.scene import render_at

ROOT = pathlib.Path(__file__).resolve().parents[1]
DEFAULT = ["configs/egg_breathing.toml", "configs/airplane_bend.toml", "configs/bunny_animated.toml"]
SETTINGS = ("image", "scanline")


def vertex_gradient(path: str, gradient: str, directions: int | None) -> tuple[np.ndarray, int, float]:
    """(V, 3) gradient of the weighted frame sum, the direction resolution used, and seconds taken."""
    scene = _scene(path, gradient, directions)
    occ = scene.occluders[0]
    t = frame_time(scene.n_frames // 2, scene.n_frames)
    n_rec = scene.receivers.points.shape[0]
    weights = jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, (n_rec, 3)), scene.dtype)

    def loss(delta):
        s = eqx.tree_at(lambda s: s.occluders[0].unit_vertices, scene, occ.unit_vertices + delta)
        return jnp.sum(weights * render_at(s, t).irradiance[:n_rec])

    delta = jnp.zeros_like(occ.unit_vertices)
    start = time.perf_counter()
    loss(delta)  # a concrete rest pose once: the static slot sizes are measured on it
    g = np.asarray(jax.jit(jax.grad(loss))(delta), np.float64)
    return g, int(scene.method.directions[0]), time.perf_counter() - start


def compare(g: np.ndarray, ref: np.ndarray) -> dict:
    """Relative difference, cosine and norm ratio of ``g`` against ``ref`` (both (V, 3))."""
    nr = np.linalg.norm(ref)
    return {
        "relative_difference": float(np.linalg.norm(g - ref) / nr),
        "cosine": float(np.sum(g * ref) / (np.linalg.norm(g) * nr)),
        "norm_ratio": float(np.linalg.norm(g) / nr),
    }


def check(path: str, fine: int) -> dict:
    grads, res, secs = {}, {}, {}
    for gradient in SETTINGS:
        for label, directions in (("shipped", None), ("fine", fine)):
            key = f"{gradient}@{label}"
            grads[key], res[key], secs[key] = vertex_gradient(path, gradient, directions)
            print(f"  {path}: {key} ({res[key]}²) in {secs[key]:.0f} s", flush=True)
    row = {"config": path, "directions": res, "seconds": secs, "comparisons": {}}
    pairs = [(f"{a}@shipped", f"{b}@fine") for a in SETTINGS for b in SETTINGS]
    pairs += [("scanline@fine", "image@fine"), ("scanline@shipped", "image@shipped")]
    for a, b in pairs:
        row["comparisons"][f"{a} vs {b}"] = compare(grads[a], grads[b])
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", nargs="*", default=DEFAULT)
    ap.add_argument("--fine", type=int, default=128, help="directions per BSV point of the reference")
    ap.add_argument(
        "--json", type=pathlib.Path, default=ROOT / "experiments" / "results" / "frame_grad_converged.json"
    )
    args = ap.parse_args(argv)
    rows = []
    for c in args.configs:
        rows.append(check(c, args.fine))
        for name, v in rows[-1]["comparisons"].items():
            print(
                f"{c:32s} {name:36s} rel. difference {100 * v['relative_difference']:6.2f} %"
                f"  cosine {v['cosine']:.4f}  norm ratio {v['norm_ratio']:.3f}",
                flush=True,
            )
    out = args.json
    meta = {
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "device": str(jax.devices()[0]),
        "fine": args.fine,
    }
    out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
