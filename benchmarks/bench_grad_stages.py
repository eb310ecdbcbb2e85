"""Where the BSV derivatives' primal goes: their stages timed as cumulative programs.

    python benchmarks/bench_grad_stages.py [--config configs/bunny_animated.toml]
                                           [--gradient scanline|image] [--runs 40] [--json out.json]

A derivative of the edge-scan BSV runs more than the forward pass in its primal: the terms its
tangent (and, transposed, its cotangent) needs. ``scanline`` (:mod:`jshadow.visibility._edgescan_scan`):
the edge-scan forward pass, the same slot stages on the transposed image (the row scan), the
boundary sign σ of every crossing (a sort of (cell, height) keys), the compaction of the crossings
with σ ≠ 0 and their per-crossing terms. ``image`` (:mod:`jshadow.visibility._edgescan_grad`, the
default): the forward pass, the silhouette (edge, view) pairs and their Gauss nodes, the pixel lists
of the projected edges (a sort) and the winding number χ of the silhouette at every node, then the
compaction of the visible nodes and their terms. Each line below is one jitted program that stops
after a stage and returns what that stage made (so XLA cannot drop it), on the config's mesh at
frame 0 with the config's method and the sizes measured on that pose; the difference between two
lines is the cost of a stage. Calls alternate between the programs (this VM drifts within minutes);
compile time and warm median per program, and the machine probe of ``bench_render.py`` before and
after. float32, whatever device JAX picks.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import platform
import time
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from bench_render import machine_probe

from jshadow.config import build_scene, load_config
from jshadow.entities import MeshOccluder
from jshadow.visibility import _edgescan as E
from jshadow.visibility import _edgescan_grad as G
from jshadow.visibility import _edgescan_scan as S
from jshadow.visibility import edgescan_grad_slots, edgescan_scan_slots, edgescan_slots

ROOT = pathlib.Path(__file__).resolve().parents[1]
IMAGE_STAGES = (
    "edge-scan forward (layer counts, SH projection)",
    "+ silhouette pairs and their Gauss nodes",
    "+ pixel lists of the projected edges (a sort)",
    "+ winding numbers of the silhouette at the nodes",
    "+ compaction of the visible nodes and their terms (the whole primal)",
)
STAGES = (
    "edge-scan forward (column scan, layer counts)",
    "+ row scan (both scans' crossing lists)",
    "+ boundary signs (sort of the crossings)",
    "+ compaction of the boundary crossings",
    "+ per-crossing terms (the whole primal)",
)


def programs(config: pathlib.Path, gradient: str = "scanline"):
    """The mesh at frame 0, the stage names and one jitted function per stage prefix."""
    scene = build_scene(load_config(config))
    # the n-band light path, as a fit's default (light_visibility = "auto" keeps it for [fit] configs)
    scene = dataclasses.replace(
        scene, method=dataclasses.replace(scene.method, light_visibility="sh", environment_lights=0)
    )
    occ = next((o for o in scene.occluders if isinstance(o, MeshOccluder)), None)
    if occ is None:
        raise SystemExit(f"{config} has no mesh occluder")
    x = jnp.asarray(occ.vertices(0.0))
    faces = np.asarray(occ.faces)
    m = scene.method
    grid, dirs, shell, n = tuple(m.bsv_grid), tuple(m.directions), float(m.shell), m.field_bands
    table = E._cached_edge_table(faces, x.shape[0])
    slots = edgescan_slots(x, faces, grid, dirs, shell)
    if gradient == "image":
        return _image_programs(x, faces, table, grid, dirs, shell, n, slots)
    scan = edgescan_scan_slots(x, faces, grid, dirs, shell, slots=slots)

    def upto(v, level):
        if level == 0:
            return E._run(v, faces, table, grid, dirs, shell, slots)[0]
        out, cr, sigma, slot_all, _ = S._scan_lists(v, faces, table, grid, dirs, shell, slots, scan[:4], n)
        if level == 1:
            return out, cr["y"], slot_all
        if level == 2:
            return out, cr["y"], sigma
        if level == 3:
            cr, sigma, _ = E.staged(E.always(v), partial(S._compact_boundary, size=scan[4]), cr, sigma)
            return out, cr["y"], sigma
        # the whole primal is the derivative's own (refine: its default, which the renderer keeps)
        return S._primal(v, faces, table, grid, dirs, shell, slots, scan, 4, n)[0]

    meta = _meta(x, faces, grid, dirs, shell, n, slots, scan_slots=list(scan))
    return x, STAGES, [jax.jit(partial(upto, level=k)) for k in range(len(STAGES))], meta


def _meta(x, faces, grid, dirs, shell, n, slots, **sizes):
    """The run's mesh, method and sizes, for the JSON."""
    return dict(
        vertices=int(x.shape[0]),
        faces=int(faces.shape[0]),
        grid=grid,
        directions=dirs,
        shell=shell,
        bands=n,
        slots=list(slots),
        **sizes,
    )


def _image_programs(x, faces, table, grid, dirs, shell, n, slots):
    """As :func:`programs` for ``bsv_gradient = "image"`` (:mod:`jshadow.visibility._edgescan_grad`),
    with the sizes its derivative uses (measured on this pose, rounded as it rounds them)."""
    nodes, views = 2, grid[0] * grid[1]
    measured = edgescan_grad_slots(x, faces, grid, shell, directions=dirs)
    sizes = G._rounded_grad_slots(measured, int(table.a.shape[0]) * views, nodes, dirs, views)
    pairs, live, pieces, window, longs = sizes
    basis_w = E._basis_weights(dirs, shell, n, x.dtype)
    kw = dict(grid=grid, directions=dirs, shell=shell, slots=pairs, nodes=nodes)
    lists = dict(piece_slots=pieces, window=window, long_slots=longs)

    def upto(v, level):
        diff = E._compute(v, faces, table, grid, dirs, shell, slots, check=False)[0]
        counts = E._stage_counts(diff)
        out = E._project_sh(counts != 0, basis_w, n)
        if level == 0:
            return out
        if level == 1:
            pair, filled, total, _ = G._pairs(v, faces, table, **kw)
            return out, pair, filled
        if level == 2:
            pair, filled, _, _ = G._pairs(v, faces, table, **kw)
            pixel_lists = partial(
                G._pixel_lists, directions=dirs, shell=shell, views=views, piece_slots=pieces, window=window
            )
            return out, E.staged(E.always(v), pixel_lists, pair, filled)
        if level == 3:
            return out, G._visible_nodes(v, faces, table, counts, **kw, **lists)[:2]
        return out, G._slot_terms(v, faces, table, counts, **kw, node_slots=live, **lists)

    meta = _meta(x, faces, grid, dirs, shell, n, slots, grad_slots=[pairs, live, pieces, window, *longs])
    return x, IMAGE_STAGES, [jax.jit(partial(upto, level=k)) for k in range(len(IMAGE_STAGES))], meta


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", type=pathlib.Path, default=ROOT / "configs/bunny_animated.toml")
    ap.add_argument("--gradient", choices=("scanline", "image"), default="scanline")
    ap.add_argument("--runs", type=int, default=40, help="warm calls per program (default 40)")
    ap.add_argument("--json", type=pathlib.Path, default=None)
    a = ap.parse_args(argv)
    probe_start = machine_probe()
    x, stages, fns, meta = programs(a.config, a.gradient)
    compiled, compile_s = [], []
    for f in fns:
        t0 = time.perf_counter()
        compiled.append(f.lower(x).compile())
        compile_s.append(time.perf_counter() - t0)
        jax.block_until_ready(compiled[-1](x))
    times = [[] for _ in fns]
    for r in range(a.runs):
        order = range(len(fns)) if r % 2 == 0 else reversed(range(len(fns)))
        for k in order:
            t0 = time.perf_counter()
            jax.block_until_ready(compiled[k](x))
            times[k].append(time.perf_counter() - t0)
    med = [float(np.median(t)) * 1e3 for t in times]
    meta.update(probe_start=probe_start, probe_end=machine_probe())
    print(f"{a.config.name}: {meta}")
    print("| stage | warm median ms | this stage ms | compile s |\n|---|---:|---:|---:|")
    for k, name in enumerate(stages):
        step = med[k] - (med[k - 1] if k else 0.0)
        print(f"| {name} | {med[k]:.2f} | {step:.2f} | {compile_s[k]:.1f} |")
    if a.json:
        rows = [
            dict(stage=s, median_ms=m, compile_s=c) for s, m, c in zip(stages, med, compile_s, strict=True)
        ]
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(
            json.dumps(
                dict(
                    gradient=a.gradient,
                    config=str(a.config.relative_to(ROOT) if a.config.is_absolute() else a.config),
                    date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                    machine=platform.processor() or platform.machine(),
                    device=str(jax.devices()[0]),
                    runs=a.runs,
                    **meta,
                    stages=rows,
                ),
                indent=1,
            )
        )


if __name__ == "__main__":
    main()
