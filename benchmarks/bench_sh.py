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

from jshadow._numerics import fast_atan2, fast_sin, small_sum
from jshadow.lights import sphere_light_dot, sphere_light_sh
from jshadow.scene import _env_rows
from jshadow.sh import (
    cap,
    product_matrix,
    rotate,
    rotation_matrix,
    sh_basis,
    sh_eval,
    sh_product,
    sh_product_t,
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
    from jshadow.field import frame_to_world  # Euler-angle rotation with the frame's constant flip

    return frame_to_world(c, theta, phi)


def _product_via_t(a, b):
    """sh_product_t with transposes in and out (comparison: the layout change for one product)."""
    return sh_product_t(a.T, b.T).T


def _mk_stacked(table, k, c):
    """M_k·c as one stacked sum per output coefficient (the form mk_apply replaced; comparison)."""
    from jshadow.scaling._matrices import _interp_values

    v = _interp_values(table, k, c.dtype)
    acc: list = [None] * c.shape[-1]
    for e, (i, j) in enumerate(zip(table.rows, table.cols)):
        term = v[..., e] * c[..., j]
        acc[i] = term if acc[i] is None else acc[i] + term
    return jnp.stack(acc, axis=-1)


def _sq(f):
    return lambda c, p: jnp.sum(f(c, p) ** 2)


def _field_cases(rng, n_rec):
    """The field at receivers (BSV 12×20 in 5 bands → 4, 16-distance table): shipped vs textbook order."""
    from jshadow.field import bsv_visibility_sh, frame_to_world, interpolate_bsv
    from jshadow.scaling import mk_apply, mk_table
    from jshadow.visibility import BSV

    table = mk_table(n=5, num=16, d_min=0.2, d_max=8.0, model="sphere", dtype=jnp.float32)
    coeffs = jnp.asarray(rng.normal(size=(12, 20, 25)).astype(np.float32))
    pts = jnp.asarray(rng.uniform(-3, 3, size=(n_rec, 3)).astype(np.float32))

    def shipped(c, p):
        return bsv_visibility_sh(BSV(c, jnp.zeros(3), jnp.float32(0.8), jnp.float32(1.2)), table, p, 4)

    def textbook(c, p):  # interpolate the BSV, interpolate and apply M_k, rotate (no range test)
        d = jnp.linalg.norm(p, axis=-1)
        th, ph = jnp.arccos(jnp.clip(p[:, 2] / d, -1, 1)), jnp.arctan2(p[:, 1], p[:, 0])
        return frame_to_world(mk_apply(table, 1.2 / d, interpolate_bsv(c, th, ph))[:, :16], th, ph)

    return [
        ("field: bsv_visibility_sh (shipped)", n_rec, shipped, (coeffs, pts)),
        ("field: interpolate, mk_apply, rotate (textbook order)", n_rec, textbook, (coeffs, pts)),
        ("grad of Σ field² w.r.t. the BSV (shipped)", n_rec, jax.grad(_sq(shipped)), (coeffs, pts)),
        ("grad of Σ field² w.r.t. the BSV (textbook order)", n_rec, jax.grad(_sq(textbook)), (coeffs, pts)),
    ]


def _env_einsum(v, m, t):
    return jnp.einsum("ni,cik,nk->nc", v, m, t)


def _norm_sum(p, c):
    """|p − c| with jnp.sum over the axis of 3 (comparison for _numerics.small_sum)."""
    return jnp.sqrt(jnp.sum((p - c) ** 2, -1))


def _norm_small_sum(p, c):
    return jnp.sqrt(small_sum((p - c) ** 2))


def _light_dot_via_sh(p, w):
    """⟨cap, w⟩ from the light's (N, n²) SH coefficients (comparison for lights.sphere_light_dot)."""
    c = sphere_light_sh(jnp.asarray([1.0, 3.5, 1.5]), 0.4, jnp.ones(1), p, N)[..., 0]
    return jnp.sum(c * w, -1)


def _light_dot_fused(p, w):
    return sphere_light_dot(jnp.asarray([1.0, 3.5, 1.5]), 0.4, p, w, N)


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
    m_env = jnp.asarray(rng.normal(size=(3, N * N, N * N)).astype(np.float32))

    cases = [
        ("sh_basis (n=4)", n_dirs, lambda d: sh_basis(d, N), (dirs,)),
        ("sh_eval, one coefficient vector (fused)", n_dirs, sh_eval, (c_one, dirs)),
        ("sh_eval, a coefficient vector per direction", n_dirs, sh_eval, (c_dirs, dirs)),
        ("rotation_matrix (n=4)", n_rec, lambda r: rotation_matrix(r, N), (rots,)),
        ("rotate (n=4, no D formed)", n_rec, rotate, (a, rots)),
        ("sh_product (unrolled sparse, n=4)", n_rec, sh_product, (a, b)),
        ("sh_product as dense Gaunt einsum (comparison)", n_rec, _sh_product_dense, (a, b)),
        ("sh_product_t with transposes in and out (comparison)", n_rec, _product_via_t, (a, b)),
        ("sh_product_t (coefficient axis first, inputs (16, N))", n_rec, sh_product_t, (a.T, b.T)),
        ("jnp.arctan2, float32 (comparison)", n_dirs, jnp.arctan2, (dirs[:, 1], dirs[:, 0])),
        ("fast_atan2, float32", n_dirs, fast_atan2, (dirs[:, 1], dirs[:, 0])),
        ("jnp.sin on [-pi, pi], float32 (comparison)", n_rec, jnp.sin, (phi,)),
        ("fast_sin on [-pi, pi], float32", n_rec, fast_sin, (phi,)),
        ("product_matrix (n=4)", n_rec, product_matrix, (a,)),
        ("cap (n=4)", n_rec, lambda ax, t: cap(ax, t, N), (axes, cos_a)),
        # distances of receivers (norm over an axis of 3) and a sphere light's <cap, w> (combination)
        ("norm of (N, 3) offsets, jnp.sum (comparison)", n_rec, _norm_sum, (axes * 3.0, axes[0])),
        ("norm of (N, 3) offsets, small_sum", n_rec, _norm_small_sum, (axes * 3.0, axes[0])),
        (
            "sphere light <cap, w>: its (N, n²) SH, then the dot (comparison)",
            n_rec,
            _light_dot_via_sh,
            (axes * 3.0, a),
        ),
        ("sphere light <cap, w>: sphere_light_dot (fused)", n_rec, _light_dot_fused, (axes * 3.0, a)),
        # the field's rotation from the BSV frame at (θ, φ) to world, two ways (and their gradients)
        ("rotate from (θ, φ): bsv_frames + fitting", n_rec, _rot_fit, (a, theta, phi)),
        ("rotate from (θ, φ): rotate_zyz (Euler angles)", n_rec, _rot_zyz, (a, theta, phi)),
        ("grad of Σ rotated² via bsv_frames + fitting", n_rec, _grad(_rot_fit), (a, theta, phi)),
        ("grad of Σ rotated² via rotate_zyz", n_rec, _grad(_rot_zyz), (a, theta, phi)),
        # a receiver's environment term Σ_ik v_i M[c,i,k] t_k (combination, a normal per receiver)
        ("env term Σ v M t: three-operand einsum (comparison)", n_rec, _env_einsum, (a, m_env, b)),
        ("env term Σ v M t: two GEMMs (scene._env_rows)", n_rec, _env_rows, (a, m_env, b)),
    ]
    cases += _field_cases(rng, n_rec)
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
        stacked_name = "mk_apply as stacked per-output sums (comparison)"
        for name, fn in ((mk_name, mk_apply), (stacked_name, _mk_stacked)):
            comp, med, ts = time_fn(lambda t, k, c, fn=fn: fn(t, k, c), (table, ks, a), args.repeats)
            rows.append({"name": name, "size": n_rec, "compile_s": comp, "median_ms": med, "runs_ms": ts})
            print(f"{name:50s} {n_rec:9.0e}  compile {comp:6.2f} s  warm {med:9.3f} ms", flush=True)
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
