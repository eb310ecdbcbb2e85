"""SH core benchmark: basis, fused evaluation, rotations, triple products, zonal caps, M_k apply.

Usage::

    python benchmarks/bench_sh.py [--repeats 7] [--scale 1.0] [--json out.json] [--md out.md]

Every row is a jit-compiled function of its array arguments (nothing is closed over, so XLA cannot
constant-fold the work away). Compile time is measured separately (``lower(...).compile()``); the
warm figure is the median of ``--repeats`` calls with ``block_until_ready``. float32, n = 4 bands.
``--scale`` multiplies every problem size (e.g. 0.1 for a quick smoke run). The M_k row needs
``jshadow.scaling`` and is skipped with a note if it cannot be imported.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import pathlib
import platform
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from jshadow.sh import (
    cap,
    product_matrix,
    rotate,
    rotation_matrix,
    sh_basis,
    sh_eval,
    sh_product,
)
from jshadow.sh._triple import _sh_product_dense

N = 4


def _unit(rng, count):
    v = rng.normal(size=(count, 3))
    return (v / np.linalg.norm(v, axis=-1, keepdims=True)).astype(np.float32)


def _rotations(rng, count):
    q = rng.normal(size=(count, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q.T
    r = np.stack(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    return np.moveaxis(r, (0, 1), (-2, -1)).astype(np.float32)


def time_fn(fn, args, repeats):
    """(compile seconds, median warm milliseconds, all warm milliseconds)."""
    jitted = jax.jit(fn)
    t0 = time.perf_counter()
    compiled = jitted.lower(*args).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(*args))  # warm-up
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        ts.append((time.perf_counter() - t0) * 1e3)
    return compile_s, float(np.median(ts)), ts


def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    dev = jax.devices()[0]
    return f"{cpu}, {os.cpu_count()} cores, JAX {jax.__version__} on {dev.platform} ({dev.device_kind})"


def rows_to_md(rows) -> str:
    out = [
        "| operation | size | compile (s) | warm median (ms) | per item (ns) |",
        "|---|---:|---:|---:|---:|",
    ]
    for r in rows:
        if r.get("skipped"):
            out.append(f"| {r['name']} | {r['size']:.0e} | – | skipped: {r['skipped']} | – |")
            continue
        per = r["median_ms"] * 1e6 / r["size"]
        out.append(
            f"| {r['name']} | {r['size']:.0e} | {r['compile_s']:.2f} | {r['median_ms']:.2f} | {per:.1f} |"
        )
    return "\n".join(out)


def _rot_fit(c, theta, phi):
    from jshadow.visibility import bsv_frames

    return rotate(c, bsv_frames(theta, phi)[1])


def _rot_zyz(c, theta, phi):
    from jshadow.field import frame_to_world  # rotate_zyz with the frame's constant flip

    return frame_to_world(c, theta, phi)


def _grad(f):
    return jax.grad(lambda *a: jnp.sum(f(*a) ** 2), argnums=(0, 1, 2))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7, help="warm runs per row (median reported), >= 5")
    ap.add_argument("--scale", type=float, default=1.0, help="multiply every problem size")
    ap.add_argument("--json", type=pathlib.Path, help="also write the rows as JSON here")
    ap.add_argument("--md", type=pathlib.Path, help="also write a markdown report here")
    args = ap.parse_args(argv)
    if args.repeats < 5:
        ap.error("--repeats must be >= 5")

    rng = np.random.default_rng(0)
    n_dirs = max(int(1e6 * args.scale), 1)
    n_rec = max(int(1e5 * args.scale), 1)
    dirs = jnp.asarray(_unit(rng, n_dirs))
    c_one = jnp.asarray(rng.normal(size=N * N).astype(np.float32))
    c_dirs = jnp.asarray(rng.normal(size=(n_dirs, N * N)).astype(np.float32))
    rots = jnp.asarray(_rotations(rng, n_rec))
    a = jnp.asarray(rng.normal(size=(n_rec, N * N)).astype(np.float32))
    b = jnp.asarray(rng.normal(size=(n_rec, N * N)).astype(np.float32))
    axes = jnp.asarray(_unit(rng, n_rec))
    cos_a = jnp.asarray(rng.uniform(-1, 1, size=n_rec).astype(np.float32))
    theta = jnp.asarray(rng.uniform(0, np.pi, size=n_rec).astype(np.float32))
    phi = jnp.asarray(rng.uniform(-np.pi, np.pi, size=n_rec).astype(np.float32))

    cases = [
        ("sh_basis (n=4)", n_dirs, lambda d: sh_basis(d, N), (dirs,)),
        ("sh_eval, one coefficient vector (fused)", n_dirs, sh_eval, (c_one, dirs)),
        ("sh_eval, a coefficient vector per direction", n_dirs, sh_eval, (c_dirs, dirs)),
        ("rotation_matrix (n=4)", n_rec, lambda r: rotation_matrix(r, N), (rots,)),
        ("rotate (n=4, no D formed)", n_rec, rotate, (a, rots)),
        ("sh_product (unrolled sparse, n=4)", n_rec, sh_product, (a, b)),
        ("sh_product as dense Gaunt einsum (comparison)", n_rec, _sh_product_dense, (a, b)),
        ("product_matrix (n=4)", n_rec, product_matrix, (a,)),
        ("cap (n=4)", n_rec, lambda ax, t: cap(ax, t, N), (axes, cos_a)),
        # the field's rotation from the BSV frame at (θ, φ) to world, two ways (and their gradients)
        ("rotate from (θ, φ): bsv_frames + fitting", n_rec, _rot_fit, (a, theta, phi)),
        ("rotate from (θ, φ): rotate_zyz (Euler angles)", n_rec, _rot_zyz, (a, theta, phi)),
        ("grad of Σ rotated² via bsv_frames + fitting", n_rec, _grad(_rot_fit), (a, theta, phi)),
        ("grad of Σ rotated² via rotate_zyz", n_rec, _grad(_rot_zyz), (a, theta, phi)),
    ]
    rows = []
    load_before = os.getloadavg()
    for name, size, fn, fargs in cases:
        comp, med, ts = time_fn(fn, fargs, args.repeats)
        rows.append({"name": name, "size": size, "compile_s": comp, "median_ms": med, "runs_ms": ts})
        print(f"{name:50s} {size:9.0e}  compile {comp:6.2f} s  warm {med:9.3f} ms", flush=True)

    mk_name = "M_k interpolation + apply (mk_apply, n=4)"
    try:
        from jshadow.scaling import mk_apply, mk_table
    except ImportError as err:
        print(f"note: skipping the M_k row ({err})")
        rows.append({"name": mk_name, "size": n_rec, "skipped": f"jshadow.scaling not importable ({err})"})
    else:
        table = mk_table(n=N, dtype=jnp.float32)
        ks = jnp.asarray(rng.uniform(0.125, 5.0, size=n_rec).astype(np.float32))
        comp, med, ts = time_fn(lambda t, k, c: mk_apply(t, k, c), (table, ks, a), args.repeats)
        rows.append({"name": mk_name, "size": n_rec, "compile_s": comp, "median_ms": med, "runs_ms": ts})
        print(f"{mk_name:50s} {n_rec:9.0e}  compile {comp:6.2f} s  warm {med:9.3f} ms", flush=True)
    load_after = os.getloadavg()

    cmd = "python " + " ".join([pathlib.Path(sys.argv[0]).as_posix(), *(argv or sys.argv[1:])])
    meta = {
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": machine(),
        "command": cmd,
        "dtype": "float32",
        "load_average_1min": [load_before[0], load_after[0]],
    }
    table_md = rows_to_md(rows)
    print()
    print(table_md)
    if args.json:
        args.json.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    if args.md:
        args.md.parent.mkdir(parents=True, exist_ok=True)
        args.md.write_text(
            f"# SH core benchmark\n\n- date: {meta['date']}\n- machine: {meta['machine']}\n"
            f"- command: `{cmd}`\n- float32, n = 4 bands; warm = median of {args.repeats} runs with "
            f"block_until_ready; compile = `jit(...).lower(...).compile()`\n"
            f"- 1-min load average before/after: {load_before[0]:.1f} / {load_after[0]:.1f}\n\n"
            f"{table_md}\n"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
