"""Equal-error comparison with Mitsuba 3: the time its Monte Carlo needs to reach jshadow's error.

Scenes: those of ``experiments/pareto.py`` (constant environment L = 1, a 32² receiver plane at
y = 0 over [−2, 2]², one occluder: sphere, bunny or spot), whose exact irradiance is cached in
``experiments/results/pareto_ref_<scene>_32.npz`` (run pareto.py first).

Mitsuba computes the same per-receiver irradiance ``E = ∫ L V max(0, n·ω) dω``: every receiver is a
tiny disk (radius 1e-4, normal +y) carrying an ``irradiancemeter`` sensor (cosine-weighted rays
from the disk), rendered with the ``path`` integrator at ``max_depth = 1`` (only directly visible
emitters: the environment where a ray escapes, nothing where it hits the occluder), one
``mi.render(scene, sensor=i, spp=s)`` per receiver. The occluder is the same triangle mesh
(written to a temporary PLY, already normalised and placed) or Mitsuba's analytic sphere. Variant
``scalar_rgb`` (C++, no JIT; the ``llvm_ad_rgb`` variant needs LLVM ≥ 16 and this machine has
libLLVM 14/15: the script records what happens when it is tried, in a subprocess).

For spp = 1, 2, 4, … ``--max-spp`` the relative RMSE against the exact irradiance and the wall time
of all receivers (warm median of ``--runs``; scene loading reported separately, a deforming mesh
would pay it every frame) are measured; the equal-error spp is the smallest one whose error is at
or below jshadow's. jshadow's times are re-measured in the same run (same configurations as
pareto.py: BSV + field + combination per frame, warm median). Compared configurations (4 bands,
32², 12×20): the library's default family and the paper's method (``pareto.family``), and the
most accurate point of the scene's Pareto front in ``pareto.json``.

Usage (repository root, project environment active, ``pip install -e .[mitsuba]``)::

    python experiments/mitsuba_compare.py [--scenes sphere bunny spot] [--max-spp 16384]

Writes ``experiments/results/mitsuba_compare.json``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time

import numpy as np
import pareto
import trimesh
from _common import RESULTS, machine

try:
    import mitsuba as mi
except ImportError:
    raise SystemExit("mitsuba_compare.py needs Mitsuba 3: pip install -e .[mitsuba]") from None

mi.set_variant("scalar_rgb")
T = mi.ScalarTransform4f

LLVM_PROBE = """
import mitsuba as mi, numpy as np
mi.set_variant("llvm_ad_rgb")
s = mi.load_dict({"type": "scene", "m": {"type": "ply", "filename": %r}})
d = np.random.default_rng(0).normal(size=(3, 1024)).astype(np.float32)
print(int(mi.Bool(s.ray_test(mi.Ray3f(mi.Point3f(0, 0, 0), mi.Vector3f(d[0], d[1], d[2])))).__len__()))
"""


def meter(p, i: int) -> dict:
    """A 1e-4 disk at p facing +y with an irradiance meter (a distinct sampler seed per meter)."""
    to_world = (
        T().translate([float(p[0]), float(p[1]), float(p[2])]) @ T().rotate([1, 0, 0], -90) @ T().scale(1e-4)
    )
    film = {"type": "hdrfilm", "width": 1, "height": 1, "rfilter": {"type": "box"}, "pixel_format": "rgb"}
    sensor = {"type": "irradiancemeter", "sampler": {"type": "independent", "seed": i}, "film": film}
    return {"type": "disk", "to_world": to_world, "sensor": sensor}


def mitsuba_scene(name: str, scene, tmp: str) -> tuple[dict, str | None]:
    occ = scene.occluders[0]
    d: dict = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 1},
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
    }
    ply = None
    if name == "sphere":
        d["occ"] = {"type": "sphere", "center": np.asarray(occ.center).tolist(), "radius": float(occ.radius)}
    else:
        ply = f"{tmp}/{name}.ply"
        trimesh.Trimesh(np.asarray(occ.vertices(0.0)), np.asarray(occ.faces), process=False).export(ply)
        d["occ"] = {"type": "ply", "filename": ply}
    for i, p in enumerate(np.asarray(scene.receivers.points)):
        d[f"meter{i:05d}"] = meter(p, i)
    return d, ply


def render_all(msc, n: int, spp: int, seed: int) -> np.ndarray:
    return np.array([np.array(mi.render(msc, sensor=i, spp=spp, seed=seed))[0, 0, 0] for i in range(n)])


def llvm_probe(ply: str) -> dict:
    r = subprocess.run(
        [sys.executable, "-c", LLVM_PROBE % ply], capture_output=True, text=True, timeout=120, check=False
    )
    err = [line for line in r.stderr.splitlines() if "ERROR" in line or "Error" in line]
    return {
        "returncode": r.returncode,
        "first_error_line": err[0][:200] if err else None,
        "works": r.returncode == 0,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="*", default=["sphere", "bunny", "spot"])
    ap.add_argument("--max-spp", type=int, default=16384)
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    info = machine()
    info["mitsuba"] = mi.__version__
    info["mitsuba_variant"] = "scalar_rgb"
    par = json.loads((RESULTS / "pareto.json").read_text())["scenes"]
    out: dict = {"settings": vars(args), "machine": info, "scenes": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.scenes:
            ref = np.load(RESULTS / f"pareto_ref_{name}_32.npz")["exact"]
            front = par[name]["pareto_front"]
            best = min(front, key=lambda r: r["rel_rmse"])
            cfgs = {
                "default": {**pareto.DEFAULT, **pareto.family("default", 4)},
                "paper": {**pareto.DEFAULT, **pareto.family("paper", 4)},
                "most_accurate_front": {
                    k: v for k, v in best.items() if k not in ("rel_rmse", "frame_ms", "family")
                },
            }
            js = {}
            for label, m in cfgs.items():
                scene = pareto.build(name, 32, m)
                irr, ms = pareto.time_config(scene, "bsv" if name == "sphere" else "analytic", args.runs)
                js[label] = {"method": m, "rel_rmse": pareto.rel_rmse(irr, ref), "frame_ms": ms["total_ms"]}
            scene = pareto.build(name, 32, {})
            t0 = time.perf_counter()
            d, ply = mitsuba_scene(name, scene, tmp)
            msc = mi.load_dict(d)
            load_s = time.perf_counter() - t0
            n = int(scene.receivers.points.shape[0])
            sweep, spp = [], 1
            while spp <= args.max_spp:
                ts, errs = [], []
                for run in range(args.runs if spp <= 1024 else 1):
                    t0 = time.perf_counter()
                    e = render_all(msc, n, spp, seed=run)
                    ts.append(time.perf_counter() - t0)
                    errs.append(pareto.rel_rmse(e, ref))
                sweep.append({"spp": spp, "rel_rmse": float(np.mean(errs)), "seconds": float(np.median(ts))})
                e, sec = sweep[-1]["rel_rmse"], sweep[-1]["seconds"]
                print(f"{name:>6} mitsuba {spp:6d} spp: {100 * e:6.2f} %  {sec:.3f} s", flush=True)
                if sweep[-1]["rel_rmse"] < 0.5 * min(v["rel_rmse"] for v in js.values()):
                    break
                spp *= 2
            for label, v in js.items():
                hit = next((s for s in sweep if s["rel_rmse"] <= v["rel_rmse"]), None)
                v["mitsuba_equal_error"] = hit
                v["time_ratio_mitsuba_over_jshadow"] = hit["seconds"] * 1e3 / v["frame_ms"] if hit else None
                print(
                    f"{name:>6} {label:>20}: jshadow {100 * v['rel_rmse']:.2f} % in {v['frame_ms']:.1f} ms; "
                    + (
                        f"Mitsuba {hit['spp']} spp {hit['seconds'] * 1e3:.0f} ms "
                        f"({v['time_ratio_mitsuba_over_jshadow']:.2g}x)"
                        if hit
                        else "Mitsuba did not reach it"
                    ),
                    flush=True,
                )
            probe = llvm_probe(ply) if ply and "llvm_probe" not in out else None
            if probe:
                out["llvm_probe"] = probe
            out["scenes"][name] = {
                "jshadow": js,
                "mitsuba_sweep": sweep,
                "mitsuba_scene_load_s": load_s,
                "receivers": n,
            }
    info["load_avg_after"] = machine()["load_avg_1_5_15"]
    (RESULTS / "mitsuba_compare.json").write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
