"""The static meshes' own-vertex transfer cast, every face against the faces each ray group can reach.

    python benchmarks/bench_own_rays.py [--meshes bunny spot] [--runs 7] [--json out.json]

Each mesh (unit-sphere normalised) casts its shadowed transfer at its own vertices as
``self_visibility = "rays"`` does (:func:`jshadow.visibility.vertex_visibility_sh`, 12 × 48
hemisphere directions per vertex, origins lifted 10⁻³ along the normal, 4 bands): once with every
face tested for every vertex (the whole-mesh fan, :func:`jshadow.visibility.ray_fan_any_hit`, as
the cast did before), once with each vertex's fan cut into groups by azimuth sector about its
normal and each group tested against only the faces that reach above the vertex's tangent plane
and into its sectors (:func:`jshadow.visibility.hemisphere_fan_any_hit`, the cast now). The first call
of each (trace, compile and run, the whole-mesh one first) is reported apart, then the median of
``--runs`` warm calls, alternating. Both give the same coefficients, which is checked here too.
Then the own vertices' lamp rays (``jshadow.scene._lamp_rays``, 256 random lamps, the same lift):
every face under ``jit`` against the culled fans (the lamps below each vertex's plane zeroed), likewise.
Last, both at once as a static mesh with a map's lamps casts them
(:func:`jshadow.visibility.vertex_transfer_and_lamps`: each vertex's grid and lamps in one fan)
against the two culled casts apart, alternating; the values are checked equal.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

from jshadow.geometry import load_mesh, normalize_to_unit_sphere
from jshadow.scene import _lamp_rays
from jshadow.visibility import vertex_transfer_and_lamps, vertex_visibility_sh
from jshadow.visibility._own import _vertex_visibility_sh

ROOT = pathlib.Path(__file__).resolve().parents[1]
GRID = (12, 48)
LIFT = 1e-3
_UNIT = np.random.default_rng(0).normal(size=(256, 3))
LAMPS = jnp.asarray(_UNIT / np.linalg.norm(_UNIT, axis=-1, keepdims=True), jnp.float32)


def _ms(fn) -> float:
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    return 1e3 * (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--meshes", nargs="+", default=["bunny", "spot"])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    out = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "grid": GRID, "rows": []}
    for name in args.meshes:
        m = load_mesh(ROOT / "assets" / f"{name}.obj", dtype=jnp.float32)
        v, f = np.asarray(normalize_to_unit_sphere(m.vertices)), np.asarray(m.faces)

        def whole(v=v, f=f):
            return _vertex_visibility_sh(jnp.asarray(v), f, 4, GRID, True, LIFT, True)

        def culled(v=v, f=f):
            return vertex_visibility_sh(v, f, 4, GRID, offset=LIFT, transfer=True)

        first_whole, first_culled = _ms(whole), _ms(culled)
        same = bool(np.array_equal(np.asarray(whole()), np.asarray(culled())))
        a, b = [], []
        for _ in range(args.runs):
            a.append(_ms(whole))
            b.append(_ms(culled))
        row = {
            "mesh": name,
            "vertices": int(v.shape[0]),
            "faces": int(f.shape[0]),
            "whole_first_s": first_whole / 1e3,
            "culled_first_s": first_culled / 1e3,
            "whole_ms": float(np.median(a)),
            "culled_ms": float(np.median(b)),
            "identical": same,
        }
        row["speedup"] = row["whole_ms"] / row["culled_ms"]
        traced = jax.jit(lambda x, f=f: _lamp_rays(x, f, LAMPS, LIFT))

        def lamps_whole(v=v, traced=traced):
            return traced(v)

        def lamps_culled(v=v, f=f):
            return _lamp_rays(v, f, LAMPS, LIFT)

        _ms(lamps_whole), _ms(lamps_culled)
        row["lamps_identical"] = bool(np.array_equal(np.asarray(lamps_whole()), np.asarray(lamps_culled())))
        a, b = [], []
        for _ in range(args.runs):
            a.append(_ms(lamps_whole))
            b.append(_ms(lamps_culled))
        row["lamps_whole_ms"], row["lamps_culled_ms"] = float(np.median(a)), float(np.median(b))

        def apart(v=v, f=f, culled=culled, lamps_culled=lamps_culled):
            return culled(), lamps_culled()

        def joint(v=v, f=f):
            return vertex_transfer_and_lamps(v, f, 4, GRID, LIFT, LAMPS)

        _ms(joint)
        x, y = apart(), joint()
        row["joint_identical"] = all(np.array_equal(np.asarray(p), np.asarray(q)) for p, q in zip(x, y))
        a, b = [], []
        for _ in range(args.runs):
            a.append(_ms(apart))
            b.append(_ms(joint))
        row["apart_ms"], row["joint_ms"] = float(np.median(a)), float(np.median(b))
        out["rows"].append(row)
        print(
            f"{name} ({v.shape[0]} vertices, {f.shape[0]} faces): every face {row['whole_ms']:.0f} ms, "
            f"culled {row['culled_ms']:.0f} ms ({row['speedup']:.2f}x); first calls "
            f"{row['whole_first_s']:.1f} / {row['culled_first_s']:.1f} s; identical: {same}; 256 lamps: "
            f"{row['lamps_whole_ms']:.0f} / {row['lamps_culled_ms']:.0f} ms, "
            f"identical: {row['lamps_identical']}; transfer and lamps apart / in one cast: "
            f"{row['apart_ms']:.0f} / {row['joint_ms']:.0f} ms, identical: {row['joint_identical']}",
            flush=True,
        )
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
