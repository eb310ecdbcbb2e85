"""Lamp lookups with and without the regions' penumbrae, on a deforming config's last pose.

    python benchmarks/bench_lamp_penumbra.py [--config configs/bunny_animated.toml]
        [--resolutions 128 192] [--runs 15] [--json out.json]

The config's default lamps (``environment_lights = "auto"``, split as the renderer splits its map)
are imaged at each resolution (entry faces, as the renderer makes them); the plane's receivers
(the shipped size, 160² for the animated bunny) look every lamp up with
:func:`jshadow.visibility.lamp_visibility`: plain (bilinear, ``spread`` None) and widened to each
region's penumbra (``spread``, the default since the "Lamp penumbrae" entry of BENCHMARKS.md).
Each lookup is one jitted call: its first call (trace and compile) is reported apart, then the
median of ``--runs`` warm calls, alternating; the images' own time (median of 5) is reported too.
The error each buys is measured by ``experiments/defaults.py``.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import jax
import numpy as np

from jshadow.config import build_scene, load_config
from jshadow.entities import frame_time
from jshadow.scene import _vertices_at, scene_lighting
from jshadow.visibility import lamp_images, lamp_visibility

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _median_ms(fn, runs: int) -> float:
    out = []
    for _ in range(runs):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        out.append(1e3 * (time.perf_counter() - t0))
    return float(np.median(out))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "bunny_animated.toml"))
    ap.add_argument("--resolutions", type=int, nargs="+", default=[128, 192])
    ap.add_argument("--runs", type=int, default=15)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    scene = build_scene(load_config(args.config))
    lights = scene_lighting(scene).env_lights
    if lights is None:
        raise SystemExit(f"{args.config}: no environment lights to look up")
    occ = scene.occluders[0]
    last = max(scene.n_frames - 1, 0)
    v = np.asarray(_vertices_at(occ, frame_time(last, scene.n_frames)))
    f = np.asarray(occ.faces)
    d = np.asarray(lights.directions, v.dtype)
    pts = scene.receivers.points
    spread = lights.spread
    plain = jax.jit(lambda img, p: lamp_visibility(img, p))
    wide = jax.jit(lambda img, p, s: lamp_visibility(img, p, spread=s))
    out = {
        "config": args.config,
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "receivers": int(pts.shape[0]),
        "lamps": int(d.shape[0]),
        "rows": [],
    }
    for res in args.resolutions:
        img = jax.block_until_ready(lamp_images(v, f, d, res, entry_only=True))
        images_ms = _median_ms(lambda res=res: lamp_images(v, f, d, res, entry_only=True).front, 5)
        t0 = time.perf_counter()
        jax.block_until_ready(plain(img, pts))
        first_plain = time.perf_counter() - t0
        t0 = time.perf_counter()
        jax.block_until_ready(wide(img, pts, spread))
        first_wide = time.perf_counter() - t0
        a, b = [], []
        for _ in range(args.runs):
            a.append(_median_ms(lambda img=img: plain(img, pts), 1))
            b.append(_median_ms(lambda img=img: wide(img, pts, spread), 1))
        row = {
            "resolution": res,
            "images_ms": images_ms,
            "plain_first_s": first_plain,
            "penumbra_first_s": first_wide,
            "plain_ms": float(np.median(a)),
            "penumbra_ms": float(np.median(b)),
        }
        row["ratio"] = row["penumbra_ms"] / row["plain_ms"]
        out["rows"].append(row)
        print(
            f"{res}²: images {images_ms:6.1f} ms | lookups plain {row['plain_ms']:6.1f} ms, "
            f"penumbra {row['penumbra_ms']:6.1f} ms ({row['ratio']:.1f}x) | first calls "
            f"{first_plain:.1f} / {first_wide:.1f} s  ({pts.shape[0]} receivers x {d.shape[0]} lamps)",
            flush=True,
        )
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
