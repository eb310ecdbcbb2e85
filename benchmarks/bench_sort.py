"""Sorting integer keys under ``jax.jit``: XLA's sort against ``jshadow._sorting`` (NumPy on the CPU).

Usage::

    python benchmarks/bench_sort.py [--sizes 115000 201000 440000] [--runs 21] [--json out.json]

For each size: random uint32 keys (31 bits) of which 43 % are padding (``_sorting.PAD``, the share
of the animated bunny's scanline crossings), timed as

* ``xla_sort`` / ``numpy_sort``: ``jnp.sort`` against :func:`jshadow._sorting.sort_keys`;
* ``xla_argsort`` / ``numpy_argsort``: ``jnp.argsort(stable=True)`` (a sort with an index payload)
  against :func:`jshadow._sorting.argsort_keys`;
* ``xla_sort_search``: the scanline derivative's former ordering, a sort and ``searchsorted``
  (``method="scan"``) of every key into it;

each jitted, compile time separate (first call minus warm median), warm medians of ``--runs`` calls
with ``block_until_ready``, and the ratios against XLA's in the same run. The two argsorts' results
are checked to be equal. On a GPU the ``_sorting`` functions run XLA's sort, so the columns agree.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np
from bench_bsv_grad import _time  # the script's folder is on sys.path
from bench_render import machine_probe

from jshadow._sorting import PAD, argsort_keys, sort_keys


def _keys(n, seed=0):
    rng = np.random.default_rng(seed)
    k = rng.integers(0, 2**31, n).astype(np.uint32)
    k[rng.random(n) < 0.43] = np.uint32(PAD)
    return jnp.asarray(k)


def bench(n, runs):
    k = _keys(n)
    fns = {
        "xla_sort": jax.jit(jnp.sort),
        "numpy_sort": jax.jit(sort_keys),
        "xla_argsort": jax.jit(lambda k: jnp.argsort(k, stable=True)),
        "numpy_argsort": jax.jit(argsort_keys),
        "xla_sort_search": jax.jit(lambda k: jnp.searchsorted(jnp.sort(k), k, method="scan")),
    }
    row = {"n": n}
    for name, fn in fns.items():
        t = _time(fn, k, runs=runs)
        row[name] = {
            "compile_s": t["compile_s"],
            "median_ms": 1e3 * t["median_s"],
            "min_ms": 1e3 * t["min_s"],
        }
    a, b = np.asarray(fns["xla_argsort"](k)), np.asarray(fns["numpy_argsort"](k))
    row["argsorts_equal"] = bool(np.array_equal(a, b))
    row["sort_ratio"] = row["numpy_sort"]["median_ms"] / row["xla_sort"]["median_ms"]
    row["argsort_ratio"] = row["numpy_argsort"]["median_ms"] / row["xla_argsort"]["median_ms"]
    row["argsort_vs_sort_search"] = row["numpy_argsort"]["median_ms"] / row["xla_sort_search"]["median_ms"]
    return row


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="*", default=[115000, 201000, 440000])
    ap.add_argument("--runs", type=int, default=21)
    ap.add_argument("--json", type=pathlib.Path)
    args = ap.parse_args()
    meta = {
        "machine": platform.platform(),
        "device": str(jax.devices()[0]),
        "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
        "machine_probe_start": machine_probe(),
    }
    rows = []
    print(
        f"{'n':>8} {'xla sort':>9} {'np sort':>9} {'xla argsort':>12} {'np argsort':>11} "
        f"{'sort+search':>12}  equal"
    )
    for n in args.sizes:
        r = bench(n, args.runs)
        rows.append(r)
        ms = [
            r[k]["median_ms"]
            for k in ("xla_sort", "numpy_sort", "xla_argsort", "numpy_argsort", "xla_sort_search")
        ]
        print(
            f"{n:>8} {ms[0]:>9.2f} {ms[1]:>9.2f} {ms[2]:>12.2f} {ms[3]:>11.2f} {ms[4]:>12.2f}  "
            f"{r['argsorts_equal']}"
        )
    meta["machine_probe_end"] = machine_probe()
    print("probe", meta["machine_probe_start"], "->", meta["machine_probe_end"])
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))


if __name__ == "__main__":
    main()
