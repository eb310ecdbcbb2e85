"""Render-time benchmark: ms per frame, BSV / shading, and the shading split into field / combination.

Usage::

    python benchmarks/bench_render.py [--frames 12] [--json out.json]
        [--methods default n-band paper paper-shell1.5]

(The figures recorded before 2026-12-06's ``light_visibility = "auto"`` were of the n-band light
path: ``--methods n-band`` reproduces them; the receiver sweep and throughput keep it.)

Rows:
* every shipped config (configs/*.toml, fit configs excluded): warm medians of the renderer's
  default (BSV, then the whole shading in one call) and of a renderer with ``split_stages=True``
  (receivers + field, combination: three calls, slower, for the split), in four alternating blocks
  of ``--frames`` frames each;
* the animated bunny (deforming every frame, 160×160 plane + self-shadowing, studio map), and its
  shading time at 80², 160² and 320² plane receivers: marginal cost per receiver and fixed cost;
* shading cost per receiver per occluder: the one-call shading time (placing the receivers, field
  evaluation, combination) / (receivers × occluders), receivers counting the plane's and, with
  self-shadowing, the occluders' vertices; for the renderer's default (read out of the field's
  table where the geometry does not move, :mod:`jshadow.readout`; how many timed frames were, or
  why not) and for the general path
  (``static_readout=False``), in the same alternating blocks;
* many occluders: 1, 4 and 16 sphere occluders through the BSV path over a 160×160 plane;
* throughput of the animated bunny with :func:`jshadow.render_frames` on one and two host threads
  (whole frames, wall time per frame including the host copies of the results).

Compile time is the first frame's time minus the warm median; warm figures are medians over the
remaining frames (block_until_ready inside the renderer).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import platform
import time
import tomllib

import jax
import jax.numpy as jnp
import numpy as np

from jshadow import entities as _entities
from jshadow.config import build_scene, config_from_dict
from jshadow.runner import Renderer, render_frames

ROOT = pathlib.Path(__file__).resolve().parents[1]

# --methods: [method] keys put over each config's own (the configs leave these to the defaults)
METHODS = {
    # shell 1.5, sphere model, n + 1 visibility bands, ratio shading; sphere lights and a lat-long
    # map's lamps through the occlusion images where they apply (light_visibility = "auto")
    "default": {},
    # the same with every light through the n-band path (the default until 2026-12-06: the
    # figures of "Latest figures" in BENCHMARKS.md, and the receiver sweep and throughput below)
    "n-band": {"light_visibility": "sh", "environment_lights": 0},
    # the paper's method (shell r: brute-force BSV; the shell given too, as a config that sets its
    # own, bunny_animated.toml's 1.5, would otherwise keep it)
    "paper": {"preset": "paper", "shell": 1.0},
    "paper-shell1.5": {"preset": "paper", "shell": 1.5},  # the paper's model on the 1.5 r shell
}


def throughput(scene, frames):
    """Wall ms per frame of ``render_frames`` over ``frames`` frames with 1 and 2 host threads
    (compilation done beforehand; the runs alternate twice and the faster of each is kept)."""
    render_frames(scene, frames=[0, 1], threads=2)  # compile
    sel = [f % scene.n_frames for f in range(frames)]
    best = {1: float("inf"), 2: float("inf")}
    for _ in range(2):
        for k in (1, 2):
            t0 = time.perf_counter()
            render_frames(scene, frames=sel, threads=k)
            best[k] = min(best[k], 1e3 * (time.perf_counter() - t0) / frames)
    return best


def run_frames(scene, frames, sphere_path="analytic", blocks=4):
    """Warm medians of :class:`Renderer`'s default (the whole shading in one call, read out of the
    field's table where the geometry does not move: :mod:`jshadow.readout`), of the general
    one-call shading (``static_readout=False``) and of the same frames with ``split_stages=True``
    (field and combination timed separately): ``blocks`` blocks of ``frames`` frames per renderer,
    alternating, frames in sequence within a block as a render loop runs them. (This VM drifts by
    ±40 % within minutes, so a single block of each gave either renderer ahead; alternating frame by
    frame slowed both: each found the caches filled by the other's buffers.)"""
    rend = Renderer(scene, sphere_path=sphere_path)
    general = Renderer(scene, sphere_path=sphere_path, static_readout=False)
    split = Renderer(scene, sphere_path=sphere_path, split_stages=True)
    t0 = time.perf_counter()
    res, first = rend.frame(0)
    first_s = time.perf_counter() - t0
    general.frame(0)
    split.frame(0)
    sel = [(i + 1) % max(scene.n_frames, 1) for i in range(frames)]
    rows, general_rows, split_rows = [], [], []
    read_before = rend.readout_frames
    for _ in range(blocks):
        rows += [rend.frame(f)[1] for f in sel]
        general_rows += [general.frame(f)[1] for f in sel]
        split_rows += [split.frame(f)[1] for f in sel]
    med = {k: float(np.median([r[k] for r in rows])) for k in rows[0]}
    return {
        "compile_s": max(first_s - med["total_ms"] / 1e3, 0.0),
        "median_ms": med,
        "readout_frames": rend.readout_frames - read_before,  # of the timed frames
        "readout_reason": rend.readout_reason,
        "general_median_ms": {k: float(np.median([r[k] for r in general_rows])) for k in general_rows[0]},
        "split_median_ms": {k: float(np.median([r[k] for r in split_rows])) for k in split_rows[0]},
        "fps": 1e3 / med["total_ms"],
        "receivers": int(res.points.shape[0]),  # plane and, with self-shadowing, occluder vertices
        "frames_timed": len(rows),
    }


def receiver_sweep(config, frames, resolutions=(80, 160, 320)):
    """The animated bunny's one-call shading time at several plane resolutions: its least-squares
    line in the receiver count splits the time into a marginal cost per receiver and a fixed cost
    per frame (dispatch, the self-shadowed vertices' small operations, per-frame tables)."""
    rows = []
    for res in resolutions:
        d = tomllib.loads(config.read_text())
        d["receiver"]["resolution"] = [res, res]
        # the n-band path with the field at the own vertices, as these figures were first taken
        # (the default now makes the vertices' "maps" every frame: BENCHMARKS.md "Self-shadowing by
        # depth images")
        d.setdefault("method", {}).update(METHODS["n-band"], self_visibility="field")
        scene = build_scene(config_from_dict(d, source=str(config), root=config.parent))
        rend = Renderer(scene)
        out, _ = rend.frame(0)
        ms = [rend.frame((i + 1) % scene.n_frames)[1]["shading_ms"] for i in range(frames)]
        rows.append(
            {"resolution": res, "receivers": int(out.points.shape[0]), "shading_ms": float(np.median(ms))}
        )
    slope, fixed = np.polyfit([r["receivers"] for r in rows], [r["shading_ms"] for r in rows], 1)
    return {"rows": rows, "marginal_us_per_receiver": 1e3 * float(slope), "fixed_ms": float(fixed)}


def plane(n, size=4.0, ent=None):
    """An n² plane of receivers (y = 0, normal +y) of ``size``, from the entities module ``ent``
    (default ``jshadow.entities``; ``bench_ab.py`` passes another package's)."""
    ent = ent or _entities
    xs = np.linspace(-size / 2, size / 2, n, dtype=np.float32)
    x, z = np.meshgrid(xs, xs)
    pts = np.stack([x.ravel(), np.zeros(x.size, np.float32), z.ravel()], -1)
    nrm = np.tile(np.float32([0, 1, 0]), (x.size, 1))
    return ent.Receivers(jnp.asarray(pts), jnp.asarray(nrm), jnp.full(3, 0.8, jnp.float32), (n, n))


def many_spheres(k, n_plane=160, far=0, ent=None):
    """k sphere occluders (radius 0.25, random positions, seed 0) over an n_plane² plane under a
    constant environment, paper method; the last ``far`` of them lifted 50 units up, beyond every
    receiver's range. ``ent``: as :func:`plane`."""
    ent = ent or _entities
    rng = np.random.default_rng(0)
    centres = [
        np.asarray(
            [*rng.uniform(-1.5, 1.5, 1), rng.uniform(0.6, 1.6), *rng.uniform(-1.5, 1.5, 1)], np.float32
        )
        for _ in range(k)
    ]
    lift = np.float32([0.0, 50.0, 0.0])
    occ = tuple(
        ent.SphereOccluder(jnp.asarray(c if i < k - far else c + lift), jnp.float32(0.25))
        for i, c in enumerate(centres)
    )
    env = ent.Environment(jnp.ones(3, jnp.float32))
    return ent.Scene(ent.Method.paper(), plane(n_plane, ent=ent), occ, (), env, n_frames=2)


def machine_probe() -> dict:
    """Speed of this machine right now, to compare runs made on different days: the fastest of 10
    NumPy passes ``2x + 1`` over 16M float32 (64 MB in, 64 MB out) and of 5 float32 2000² GEMMs.
    The VM these figures come from has run the same code 2.5x apart on different days."""
    x = np.random.default_rng(0).random(16_000_000, dtype=np.float32)
    a = x[: 2000 * 2000].reshape(2000, 2000)
    stream, gemm = [], []
    for _ in range(10):
        t = time.perf_counter()
        _ = x * 2.0 + 1.0
        stream.append(time.perf_counter() - t)
    for _ in range(5):
        t = time.perf_counter()
        _ = a @ a
        gemm.append(time.perf_counter() - t)
    return {"stream_64MB_ms": round(1e3 * min(stream), 2), "sgemm_2000_gflops": round(16.0 / min(gemm), 1)}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--json", default=None)
    ap.add_argument("--configs", nargs="*", default=None)
    ap.add_argument(
        "--methods",
        nargs="*",
        default=["default"],
        choices=sorted(METHODS),
        help="[method] settings to time each config with (same run, same frames)",
    )
    args = ap.parse_args()
    out = {
        "machine": f"{platform.processor() or platform.machine()}, {jax.devices()[0]}",
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine_probe_start": machine_probe(),
        "configs": {},
        "occluders": {},
    }
    cfgs = args.configs or sorted(str(p) for p in (ROOT / "configs").glob("*.toml") if "fit" not in p.name)
    for c in cfgs:
        for label in args.methods:
            d = tomllib.loads(pathlib.Path(c).read_text())
            d.setdefault("method", {}).update(METHODS[label])
            scene = build_scene(config_from_dict(d, source=str(c), root=pathlib.Path(c).parent))
            r = run_frames(scene, args.frames)
            n_occ = max(len(scene.occluders), 1)
            per = r["receivers"] * n_occ
            r["shading_us_per_receiver_per_occluder"] = 1e3 * r["median_ms"]["shading_ms"] / per
            r["general_shading_us_per_receiver_per_occluder"] = (
                1e3 * r["general_median_ms"]["shading_ms"] / per
            )
            name = pathlib.Path(c).name + ("" if label == "default" else f" [{label}]")
            out["configs"][name] = r
            sp = r["split_median_ms"]
            print(
                f"{name:40s} {r['receivers']:7d} rec  compile {r['compile_s']:5.1f} s  "
                + "  ".join(f"{k} {v:7.2f}" for k, v in r["median_ms"].items())
                + f"  fps {r['fps']:6.1f}  shade {r['shading_us_per_receiver_per_occluder']:.3f} µs/rec/occ"
                + f" (readout {r['readout_frames']}/{r['frames_timed']} frames"
                + ("" if r["readout_reason"] is None else f", not: {r['readout_reason']}")
                + ";"
                + f" general {r['general_median_ms']['shading_ms']:.2f} ms,"
                + f" {r['general_shading_us_per_receiver_per_occluder']:.3f} µs/rec/occ)"
                + f"  | split: field {sp['field_ms']:.2f} combine {sp['combine_ms']:.2f}"
                + f" total {sp['total_ms']:.2f}",
                flush=True,
            )
    if not args.configs or any("bunny_animated" in c for c in args.configs):
        c = ROOT / "configs" / "bunny_animated.toml"
        out["receiver_sweep"] = receiver_sweep(c, args.frames)
        sw = out["receiver_sweep"]
        print(
            "bunny_animated, plane resolution "
            + ", ".join(f"{r['resolution']}²: {r['shading_ms']:.2f} ms" for r in sw["rows"])
            + f" -> marginal shading {sw['marginal_us_per_receiver']:.3f} µs per receiver,"
            + f" fixed {sw['fixed_ms']:.2f} ms per frame",
            flush=True,
        )
        d = tomllib.loads(c.read_text())
        d.setdefault("method", {}).update(METHODS["n-band"], self_visibility="field")  # as the sweep
        scene = build_scene(config_from_dict(d, source=str(c), root=c.parent))
        out["throughput"] = throughput(scene, 2 * args.frames + 8)
        print(
            "bunny_animated throughput (render_frames): "
            + "  ".join(f"{k} thread(s) {v:6.2f} ms/frame" for k, v in out["throughput"].items()),
            flush=True,
        )
    for k in (1, 4, 16):
        r = run_frames(many_spheres(k), args.frames, sphere_path="bsv")
        out["occluders"][k] = r
        print(
            f"{k:2d} sphere occluders (BSV path), 160² receivers: "
            + "  ".join(f"{kk} {v:7.2f}" for kk, v in r["median_ms"].items())
        )
    out["machine_probe_end"] = machine_probe()
    print("machine probe (start / end):", out["machine_probe_start"], out["machine_probe_end"])
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
