"""Full-frame gradients of shipped scenes: the backward pass against the forward pass.

Usage::

    python benchmarks/bench_frame_grad.py [--configs configs/egg_breathing.toml ...] [--runs 5]
                                          [--light-visibility sh images] [--json out.json]
                                          [--wrt vertices placement light radiance]

For each config with a deforming mesh (first occluder) at the middle frame, three jitted calls on the
same receivers:

* ``render``: the frame as ``jshadow render`` computes it (:class:`jshadow.Renderer`, no derivative
  machinery; BSV + field + combination);
* ``forward``: ``L(δ) = Σ w · irradiance`` of :func:`jshadow.scene.render_at` with per-vertex offsets δ
  (V, 3) added to the mesh's rest pose, w fixed random weights — the differentiable forward pass;
* ``value_and_grad``: ``jax.value_and_grad(L)`` at δ = 0, the visibility-correct vertex gradient
  (silhouette-edge term of the BSV, differentiable field and combination), with the silhouette
  visibility of ``[method] bsv_gradient`` (``--bsv-gradient raycast image scanline`` times each and
  reports the relative difference and cosine between their gradients; ``coverage`` times ``[method]
  bsv_images = "coverage"`` instead: the BSV projected from the coverage images, JAX's derivative).

``--light-visibility sh images`` times each setting of ``[method] light_visibility`` in the same run
(``images``: the sphere lights' visible fractions looked up in the occlusion images, and their
derivative through the coverage images; ``coverage``: the same with ``light_images = "coverage"``,
the scan lines' coverage read bilinearly, whose derivative is exact).

``--wrt`` takes the gradient with respect to other leaves instead of the vertex offsets: the first
occluder's position (``placement``), the first sphere light's position (``light``) or radiance
(``radiance``); the forward pass is the same.

``--ab-plane-first`` instead times, per config and setting, the forward and value_and_grad with the
field evaluated on the plane and on the own vertices as two calls (``render_at``'s
``plane_first=True``) against one call over all receivers, in one process, calls alternating (the
VM's speed drifts too much between runs for separate runs to compare), and checks that the two
gradients agree.

Compile time (first call minus warm median) is reported separately; warm figures are medians of
``--runs`` calls with ``block_until_ready``. "backward / forward" is (value_and_grad − forward) /
forward. float32, CPU unless JAX picks another device.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import time
import tomllib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from bench_bsv_grad import _time as _time_stats  # the script's folder is on sys.path
from bench_render import machine_probe

from jshadow.config import build_scene, config_from_dict
from jshadow.entities import MeshOccluder, frame_time
from jshadow.runner import Renderer
from jshadow.scene import render_at

ROOT = pathlib.Path(__file__).resolve().parents[1]
DEFAULT = ["configs/egg_breathing.toml", "configs/airplane_bend.toml", "configs/bunny_animated.toml"]


def _time(fn, *args, runs):
    """(compile s, warm median ms) with the timing helper of bench_bsv_grad.py."""
    t = _time_stats(fn, *args, runs=runs)
    return t["compile_s"], 1e3 * t["median_s"]


_GRADIENTS: dict = {}  # (config, bsv_gradient) -> vertex gradient, to compare the two modes


WRT = {  # what δ is added to: the leaf of the scene the gradient is taken with respect to
    "vertices": lambda s: s.occluders[0].unit_vertices,  # per-vertex offsets of the rest pose (V, 3)
    "placement": lambda s: s.occluders[0].center,  # the first occluder's position (3,)
    "light": lambda s: s.lights[0].center,  # the first sphere light's position (3,)
    "radiance": lambda s: s.lights[0].radiance,  # its radiance (3,)
}


def frame_loss(scene, t, wrt: str = "vertices"):
    """``L(δ) = Σ w · irradiance`` of :func:`jshadow.scene.render_at` at time t, with δ added to the
    leaf ``WRT[wrt]`` of the scene (by default per-vertex offsets (V, 3) of the first occluder's rest
    pose) and fixed random weights w (seed 0)."""
    n_rec = scene.receivers.points.shape[0]
    weights = jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, (n_rec, 3)), scene.dtype)
    where = WRT[wrt]

    def loss(delta):
        s = eqx.tree_at(where, scene, where(scene) + delta)
        return jnp.sum(weights * render_at(s, t).irradiance[:n_rec])

    return loss


def _scene(path: str, bsv_gradient: str, light_visibility: str = "sh"):
    """The config's scene with ``[method] bsv_gradient`` and ``light_visibility`` set."""
    d = tomllib.loads((ROOT / path).read_text())
    if bsv_gradient == "coverage":  # the BSV projected from coverage images: JAX's own derivative
        d.setdefault("method", {})["bsv_images"] = "coverage"
    else:  # the samples' BSV (also where a fit config's "auto" would pick the coverage)
        d.setdefault("method", {}).update(bsv_gradient=bsv_gradient, bsv_images="samples")
    # "coverage": the images' lookups reading the scan lines' coverage (light_images = "coverage")
    d["method"]["light_visibility"] = "images" if light_visibility == "coverage" else light_visibility
    if light_visibility == "coverage":
        d["method"]["light_images"] = "coverage"
    return build_scene(config_from_dict(d, source=path, root=(ROOT / path).parent))


def bench(
    path: str, runs: int, bsv_gradient: str = "raycast", light_visibility: str = "sh", wrt: str = "vertices"
) -> dict | None:
    scene = _scene(path, bsv_gradient, light_visibility)
    occ = scene.occluders[0]
    if not isinstance(occ, MeshOccluder):
        raise SystemExit(f"{path}: the first occluder is not a mesh")
    if wrt in ("light", "radiance") and not scene.lights:
        print(f"{path}: no sphere light, no gradient with respect to its {wrt}", flush=True)
        return None
    frame = scene.n_frames // 2
    t = frame_time(frame, scene.n_frames)
    rend = Renderer(scene, progress=False)
    rend.frame(frame)
    render_ms = float(np.median([rend.frame(frame)[1]["total_ms"] for _ in range(runs)]))

    n_rec = scene.receivers.points.shape[0]
    loss = frame_loss(scene, t, wrt)
    delta = jnp.zeros_like(WRT[wrt](scene))
    frame_loss(scene, t)(jnp.zeros_like(occ.unit_vertices))  # concrete: the BSV's slot sizes measured
    c_f, fwd_ms = _time(jax.jit(loss), delta, runs=runs)
    vag = jax.jit(jax.value_and_grad(loss))
    c_g, vag_ms = _time(vag, delta, runs=runs)
    g = np.asarray(vag(delta)[1])
    row = {
        "config": path,
        "bsv_gradient": bsv_gradient,
        "light_visibility": light_visibility,
        "wrt": wrt,
        "frame": frame,
        "vertices": int(occ.unit_vertices.shape[0]),
        "faces": int(occ.faces.shape[0]),
        "receivers": int(n_rec),
        "render_ms": render_ms,
        "forward_ms": fwd_ms,
        "value_and_grad_ms": vag_ms,
        "backward_over_forward": (vag_ms - fwd_ms) / fwd_ms,
        "value_and_grad_over_render": vag_ms / render_ms,
        "compile_forward_s": c_f,
        "compile_value_and_grad_s": c_g,
        "gradient_finite": bool(np.all(np.isfinite(g))),
        "gradient_norm": float(np.linalg.norm(g)),
    }
    if wrt == "vertices":
        _GRADIENTS[(path, bsv_gradient, light_visibility)] = g
    print(
        f"{path:32s} {bsv_gradient:8s} {light_visibility:6s} {wrt:9s} V={row['vertices']:5d} rec={n_rec:6d}"
        f"  render {render_ms:7.1f} ms"
        f"  forward {fwd_ms:7.1f} ms"
        f"  value_and_grad {vag_ms:8.1f} ms  backward/forward {row['backward_over_forward']:5.2f}"
        f"  compile {c_f:4.1f} / {c_g:4.1f} s",
        flush=True,
    )
    return row


def ab_plane_first(path: str, runs: int, bsv_gradient: str) -> dict:
    """Forward and value_and_grad with ``occluder_visibilities(..., plane_first=True)`` (the default
    of ``render_at``) against ``False``, alternating calls in this process (module docstring)."""
    import jshadow.scene as sc

    scene = _scene(path, bsv_gradient)
    t = frame_time(scene.n_frames // 2, scene.n_frames)
    delta = jnp.zeros_like(scene.occluders[0].unit_vertices)
    original = sc.occluder_visibilities
    calls = {}
    try:
        for split in (True, False):
            sc.occluder_visibilities = lambda *a, _s=split, **k: original(*a, **{**k, "plane_first": _s})
            loss = frame_loss(scene, t)
            loss(delta)  # concrete rest pose first: the BSV's slot sizes
            calls[split] = (jax.jit(loss), jax.jit(jax.value_and_grad(loss)))
            for f in calls[split]:
                jax.block_until_ready(f(delta))  # compiled now, while the patch is in place
    finally:
        sc.occluder_visibilities = original
    grads = {k: np.asarray(v[1](delta)[1]) for k, v in calls.items()}
    times = {(k, i): [] for k in calls for i in (0, 1)}
    for _ in range(runs):
        for k, fns in calls.items():
            for i, f in enumerate(fns):
                t0 = time.perf_counter()
                jax.block_until_ready(f(delta))
                times[(k, i)].append(1e3 * (time.perf_counter() - t0))
    med = {k: float(np.median(v)) for k, v in times.items()}
    row = {
        "config": path,
        "bsv_gradient": bsv_gradient,
        "forward_ms": {"plane_first": med[(True, 0)], "one_call": med[(False, 0)]},
        "value_and_grad_ms": {"plane_first": med[(True, 1)], "one_call": med[(False, 1)]},
        "value_and_grad_ratio": med[(True, 1)] / med[(False, 1)],
        "gradient_relative_difference": float(
            np.linalg.norm(grads[True] - grads[False]) / np.linalg.norm(grads[False])
        ),
    }
    print(
        f"{path:32s} {bsv_gradient:8s} forward {med[(True, 0)]:6.1f} / {med[(False, 0)]:6.1f} ms"
        f"  value_and_grad {med[(True, 1)]:7.1f} / {med[(False, 1)]:7.1f} ms (plane first / one call,"
        f" ratio {row['value_and_grad_ratio']:.3f})"
        f"  gradients differ by {row['gradient_relative_difference']:.1e}",
        flush=True,
    )
    return row


def _compare_gradients(configs, rows) -> None:
    """Each timed gradient against the ray-cast one (and "scanline" against "image"), same loss and
    pose: relative difference, cosine and norm ratio, printed and added to the rows."""
    pairs = [("image", "raycast"), ("scanline", "raycast"), ("scanline", "image")]
    for c, mine, other, lv in ((c, m, o, lv) for c in configs for m, o in pairs for lv in ("sh", "images")):
        if (c, mine, lv) not in _GRADIENTS or (c, other, lv) not in _GRADIENTS:
            continue
        a, b = _GRADIENTS[(c, mine, lv)].ravel(), _GRADIENTS[(c, other, lv)].ravel()
        cmp = {
            "relative_difference": float(np.linalg.norm(a - b) / np.linalg.norm(b)),
            "cosine": float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b))),
            "norm_ratio": float(np.linalg.norm(a) / np.linalg.norm(b)),
        }
        for r in rows:
            if r["config"] == c and r["bsv_gradient"] == mine and r["light_visibility"] == lv:
                r[f"against_{other}"] = cmp
        print(f"{c:32s} {mine} vs {other} ({lv}): " + "  ".join(f"{k} {v:.4f}" for k, v in cmp.items()))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", nargs="*", default=DEFAULT)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--json", type=pathlib.Path)
    ap.add_argument(
        "--bsv-gradient",
        nargs="*",
        default=["image", "raycast"],
        choices=["raycast", "image", "scanline", "coverage"],
        help="[method] bsv_gradient settings to time (same run; 'auto' is 'image' for these configs); "
        "'coverage': bsv_images = 'coverage' instead (the BSV from the coverage images, JAX's derivative)",
    )
    ap.add_argument(
        "--light-visibility",
        nargs="*",
        default=["sh"],
        choices=["sh", "images", "coverage"],
        help="[method] light_visibility settings to time (same run; 'images' differentiates the lookups, "
        "'coverage' is 'images' with light_images = 'coverage')",
    )
    ap.add_argument(
        "--wrt",
        nargs="*",
        default=["vertices"],
        choices=list(WRT),
        help="the gradient's argument: per-vertex offsets, the occluder's position, the first sphere "
        "light's position or its radiance (same run)",
    )
    ap.add_argument("--ab-plane-first", action="store_true", help="time plane_first=True against False")
    args = ap.parse_args(argv)
    load = os.getloadavg()[0]
    if args.ab_plane_first:
        rows = [ab_plane_first(c, args.runs, g) for c in args.configs for g in args.bsv_gradient]
    else:
        rows = [
            bench(c, args.runs, g, lv, w)
            for c in args.configs
            for g in args.bsv_gradient
            for lv in args.light_visibility
            for w in args.wrt
        ]
        rows = [r for r in rows if r is not None]
        _compare_gradients(args.configs, rows)
    meta = {
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "device": str(jax.devices()[0]),
        "load_average_1min": [load, os.getloadavg()[0]],
        "runs": args.runs,
        "machine_probe": machine_probe(),
    }
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
