"""BSV benchmark: edge-scan vs JAX brute force vs Embree, on the same gnomonic cone rays.

For each mesh and image size, all methods use the same T×P shell points (R = shell · r) and the
same pixel-centre rays of the gnomonic image of the cone holding the bounding sphere
(:func:`jshadow.visibility._edgescan.edgescan_cone_directions`):

* ``edgescan``: :func:`bsv_mesh_edgescan` from the vertices (bounding sphere, shell points, SH
  projection included; edge table and static slots prepared once from the rest pose);
* ``brute``: the JAX brute-force fan caster (:func:`jshadow.visibility.ray_fan_any_hit`, the
  kernel behind ``bsv_mesh(method="brute")``) on the same cone rays, plus the same SH projection,
  in one ``jax.jit``;
* ``embree trace``: embreex ``OCCLUDED`` queries on a prebuilt scene (rays prepared beforehand);
* ``embree full``: bounding sphere, rays, scene build, trace and SH projection in numpy.

Times: compile + first call separately; then the median of ``--runs`` warm runs
(``block_until_ready``). Ratios are to ``embree trace`` from the same run. Mismatches are pixels
whose occlusion differs from Embree's.

Usage: ``python benchmarks/bench_bsv.py [--runs 7] [--meshes bunny_small bunny spot airplane]
[--sizes 32 16] [--out benchmarks/results/bsv.md]``
"""

from __future__ import annotations

import os

# numpy's OpenBLAS threads spin after a matmul and steal the 2 cores from Embree's own threads
# (measured: Embree trace 16 ms -> 30-50 ms, a 4 MFLOP matmul 3-10 ms); keep BLAS single-threaded
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import datetime
import math
import platform
import statistics
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jshadow.geometry import bounding_sphere, load_mesh
from jshadow.sh import sh_basis
from jshadow.visibility import ray_fan_any_hit
from jshadow.visibility._bsv import bsv_sample_points
from jshadow.visibility._edgescan import (
    bsv_mesh_edgescan,
    build_edge_table,
    edgescan_cone_directions,
    edgescan_occlusion,
    edgescan_slots,
)

ROOT = Path(__file__).resolve().parents[1]
GRID = (12, 20)
SHELL = 1.5
N_BANDS = 4


def _timed(fn, runs):
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return first, 1e3 * statistics.median(times), 1e3 * min(times)


@partial(jax.jit, static_argnames=("directions",))
def _brute_bsv(vertices, faces, *, directions):
    center, radius = bounding_sphere(vertices)
    points, frames = bsv_sample_points(center, radius, GRID, SHELL)
    local, w = edgescan_cone_directions(directions, SHELL, vertices.dtype)
    world = jnp.einsum("tpab,kb->tpka", frames, local).reshape(-1, local.shape[0], 3)
    occ = ray_fan_any_hit(points.reshape(-1, 3), world, vertices, faces)
    full = jnp.zeros(N_BANDS**2, vertices.dtype).at[0].set(math.sqrt(4.0 * math.pi))
    return occ, full - occ.astype(vertices.dtype) @ (sh_basis(local, N_BANDS) * w[:, None])


def _np_frames():
    """Shell directions u (G, 3) and frames (G, 3, 3) of the BSV grid, numpy (see ``_frames``)."""
    t, p = GRID
    theta = (np.arange(t) + 0.5) * (math.pi / t)
    phi = np.arange(p) * (2.0 * math.pi / p)
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    st, ct, sp, cp = np.sin(th), np.cos(th), np.sin(ph), np.cos(ph)
    u = np.stack([st * cp, st * sp, ct], -1).reshape(-1, 3)
    x = np.stack([ct * cp, ct * sp, -st], -1).reshape(-1, 3)
    y = np.stack([sp, -cp, np.zeros_like(sp)], -1).reshape(-1, 3)
    return u, np.stack([x, y, -u], axis=-1)


def _embree_rays(vertices, directions, local):
    """World origins (G·K, 3) and directions (G·K, 3) of the cone rays, float32, all in numpy."""
    v = np.asarray(vertices, np.float64)
    center = 0.5 * (v.min(0) + v.max(0))
    radius = np.max(np.linalg.norm(v - center, axis=1))
    u, frames = _np_frames()
    points = center + SHELL * radius * u
    k = local.shape[0]
    dirs = np.matmul(local.astype(np.float32)[None], frames.astype(np.float32).transpose(0, 2, 1))
    origins = np.empty((points.shape[0], k, 3), np.float32)
    origins[...] = points.astype(np.float32)[:, None, :]
    return origins.reshape(-1, 3), dirs.reshape(-1, 3)


def _embree_scene(vertices, faces):
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh

    scene = rtcs.EmbreeScene()
    TriangleMesh(scene, np.asarray(vertices, np.float32), np.asarray(faces, np.int32))
    return scene


def _embree_occluded(scene, origins, dirs):
    return scene.run(origins, dirs, query="OCCLUDED") != -1


def _machine():
    model = platform.processor() or "unknown CPU"
    try:
        for line in subprocess.run(
            ["lscpu"], capture_output=True, text=True, check=False
        ).stdout.splitlines():
            if line.strip().startswith("Model name"):
                model = line.split(":", 1)[1].strip()
    except OSError:
        pass
    return f"{model}, {os.cpu_count()} logical CPUs; jax {jax.__version__} on {jax.devices()[0].platform}"


def _twist(vertices, amount):
    """Rotate each slice y = const about the bounding-sphere centre's y axis by ``amount · (y − c_y) / r``."""
    v = np.asarray(vertices, np.float64)
    c = 0.5 * (v.min(0) + v.max(0))
    r = np.max(np.linalg.norm(v - c, axis=1))
    ang = amount * (v[:, 1] - c[1]) / r
    x, z = v[:, 0] - c[0], v[:, 2] - c[2]
    cos, sin = np.cos(ang), np.sin(ang)
    out = np.stack([c[0] + cos * x + sin * z, v[:, 1], c[2] - sin * x + cos * z], -1)
    return jnp.asarray(out, jnp.asarray(vertices).dtype)


def bench_one(name, size, runs, twist=0.0):
    mesh = load_mesh(ROOT / "assets" / f"{name}.obj")
    v, f = mesh.vertices, mesh.faces
    directions = (size, size)
    table = build_edge_table(f, v.shape[0])
    slots = edgescan_slots(v, f, GRID, directions, SHELL, edge_table=table)  # from the rest pose
    label = name if twist == 0.0 else f"{name}, twisted {twist:g} rad/r"
    if twist != 0.0:
        v = _twist(v, twist)
    need = edgescan_slots(v, f, GRID, directions, SHELL, margin=1.0, edge_table=table)
    fits = all(
        n <= s for n, s in zip(need, slots, strict=True)
    )  # else every call recomputes with larger slots
    row = dict(mesh=label, faces=int(f.shape[0]), size=size, slots=slots, fits=fits)

    def edgescan():
        return bsv_mesh_edgescan(v, f, N_BANDS, GRID, directions, SHELL, edge_table=table, slots=slots).coeffs

    row["es_first"], row["es_med"], row["es_best"] = _timed(edgescan, runs)
    occ_es, _ = edgescan_occlusion(v, f, GRID, directions, SHELL, edge_table=table, slots=slots)
    occ_es = np.asarray(occ_es).reshape(-1)

    f32 = f.astype(jnp.int32)
    row["bf_first"], row["bf_med"], row["bf_best"] = _timed(
        lambda: _brute_bsv(v, f32, directions=directions), max(3, runs // 2)
    )
    occ_bf = np.asarray(_brute_bsv(v, f32, directions=directions)[0]).reshape(-1)

    local, w = edgescan_cone_directions(directions, SHELL, jnp.float32)
    local_np = np.asarray(local, np.float64)
    origins, dirs = _embree_rays(v, directions, local_np)
    scene = _embree_scene(v, f)
    _, row["em_med"], row["em_best"] = _timed(lambda: _embree_occluded(scene, origins, dirs), runs)
    occ_em = _embree_occluded(scene, origins, dirs)
    basis_w = np.asarray(sh_basis(local, N_BANDS) * w[:, None])
    v_np, f_np = np.asarray(v), np.asarray(f)

    def embree_full():
        o, d = _embree_rays(v_np, directions, local_np)
        occ = _embree_occluded(_embree_scene(v_np, f_np), o, d).reshape(-1, basis_w.shape[0])
        coeffs = -(occ.astype(np.float32) @ basis_w)
        coeffs[:, 0] += math.sqrt(4.0 * math.pi)
        return coeffs

    _, row["emf_med"], row["emf_best"] = _timed(embree_full, runs)
    row["mis_es"] = int(np.sum(occ_es != occ_em))
    row["mis_bf"] = int(np.sum(occ_bf != occ_em))
    row["rays"] = occ_em.size
    row["hit"] = float(np.mean(occ_em))
    return row


def stage_times(name, size, runs):
    """Median warm time (ms) of each separately jitted edge-scan stage, for one mesh."""
    from jshadow.visibility import _edgescan as es

    mesh = load_mesh(ROOT / "assets" / f"{name}.obj")
    v, f = mesh.vertices, mesh.faces
    d = (size, size)
    t = es.build_edge_table(f, v.shape[0])
    s, s2, s3, k = es.edgescan_slots(v, f, GRID, d, SHELL, edge_table=t)
    out = {}

    def run(label, fn):
        out[label] = _timed(fn, runs)[1]
        return fn()

    _, _, comps, offset = run("1 views", lambda: es._stage_views(v, f, grid=GRID, shell=SHELL))
    px, py, col, front = run("2 project", lambda: es._stage_project(comps, offset, directions=d, shell=SHELL))
    cand = run("3 candidates", lambda: es._stage_candidates(front, col, t.a, t.b, t.t1, t.t2))
    slot, most = run("4 slots", lambda: es._stage_slots(cand, slots=s))
    params = run("5 gather", lambda: es._stage_gather(slot, px, py, col, front, t.a, t.b, t.t1, directions=d))
    views = GRID[0] * GRID[1]
    diff, _, _ = run(
        "6 emit",
        lambda: es._stage_emit(
            params, most, views=views, directions=d, shell=SHELL, long_slots=(s2, s3), span=k
        ),
    )
    basis_w = es._basis_weights(d, SHELL, N_BANDS, v.dtype)
    run("7 SH", lambda: es._stage_sh(diff, basis_w, n=N_BANDS, grid=GRID))
    total = _timed(
        lambda: bsv_mesh_edgescan(v, f, N_BANDS, GRID, d, SHELL, edge_table=t, slots=(s, s2, s3, k)).coeffs,
        runs,
    )[1]
    out["whole call"] = total
    return out


def _table(rows):
    head = (
        "| mesh (F) | dirs | edge-scan median / best (ms) | compile + 1st (s) | brute median (ms) | "
        "brute compile + 1st (s) | Embree trace (ms) | Embree full (ms) | edge-scan / Embree trace | "
        "brute / Embree trace | mismatches vs Embree: edge-scan, brute (of rays) | "
        "slots (S, S2, S3, K), rest pose |"
    )
    lines = [head, "|" + "---|" * 12]
    for r in rows:
        lines.append(
            f"| {r['mesh']} ({r['faces']}) | {r['size']}² | **{r['es_med']:.2f}** / {r['es_best']:.2f} | "
            f"{r['es_first']:.2f} | {r['bf_med']:.0f} | {r['bf_first']:.2f} | {r['em_med']:.2f} | "
            f"{r['emf_med']:.2f} | {r['es_med'] / r['em_med']:.2f} | {r['bf_med'] / r['em_med']:.1f} | "
            f"{r['mis_es']}, {r['mis_bf']} (of {r['rays']}; {100 * r['hit']:.0f} % occluded) | {r['slots']}"
            f"{'' if r['fits'] else ' (overflow: retried)'} |"
        )
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=7)
    ap.add_argument("--meshes", nargs="+", default=["bunny_small", "bunny", "spot", "airplane"])
    ap.add_argument("--sizes", nargs="+", type=int, default=[32, 16])
    ap.add_argument("--twisted", nargs="*", default=["bunny"], help="meshes also measured twisted")
    ap.add_argument("--twist", type=float, default=1.0, help="twist (radians per bounding radius)")
    ap.add_argument("--stages", default="bunny", help="mesh whose per-stage times are reported ('' = none)")
    ap.add_argument("--out", type=Path, default=None, help="write a markdown report here")
    args = ap.parse_args(argv)
    load0 = os.getloadavg()
    rows = []
    jobs = [(name, size, 0.0) for name in args.meshes for size in args.sizes]
    jobs += [(name, size, args.twist) for name in args.twisted for size in args.sizes]
    for name, size, twist in jobs:
        r = bench_one(name, size, args.runs, twist)
        rows.append(r)
        print(
            f"{r['mesh']:12s} {size}²  edgescan {r['es_med']:7.2f} ms (best {r['es_best']:.2f}, "
            f"first {r['es_first']:.2f} s)  brute {r['bf_med']:8.1f} ms  "
            f"embree trace {r['em_med']:6.2f} ms full {r['emf_med']:6.2f} ms"
            f"  mismatches {r['mis_es']} / {r['mis_bf']}",
            flush=True,
        )
    stages = stage_times(args.stages, 32, args.runs) if args.stages else {}
    load1 = os.getloadavg()
    table = _table(rows)
    if stages:
        table += f"\n\nEdge-scan stages, {args.stages} at 32² (median ms, same run):\n\n"
        table += "| " + " | ".join(stages) + " |\n|" + "---|" * len(stages) + "\n"
        table += "| " + " | ".join(f"{x:.2f}" for x in stages.values()) + " |"
    print(table)
    if args.out is not None:
        now = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
        cmd = "python " + " ".join(
            [os.path.relpath(__file__, ROOT), *(argv if argv is not None else sys.argv[1:])]
        )
        text = (
            "# BSV: edge-scan vs brute force vs Embree\n\n"
            f"- Date: {now}\n- Machine: {_machine()}\n- Command: `{cmd}` (from the repository root)\n"
            f"- Setting: grid {GRID[0]}×{GRID[1]} shell points at R = {SHELL} r, n = {N_BANDS} bands, "
            "gnomonic cone image (pixel-centre rays), the same rays for every method.\n"
            f"- Load average (1 min) at start / end: {load0[0]:.2f} / {load1[0]:.2f}. **Caveat:** other "
            "engineers were running tests and benchmarks on the same 2 cores, so absolute times are inflated "
            "and noisy; the ratios come from the same run.\n"
            f"- Median of {args.runs} warm runs (brute: {max(3, args.runs // 2)}), `block_until_ready`; "
            "compile + first call reported separately.\n"
            "- edge-scan: `bsv_mesh_edgescan` from the vertices (bounding sphere, rays, SH included; edge "
            "table and slots from the rest pose, prepared once). brute: `ray_fan_any_hit` (the kernel of "
            "`bsv_mesh(method='brute')`) on the same cone rays + the same SH projection, one jit. "
            "Embree trace: embreex OCCLUDED on a prebuilt BVH; Embree full: rays + BVH build + trace + SH "
            "in numpy.\n\n"
            f"{table}\n"
        )
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
