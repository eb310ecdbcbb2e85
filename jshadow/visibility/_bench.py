"""Timing of the brute-force BSV: ``python -m jshadow.visibility._bench [mesh.obj ...] [--chunks]``.

Loads each mesh (default: the repository's ``assets/bunny_small.obj`` and ``assets/bunny.obj``),
and times :func:`jshadow.visibility.bsv_mesh` with ``method="brute"`` (240 shell points × 32² hemisphere
directions, SH projection included): the first call (compile + run) separately, then the median and
minimum of warm ``block_until_ready`` runs. ``--chunks`` sweeps the ray caster's chunk sizes.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from ._bsv import bsv_mesh


def _load(path):
    import trimesh

    m = trimesh.load(path, process=False, force="mesh")
    return jnp.asarray(m.vertices, jnp.float32), jnp.asarray(m.faces, jnp.int32)


def time_bsv(vertices, faces, runs=5, **kw):
    """(first-call seconds, median warm seconds, min warm seconds) of the brute-force BSV."""
    t0 = time.perf_counter()
    jax.block_until_ready(bsv_mesh(vertices, faces, method="brute", **kw))
    first = time.perf_counter() - t0
    ts = []
    for _ in range(runs):
        t0 = time.perf_counter()
        jax.block_until_ready(bsv_mesh(vertices, faces, method="brute", **kw))
        ts.append(time.perf_counter() - t0)
    return first, statistics.median(ts), min(ts)


def main(argv=None):
    root = Path(__file__).resolve().parents[2]
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default = [str(root / "assets/bunny_small.obj"), str(root / "assets/bunny.obj")]
    p.add_argument("meshes", nargs="*", default=default)
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--shell", type=float, default=1.0)
    p.add_argument("--chunks", action="store_true", help="sweep face_chunk × origin_chunk")
    a = p.parse_args(argv)
    print(f"jax {jax.__version__}, devices {jax.devices()}")
    for path in a.meshes:
        v, f = _load(path)
        combos = [(4, 256)]
        if a.chunks:
            combos = [(fc, oc) for fc in (1, 2, 4, 8) for oc in (16, 60, 240)]
        for fc, oc in combos:
            first, med, best = time_bsv(v, f, runs=a.runs, shell=a.shell, face_chunk=fc, origin_chunk=oc)
            print(
                f"{Path(path).name:18s} F={f.shape[0]:5d} shell={a.shell} face_chunk={fc} origin_chunk={oc}: "
                f"first {first * 1e3:7.0f} ms, median {med * 1e3:7.1f} ms, min {best * 1e3:7.1f} ms"
            )
    return 0


if __name__ == "__main__":
    np.set_printoptions(precision=4)
    raise SystemExit(main())
