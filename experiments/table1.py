"""Table 1 of the deformable-shadow-fields paper ("Rendering Performance"), measured here.

Per model (bunny_small, bunny, spot, airplane, the procedural egg of ``jshadow.geometry.egg`` at 3
subdivisions): vertex count, BSV sampling time, SH conversion time, shadowing time (field
evaluation + combination at every receiver) and frames per second for a model that deforms every
frame (BSV + SH + shadowing each frame). The paper's setting: a 12×20 BSV, 32² hemisphere
directions, 4 SH bands, a 160×160 receiver plane, environment-map lighting only (the studio map
here), no lights, no self-shadowing. Two method settings:

* ``paper``: the paper's method exactly (``Method.paper``): samples on the bounding sphere
  (shell 1.0) → the brute-force JAX ray caster (``bsv_mesh(method="brute")``), 32² Gauss–Legendre ×
  uniform-φ hemisphere directions, square-silhouette f_k, 4-band BSV, SH products;
* ``default``: the library's accurate setting: shell 1.5 → the silhouette-edge scanline
  (``edgescan``, 32² pixels of a gnomonic image of the cone that holds the bounding sphere),
  concentric-sphere rescaling, BSV and M_k in 5 bands, ratio shading.

Both samplers fuse visibility sampling and SH projection into one call; the split is measured by
timing the two halves on their own: "sampling" = the occlusion mask only (brute: shell points,
frames and ``ray_fan_any_hit``; edge-scan: ``edgescan_occlusion``, which includes the scanline's
row prefix sum), "SH" = ``√(4π)·e0 − occ @ (w·Y)`` on a precomputed mask. The fused BSV time (the
one a frame pays) is reported beside them and used for FPS. Shadowing comes from
:class:`jshadow.runner.Renderer` with ``split_stages=True`` (field, combine timed apart). All times are warm
medians of ``--runs`` calls with ``block_until_ready``; first-call (compile) times separately.

The paper's figures (2.8 GHz Pentium IV, 1 GB RAM, nVidia GeForce 6800 GT; BSV and SH on the
GPU, shadowing on the CPU, the two in parallel): Dragon 1151 vertices 11.0 / 5.0 / 37.7 ms,
21.3 Hz; Egg 482 vertices 7.4 / 5.0 / 36.7 ms, 22.5 Hz; Plane 8382 vertices 72.4 / 5.0 / 47.9 ms,
13.5 Hz; shadow-field evaluation ≈ 1.41 µs per vertex.

Usage (repository root, project environment active)::

    python experiments/table1.py [--runs 5] [--res 160] [--only bunny egg]

Writes ``experiments/results/table1.json`` and ``experiments/results/table1.md``.
"""

from __future__ import annotations

import argparse
import json
import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from _common import MODELS, RESULTS, machine, make_scene, md_table, scene_dict, timed, world_dirs

from jshadow.geometry import bounding_sphere
from jshadow.runner import Renderer
from jshadow.sh import sh_basis
from jshadow.visibility import (
    bsv_mesh,
    bsv_sample_points,
    edgescan_cone_directions,
    hemisphere_directions,
    ray_fan_any_hit,
)
from jshadow.visibility._edgescan import edgescan_occlusion

PAPER = {
    "hardware": "2.8 GHz Pentium IV, 1 GB RAM, nVidia GeForce 6800 GT (BSV + SH on the GPU, "
    "shadowing on the CPU, in parallel); 160×160 plane vertices",
    "rows": [
        {"model": "Dragon", "vertices": 1151, "bsv_ms": 11.0, "sh_ms": 5.0, "shadow_ms": 37.7, "fps": 21.3},
        {"model": "Egg", "vertices": 482, "bsv_ms": 7.4, "sh_ms": 5.0, "shadow_ms": 36.7, "fps": 22.5},
        {"model": "Plane", "vertices": 8382, "bsv_ms": 72.4, "sh_ms": 5.0, "shadow_ms": 47.9, "fps": 13.5},
    ],
    "us_per_vertex": 1.41,
}

FIELD_BANDS = {"paper": 4, "default": 5}  # bands of the BSV (bsv_bands)
SETTINGS = {  # every key explicit, so that the figures do not depend on the library's defaults
    "paper": {"shell": 1.0, "bsv_method": "brute", "model": "paper", "bsv_bands": 4, "shading": "product"},
    "default": {
        "shell": 1.5,
        "bsv_method": "edgescan",
        "model": "sphere",
        "bsv_bands": 5,
        "shading": "ratio",
    },
}


@partial(jax.jit, static_argnames=("grid", "directions", "shell"))
def brute_occlusion(vertices, faces, *, grid, directions, shell):
    """(G, K) occlusion mask of the brute-force BSV (the sampling half of ``bsv_mesh(method="brute")``)."""
    center, radius = bounding_sphere(vertices)
    points, frames = bsv_sample_points(center, radius, grid, shell)
    local, _ = hemisphere_directions(*directions, dtype=vertices.dtype)
    world = world_dirs(frames.reshape(-1, 3, 3), local)
    return ray_fan_any_hit(points.reshape(-1, 3), world, vertices, faces)


@jax.jit
def project(occ, basis_w):
    """SH conversion: ``√(4π)·e0 − occ (G, K) @ (w·Y) (K, n²)``."""
    full = jnp.zeros(basis_w.shape[-1], basis_w.dtype).at[0].set(math.sqrt(4.0 * math.pi))
    return full - occ.astype(basis_w.dtype) @ basis_w


def basis_weights(setting: str, m, dtype):
    if setting == "paper":
        local, w = hemisphere_directions(*m.directions, dtype=dtype)
    else:
        local, w = edgescan_cone_directions(m.directions, m.shell, dtype)
        local, w = local.reshape(-1, 3), w.reshape(-1)
    return sh_basis(local, FIELD_BANDS[setting]) * w[:, None]


def measure(model: str, setting: str, res: int, runs: int) -> dict:
    scene = make_scene(scene_dict(model, res=res, method=SETTINGS[setting]))
    m, occ = scene.method, scene.occluders[0]
    v, f = occ.vertices(0.0), occ.faces
    kw = dict(grid=m.bsv_grid, directions=m.directions, shell=m.shell)
    bsv_first, bsv_ms, _ = timed(
        lambda: bsv_mesh(v, f, n=FIELD_BANDS[setting], method=m.bsv_method, **kw).coeffs, runs=runs
    )
    if setting == "paper":
        samp_first, samp_ms, occ_mask = timed(lambda: brute_occlusion(v, f, **kw), runs=runs)
    else:
        samp_first, samp_ms, out = timed(lambda: edgescan_occlusion(v, f, **kw)[0], runs=runs)
        occ_mask = out.reshape(out.shape[0] * out.shape[1], -1)
    bw = basis_weights(setting, m, v.dtype)
    sh_first, sh_ms, _ = timed(project, occ_mask, bw, runs=runs)

    r = Renderer(scene, split_stages=True)  # field and combination timed separately
    t0_first = r.frame(0)[1]
    stages = [r.frame(0)[1] for _ in range(runs)]  # BSV reused: field + combine only
    field_ms = float(np.median([s["field_ms"] for s in stages]))
    combine_ms = float(np.median([s["combine_ms"] for s in stages]))
    shadow_ms = field_ms + combine_ms
    n_recv = int(scene.receivers.points.shape[0])
    frame_ms = bsv_ms + shadow_ms
    return {
        "model": model,
        "setting": setting,
        "method": SETTINGS[setting],
        "shell": m.shell,
        "bsv_method": m.bsv_method,
        "vertices": int(occ.unit_vertices.shape[0]),
        "faces": int(occ.faces.shape[0]),
        "receivers": n_recv,
        "bsv_fused_ms": bsv_ms,
        "bsv_sampling_ms": samp_ms,
        "sh_conversion_ms": sh_ms,
        "field_ms": field_ms,
        "combine_ms": combine_ms,
        "shadowing_ms": shadow_ms,
        "shadowing_us_per_receiver": 1e3 * shadow_ms / n_recv,
        "frame_ms": frame_ms,
        "fps": 1e3 / frame_ms,
        "first_call_ms": {
            "bsv_fused": bsv_first,
            "sampling": samp_first,
            "sh": sh_first,
            "field": t0_first["field_ms"],
            "combine": t0_first["combine_ms"],
        },
    }


def markdown(rows: list[dict]) -> str:
    ours = md_table(
        [
            "model",
            "vertices",
            "setting",
            "BSV sampling",
            "SH conversion",
            "BSV fused",
            "shadowing (field + comb.)",
            "µs / receiver",
            "FPS",
            "compile (BSV, field, comb.)",
        ],
        [
            [
                r["model"],
                r["vertices"],
                f"{r['setting']} (shell {r['shell']}, {r['bsv_method']})",
                f"{r['bsv_sampling_ms']:.1f} ms",
                f"{r['sh_conversion_ms']:.2f} ms",
                f"{r['bsv_fused_ms']:.1f} ms",
                f"{r['shadowing_ms']:.1f} ms ({r['field_ms']:.1f} + {r['combine_ms']:.1f})",
                f"{r['shadowing_us_per_receiver']:.2f}",
                f"**{r['fps']:.1f} Hz**",
                "{:.1f}, {:.1f}, {:.1f} s".format(
                    r["first_call_ms"]["bsv_fused"] / 1e3,
                    r["first_call_ms"]["field"] / 1e3,
                    r["first_call_ms"]["combine"] / 1e3,
                ),
            ]
            for r in rows
        ],
    )
    paper = md_table(
        ["model (paper)", "vertices", "BSV sampling", "SH conversion", "shadowing", "FPS"],
        [
            [
                p["model"],
                p["vertices"],
                f"{p['bsv_ms']} ms",
                f"{p['sh_ms']} ms",
                f"{p['shadow_ms']} ms",
                p["fps"],
            ]
            for p in PAPER["rows"]
        ],
    )
    return f"{ours}\n\nPaper, Table 1 ({PAPER['hardware']}):\n\n{paper}\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=5, help="warm runs per timing (median)")
    ap.add_argument("--res", type=int, default=160, help="receiver plane resolution (res × res)")
    ap.add_argument("--only", nargs="*", default=None, help=f"models (default: {' '.join(MODELS)})")
    args = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    info = machine()
    rows = []
    for model in args.only or list(MODELS):
        for setting in SETTINGS:
            r = measure(model, setting, args.res, args.runs)
            rows.append(r)
            print(
                f"{model:>12} {setting:>7}: V={r['vertices']:5d} sampling {r['bsv_sampling_ms']:7.1f} ms  "
                f"SH {r['sh_conversion_ms']:5.2f} ms  fused {r['bsv_fused_ms']:7.1f} ms  "
                f"shadowing {r['shadowing_ms']:6.1f} ms  {r['fps']:6.1f} Hz",
                flush=True,
            )
    info["load_avg_after"] = machine()["load_avg_1_5_15"]
    out = {"settings": vars(args), "machine": info, "rows": rows, "paper": PAPER}
    suffix = "" if not args.only else "_" + "_".join(args.only)
    (RESULTS / f"table1{suffix}.json").write_text(json.dumps(out, indent=2))
    md = markdown(rows)
    (RESULTS / f"table1{suffix}.md").write_text(
        f"# Table 1, measured\n\n`python experiments/table1.py` — {info['date']}, {info['cpu']} "
        f"({info['cores']} cores, {info['backend']}), load average {info['load_avg_1_5_15']} before, "
        f"{info['load_avg_after']} after.\n\n{md}"
    )
    print(md)


if __name__ == "__main__":
    main()
