"""BSV forward pass against its vertex derivatives (silhouette boundary term), 240 viewpoints.

Usage::

    python benchmarks/bench_bsv_grad.py [--mesh bunny_small] [--nodes 4 8] [--runs 5] [--shell 1.0]
                                        [--json out.json]

For each mesh: the brute-force BSV forward pass (``bsv_mesh(..., method="brute")``, 12×20 points,
32×32 directions, 4 bands), the forward-mode derivative (``jax.jvp`` of ``bsv_mesh_diff``: primal +
tangent) and the reverse-mode derivative (``jax.value_and_grad`` of a scalar loss of the
coefficients: primal + cotangent), each jitted; compile time (first call minus warm median) and the
median (and minimum, "best") of warm runs (``block_until_ready``). ``slots`` is 1.25 × the largest
silhouette count over the 240 viewpoints. "backward / forward" is (value_and_grad − forward) /
forward, i.e. the extra cost of the gradient, and "total / forward" the whole value_and_grad call
relative to the forward pass.
float32, whatever device JAX picks.
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

from jshadow.geometry import load_mesh
from jshadow.visibility._bsv import bsv_mesh
from jshadow.visibility._bsv_grad import _sample_points, bsv_mesh_diff, bsv_silhouette_counts

ROOT = pathlib.Path(__file__).resolve().parents[1]
GRID, DIRECTIONS, N_BANDS = (12, 20), (32, 32), 4


def _asset(name):
    p = ROOT / "assets" / f"{name}.obj"
    return p if p.exists() else pathlib.Path("/work/shared/assets") / f"{name}.obj"


def _time(fn, *args, runs):
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - t0
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    med = float(np.median(times))
    return {"compile_s": max(first - med, 0.0), "median_s": med, "min_s": float(np.min(times))}


def bench_mesh(name, nodes_list, runs, shell):
    mesh = load_mesh(_asset(name))
    x, faces = jnp.asarray(mesh.vertices, jnp.float32), np.asarray(mesh.faces)
    counts = np.asarray(bsv_silhouette_counts(x, faces, GRID, shell))
    slots = int(math.ceil(1.25 * counts.max()))
    rng = np.random.default_rng(0)
    w = jnp.asarray(rng.normal(size=(*GRID, N_BANDS**2)), jnp.float32)
    dx = jnp.asarray(rng.normal(size=x.shape), jnp.float32)

    fwd = jax.jit(lambda v: bsv_mesh(v, faces, N_BANDS, GRID, DIRECTIONS, shell, method="brute").coeffs)
    row = {
        "mesh": name,
        "V": int(x.shape[0]),
        "F": int(faces.shape[0]),
        "silhouette_mean": float(counts.mean()),
        "silhouette_max": int(counts.max()),
        "slots": slots,
        "forward": _time(fwd, x, runs=runs),
        "nodes": {},
    }
    for nodes in nodes_list:

        def f(v, nodes=nodes):
            return bsv_mesh_diff(v, faces, N_BANDS, GRID, DIRECTIONS, shell, slots=slots, nodes=nodes)

        jvp = jax.jit(lambda v, t, f=f: jax.jvp(f, (v,), (t,)))
        vag = jax.jit(jax.value_and_grad(lambda v, f=f: jnp.sum(w * f(v))))
        r = {"jvp": _time(jvp, x, dx, runs=runs), "value_and_grad": _time(vag, x, runs=runs)}
        fm = row["forward"]["median_s"]
        r["backward_over_forward"] = (r["value_and_grad"]["median_s"] - fm) / fm
        r["total_over_forward"] = r["value_and_grad"]["median_s"] / fm
        row["nodes"][nodes] = r
    return row


def accuracy(name, nodes_list, shells, views=4):
    """Relative error of the float64 tangent against the closed form of a rotation about p.

    Uses the converged reference of tests/test_bsv_grad.py (exact piecewise integration of the
    occluded region); needs only S, no finite differences (notes/visibility-gradients.md §2 (ii)).
    """
    import sys

    sys.path.insert(0, str(ROOT / "tests"))
    from test_bsv_grad import _rotation_generator, _visibility_ref

    from jshadow.visibility._bsv_grad import bsv_sh_tangent
    from jshadow.visibility._silhouette import silhouette_edges_table

    rows = []
    with jax.enable_x64(True):
        mesh = load_mesh(_asset(name), dtype=jnp.float64)
        x, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        table = silhouette_edges_table(f)
        rng = np.random.default_rng(1)
        for shell in shells:
            pts, frames = _sample_points(jnp.asarray(x), GRID, shell)
            pick = rng.choice(pts.shape[0], views, replace=False)
            for i in pick:
                p, fr = np.asarray(pts[i]), np.asarray(frames[i])
                axis = rng.normal(size=3)
                axis /= np.linalg.norm(axis)
                expected = _rotation_generator(fr.T @ axis) @ _visibility_ref(x, f, p, fr)
                for nodes in nodes_list:
                    g, count = bsv_sh_tangent(
                        x,
                        f,
                        table,
                        p[None],
                        fr[None],
                        N_BANDS,
                        400,
                        nodes,
                        np.cross(axis, x - p),
                        np.zeros((1, 3)),
                    )
                    g = np.asarray(g[0])
                    rel = float(np.linalg.norm(g - expected) / np.linalg.norm(expected))
                    cos = float(g @ expected / (np.linalg.norm(g) * np.linalg.norm(expected)))
                    rows.append({"shell": shell, "view": int(i), "nodes": nodes, "rel": rel, "cos": cos})
    for shell in shells:
        for nodes in nodes_list:
            r = [row for row in rows if row["shell"] == shell and row["nodes"] == nodes]
            rel = [row["rel"] for row in r]
            print(
                f"accuracy {name} shell={shell} nodes={nodes}: rel. err median {np.median(rel):.1e} "
                f"max {np.max(rel):.1e}, cos min {min(row['cos'] for row in r):.5f} ({len(r)} views)"
            )
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh", nargs="+", default=["bunny_small"])
    ap.add_argument("--nodes", nargs="+", type=int, default=[4, 8])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--shell", type=float, default=1.0)
    ap.add_argument("--json", type=pathlib.Path, default=None)
    ap.add_argument("--accuracy", action="store_true", help="also the rotation closed-form error (float64)")
    args = ap.parse_args()
    if args.accuracy:
        acc = {m: accuracy(m, args.nodes, [1.0, 1.5]) for m in args.mesh}
    rows = [bench_mesh(m, args.nodes, args.runs, args.shell) for m in args.mesh]
    meta = {
        "device": str(jax.devices()[0]),
        "platform": platform.platform(),
        "cpu_count": __import__("os").cpu_count(),
        "jax": jax.__version__,
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "shell": args.shell,
    }
    print(json.dumps(meta))
    for row in rows:
        f = row["forward"]
        print(
            f"{row['mesh']} V={row['V']} F={row['F']} silhouette mean/max {row['silhouette_mean']:.0f}/"
            f"{row['silhouette_max']} slots={row['slots']}: forward {f['median_s'] * 1e3:.0f} ms "
            f"(best {f['min_s'] * 1e3:.0f} ms) "
            f"(compile {f['compile_s']:.1f} s)"
        )
        for nodes, r in row["nodes"].items():
            print(
                f"  nodes={nodes}: jvp {r['jvp']['median_s'] * 1e3:.0f} ms "
                f"(compile {r['jvp']['compile_s']:.1f} s), "
                f"value_and_grad {r['value_and_grad']['median_s'] * 1e3:.0f} ms "
                f"(best {r['value_and_grad']['min_s'] * 1e3:.0f} ms) "
                f"(compile {r['value_and_grad']['compile_s']:.1f} s); backward/forward "
                f"{r['backward_over_forward']:.2f}, total/forward {r['total_over_forward']:.2f}"
            )
    if args.json:
        out = {"meta": meta, "rows": rows, "accuracy": acc if args.accuracy else None}
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
