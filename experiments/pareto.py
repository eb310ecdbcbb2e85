"""Run time against error of the shadow-field method, per scene, with the error decomposed.

Scenes (the calibration setting of DESIGN.md §2, at a modest receiver count): a constant
environment L = 1, no lights, a ``--res``² receiver plane (default 32²) over [−2, 2]² at y = 0 with
normal +y, and one occluder: ``sphere`` (radius 0.5 at (0, 1.2, 0) through the BSV path, i.e. the
analytic BSV of a sphere + M_k; directions play no part), ``bunny`` and ``spot`` (bounding radius
0.8 at (0, 1, 0)).

Sweep. Three method families, every key given explicitly (:func:`family`): ``default`` — the
library's accurate setting (shell R = 1.5 r with the edge-scan sampler, concentric-sphere rescaling,
BSV and M_k in n + 1 bands, ratio shading); ``paper`` — the deformable-shadow-fields paper exactly
(R = r, brute force, square-silhouette f_k, n-band BSV, SH products); ``shell1.5`` — the paper's
method with the BSV on a 1.5 r shell. Full factorial for ``default``: SH bands 3–6 × directions
8², 16², 32² × BSV grid 6×10, 12×20, 24×40; axis sweeps around 4 bands, 32², 12×20 for the other
two. Each configuration is rendered with :class:`jshadow.runner.Renderer` (BSV sampled every
frame, as for a deforming occluder); time per frame = BSV + field + combination, warm median of
``--runs`` (fresh renderers), compile separately.

Error: relative RMSE of irradiance against the exact irradiance ``E = ∫ V(ω) max(0, n·ω) dω``
(divided by the mean exact irradiance). The exact irradiance is computed by a deterministic
product quadrature over the upper hemisphere (Gauss–Legendre in cos θ × uniform φ, 128 × 256
directions per receiver, exact ray casting with :func:`jshadow.visibility.ray_fan_any_hit`)
instead of Monte Carlo: at the 0.1 % level that the smallest errors here need, the Monte Carlo
reference would need ~10⁵ spp per receiver. It is checked three ways and the checks are written
to the JSON: against the closed form for the sphere, against the same quadrature at 64 × 128 (the
difference bounds its own error) and against :func:`jshadow.reference` (Monte Carlo, ``--spp``;
the RMS of the differences over the reference's standard errors should be ≈ 1). Cached per scene
in ``experiments/results/pareto_ref_<scene>.npz``.

Decomposition, per number of bands n (cumulative, each a relative RMSE against the exact E):

* ``truncation``: the exact visibility at each receiver projected onto n bands (64² directions
  per hemisphere), times the clamped cosine — what any n-band method would get;
* ``+ shrinking``: the visibility sampled on the shell at the receiver's own direction (64²
  hemisphere directions, no BSV grid) and extrapolated with the family's M_k (model, bands) at the
  receiver's exact k (a 256-entry table), then truncated to n bands — the rescaling approximation
  on top of truncation (per family);
* ``+ interpolation`` (the method): bilinear BSV interpolation on the grid and the 16-entry M_k
  table, at the configuration's directions — read off the sweep.

Usage (repository root, project environment active)::

    python experiments/pareto.py [--scenes sphere bunny spot] [--res 32] [--runs 3] [--spp 2048]

Writes ``experiments/results/pareto.json`` and ``experiments/figures/pareto_<scene>.png``.
Default run: see BENCHMARKS.md for its duration.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import time
from functools import partial

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from _common import (  # noqa: E402
    FIGURES,
    RESULTS,
    ROOT,
    exact_visibility_sh,
    machine,
    make_scene,
    scene_dict,
    world_dirs,
)

import jshadow  # noqa: E402
from jshadow import sh  # noqa: E402
from jshadow.runner import Renderer  # noqa: E402
from jshadow.scaling import mk_apply, mk_table  # noqa: E402
from jshadow.visibility import bsv_frames, hemisphere_directions, ray_fan_any_hit  # noqa: E402

SCENES = {
    "sphere": {"model": "sphere", "center": (0.0, 1.2, 0.0), "radius": 0.5},
    "bunny": {"model": "bunny", "center": (0.0, 1.0, 0.0), "radius": 0.8},
    "spot": {"model": "spot", "center": (0.0, 1.0, 0.0), "radius": 0.8},
}
BANDS = (3, 4, 5, 6)
DIRECTIONS = ((8, 8), (16, 16), (32, 32))
GRIDS = ((6, 10), (12, 20), (24, 40))
DEFAULT = {"sh_bands": 4, "directions": (32, 32), "bsv_grid": (12, 20)}


def family(name: str, n: int) -> dict:
    """The method keys that define a family, for n bands (all given explicitly, so that the results
    do not depend on the library's defaults)."""
    if name == "default":  # the library's accurate setting
        return {"shell": 1.5, "model": "sphere", "bsv_bands": min(n + 1, 8), "shading": "ratio"}
    if name == "paper":  # the deformable-shadow-fields paper exactly (jshadow.entities.Method.paper)
        return {"shell": 1.0, "model": "paper", "bsv_bands": n, "shading": "product"}
    if name == "shell1.5":  # the paper's method with the BSV on a 1.5 r shell (edge-scan)
        return {"shell": 1.5, "model": "paper", "bsv_bands": n, "shading": "product"}
    raise ValueError(f"unknown family {name!r}")


FAMILIES = ("default", "paper", "shell1.5")
CONST_ENV = {"type": "constant", "radiance": [1.0, 1.0, 1.0]}


def build(name: str, res: int, method: dict):
    s = SCENES[name]
    d = scene_dict(
        s["model"], res=res, method=method, environment=CONST_ENV, center=s["center"], radius=s["radius"]
    )
    return make_scene(d)


def occluder_mesh(scene):
    occ = scene.occluders[0]
    if isinstance(occ, jshadow.entities.MeshOccluder):
        return occ.vertices(0.0), occ.faces
    from jshadow.geometry import icosphere

    ico = icosphere(4, dtype=jnp.float32)  # 2562 vertices; inscribed, faces within 0.1 % of the radius
    return occ.center + occ.radius * ico.vertices, ico.faces


def up_hemisphere(nt: int, nphi: int):
    """Upper (+y) hemisphere directions (K, 3) and cosine-weighted weights w·cos θ (K,)."""
    local, w = hemisphere_directions(nt, nphi, dtype=jnp.float32)
    dirs = jnp.stack([local[:, 0], local[:, 2], local[:, 1]], axis=-1)
    return dirs, w * local[:, 2]


@partial(jax.jit, static_argnames=())
def _irr_chunk(points, dirs, wcos, vertices, faces):
    hit = ray_fan_any_hit(points, jnp.broadcast_to(dirs, (points.shape[0], *dirs.shape)), vertices, faces)
    return jnp.sum(jnp.where(hit, 0.0, wcos), axis=-1)


def quadrature_irradiance(points, vertices, faces, nt: int, nphi: int, chunk: int = 32) -> np.ndarray:
    dirs, wcos = up_hemisphere(nt, nphi)
    out = [
        np.asarray(_irr_chunk(points[i : i + chunk], dirs, wcos, vertices, faces), np.float64)
        for i in range(0, points.shape[0], chunk)
    ]
    return np.concatenate(out)


def sphere_exact(points, center, radius) -> np.ndarray:
    """E = π (1 − sin²α cos β) (cap above the horizon; see experiments/calibration.py)."""
    v = np.asarray(center, np.float64) - np.asarray(points, np.float64)
    d = np.linalg.norm(v, axis=-1)
    return math.pi * (1.0 - (radius / d) ** 2 * v[:, 1] / d)


def reference(name: str, res: int, spp: int) -> dict:
    """Exact irradiance (N,) and its checks, cached in experiments/results/pareto_ref_<name>_<res>.npz.

    Meshes: the 128 × 256 quadrature is the exact value, the 64 × 128 one a check. Sphere: the
    closed form is the exact value, the 64 × 128 quadrature of a 4-times subdivided icosphere (5120
    faces, inscribed: 0.1 % smaller) the check.
    """
    path = RESULTS / f"pareto_ref_{name}_{res}.npz"
    if path.exists():
        z = np.load(path)
        return {k: z[k] for k in z.files}
    t0 = time.perf_counter()
    scene = build(name, res, {})
    points = scene.receivers.points
    v, f = occluder_mesh(scene)
    out = {"coarse": quadrature_irradiance(points, v, f, 64, 128)}
    if name == "sphere":
        s = SCENES[name]
        out["exact"] = out["closed_form"] = sphere_exact(np.asarray(points), s["center"], s["radius"])
    else:
        out["exact"] = quadrature_irradiance(points, v, f, 128, 256)
    mc = jshadow.reference(scene, spp, jax.random.PRNGKey(7))
    out["mc"] = np.asarray(mc.irradiance[:, 0], np.float64)
    out["mc_stderr"] = np.asarray(mc.irradiance_stderr[:, 0], np.float64)
    out["seconds"] = np.asarray(time.perf_counter() - t0)
    np.savez_compressed(path, **out)
    return out


def rel_rmse(a, b) -> float:
    return float(np.sqrt(np.mean((np.asarray(a, np.float64) - b) ** 2)) / np.mean(b))


@partial(jax.jit, static_argnames=("directions",))
def _shell_sh(points, center, shell_radius, vertices, faces, *, directions):
    """Visibility SH (8 bands) on the shell at each receiver's own direction, local frame."""
    rel = points - center
    u = rel / jnp.linalg.norm(rel, axis=-1, keepdims=True)
    theta = jnp.arccos(jnp.clip(u[:, 2], -1.0, 1.0))
    phi = jnp.arctan2(u[:, 1], u[:, 0])
    _, frames = bsv_frames(theta, phi)
    local, w = hemisphere_directions(*directions, dtype=points.dtype)
    occ = ray_fan_any_hit(center + shell_radius * u, world_dirs(frames, local), vertices, faces)
    full = jnp.zeros(64, points.dtype).at[0].set(math.sqrt(4.0 * math.pi))
    return full - occ.astype(points.dtype) @ (sh.sh_basis(local, 8) * w[:, None]), frames


def decomposition(name: str, res: int, fam: str, exact: np.ndarray) -> dict:
    """Cumulative error per band count for a method family: truncation, + shrinking (the family's
    shell, rescaling model and BSV bands; see the module docstring)."""
    shell = family(fam, 4)["shell"]
    scene = build(name, res, {"shell": shell})
    occ = scene.occluders[0]
    points = scene.receivers.points
    normals = jnp.tile(jnp.asarray([0.0, 1.0, 0.0], jnp.float32), (points.shape[0], 1))
    if name == "sphere":  # exact visibility and the method's BSV are analytic caps
        from jshadow.field import sphere_visibility_sh
        from jshadow.visibility import bsv_sphere

        s_ex = sphere_visibility_sh(occ.center, occ.radius, points, 6)
        cap = bsv_sphere(occ.center, occ.radius, n=8, grid=(1, 1), shell=shell).coeffs[0, 0]
        rel = points - occ.center
        u = rel / jnp.linalg.norm(rel, axis=-1, keepdims=True)
        _, frames = bsv_frames(jnp.arccos(jnp.clip(u[:, 2], -1.0, 1.0)), jnp.arctan2(u[:, 1], u[:, 0]))
        s_r = jnp.broadcast_to(cap, (points.shape[0], 64))
    else:
        v, f = occluder_mesh(scene)
        s_ex = exact_visibility_sh(points, v, f, n=6, directions=(64, 64))
        s_r, frames = _shell_sh(points, occ.center, shell * occ.radius, v, f, directions=(64, 64))
    d = jnp.linalg.norm(points - occ.center, axis=-1)
    k = shell * occ.radius / d
    out = {}
    for n in BANDS:
        t = sh.clamped_cosine(normals, n)
        e_trunc = np.asarray(jnp.sum(s_ex[:, : n * n] * t, -1))
        f = family(fam, n)
        nf = f["bsv_bands"]
        table = mk_table(n=nf, num=256, d_min=0.2, d_max=8.0, model=f["model"], dtype=jnp.float32)
        s_d = sh.rotate(mk_apply(table, k, s_r[:, : nf * nf]), frames)[:, : n * n]
        e_shrink = np.asarray(jnp.sum(s_d * t, -1))
        out[n] = {"truncation": rel_rmse(e_trunc, exact), "shrinking": rel_rmse(e_shrink, exact)}
    return out


def time_config(scene, sphere_path: str, runs: int) -> tuple[np.ndarray, dict]:
    t0 = time.perf_counter()
    res, _ = Renderer(scene, sphere_path).frame(0)
    first = 1e3 * (time.perf_counter() - t0)
    stages = [Renderer(scene, sphere_path).frame(0)[1] for _ in range(runs)]
    med = {k: float(np.median([s[k] for s in stages])) for k in stages[0]}
    med["first_call_ms"] = first
    return np.asarray(res.irradiance[:, 0], np.float64), med


def configs(name: str):
    """(family, method keys): the full factorial for the default family, axis sweeps around
    :data:`DEFAULT` for the others."""
    dirs = DIRECTIONS if name != "sphere" else ((32, 32),)  # the sphere's BSV is analytic
    for n, dr, g in itertools.product(BANDS, dirs, GRIDS):
        yield "default", {"sh_bands": n, "directions": dr, "bsv_grid": g, **family("default", n)}
    for fam in FAMILIES[1:]:
        seen = []
        for key, values in (("sh_bands", BANDS), ("directions", dirs), ("bsv_grid", GRIDS)):
            for val in values:
                m = {**DEFAULT, key: val}
                if m not in seen:
                    seen.append(m)
                    yield fam, {**m, **family(fam, m["sh_bands"])}


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], math.inf
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


def plot(name: str, rows: list[dict], decomp: dict, path):
    fig, ax = plt.subplots(figsize=(8.0, 4.4), dpi=100)
    colors = dict(zip(BANDS, plt.get_cmap("viridis")(np.linspace(0.0, 0.9, len(BANDS))), strict=True))
    markers = dict(zip(GRIDS, ("v", "o", "s", "D", "^"), strict=False))
    sizes = {d: 10 + 50 * i / max(len(DIRECTIONS) - 1, 1) for i, d in enumerate(DIRECTIONS)}
    for r in rows:
        m = r["method"]
        ax.scatter(
            r["frame_ms"],
            100 * r["rel_rmse"],
            color=colors.get(m["sh_bands"], "gray"),
            marker=markers.get(tuple(m["bsv_grid"]), "x"),
            s=sizes.get(tuple(m["directions"]), 30),
            edgecolors={"default": "none", "paper": "k", "shell1.5": "r"}[r["family"]],
            linewidths=0.8,
        )
    pts = [(r["frame_ms"], r["rel_rmse"]) for r in rows]
    front = pareto_front(pts)
    ax.plot([pts[i][0] for i in front], [100 * pts[i][1] for i in front], "k--", lw=0.8, label="Pareto front")
    for n in BANDS:
        for key, ls in (("truncation", ":"), ("shrinking", "-.")):
            ax.axhline(100 * decomp["default"][str(n)][key], color=colors[n], ls=ls, lw=0.9)
    for n in BANDS:
        ax.scatter([], [], color=colors[n], label=f"{n} bands")
    for g in GRIDS:
        ax.scatter([], [], color="gray", marker=markers[g], label=f"BSV {g[0]}×{g[1]}")
    ax.plot([], [], "k:", lw=0.9, label="SH truncation (n bands)")
    ax.plot([], [], "k-.", lw=0.9, label="+ shrinking (default family)")
    ax.scatter([], [], color="gray", label="default (shell 1.5, sphere model,\nn+1 BSV bands, ratio)")
    ax.scatter([], [], facecolors="none", edgecolors="k", label="paper (shell 1, f_k, product)")
    ax.scatter([], [], facecolors="none", edgecolors="r", label="paper's method, shell 1.5")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("time per frame, BSV + field + combination [ms] (marker size: directions 8², 16², 32²)")
    ax.set_ylabel("relative RMSE of irradiance [%]")
    ax.set_title(
        f"{name}: error vs time (constant environment, {rows[0]['receivers']} receivers)", fontsize=9
    )
    ax.legend(fontsize=6, loc="center left", bbox_to_anchor=(1.01, 0.5))
    ax.xaxis.label.set_fontsize(7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main() -> None:
    global BANDS, DIRECTIONS, GRIDS
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="*", default=list(SCENES))
    ap.add_argument("--res", type=int, default=32, help="receiver plane resolution (res × res)")
    ap.add_argument("--runs", type=int, default=3, help="warm runs per configuration (median)")
    ap.add_argument("--spp", type=int, default=2048, help="Monte Carlo spp of the reference check")
    ap.add_argument("--bands", type=int, nargs="+", default=list(BANDS))
    ap.add_argument(
        "--dirs", type=int, nargs="+", default=[d[0] for d in DIRECTIONS], help="n: n² directions"
    )
    ap.add_argument("--grids", nargs="+", default=[f"{t}x{p}" for t, p in GRIDS], help="TxP BSV grids")
    ap.add_argument("--replot", action="store_true", help="only redraw the figures from pareto.json")
    args = ap.parse_args()
    if args.replot:
        data = json.loads((RESULTS / "pareto.json").read_text())
        for name, sc in data["scenes"].items():
            plot(name, sc["rows"], sc["decomposition"], ROOT / sc["figure"])
        return
    BANDS = tuple(args.bands)
    DIRECTIONS = tuple((d, d) for d in args.dirs)
    GRIDS = tuple(tuple(int(x) for x in g.split("x")) for g in args.grids)
    t_start = time.perf_counter()
    info = machine()
    path = RESULTS / "pareto.json"
    data = json.loads(path.read_text()) if path.exists() else {"scenes": {}}
    for name in args.scenes:
        ref = reference(name, args.res, args.spp)
        exact = ref["exact"]
        noisy = ref["mc_stderr"] > 1e-4 * np.mean(exact)
        checks = {
            "coarse_quadrature_vs_exact_rel_rmse": rel_rmse(ref["coarse"], ref["exact"]),
            "mc_spp": args.spp,
            "mc_rel_rmse_vs_exact": rel_rmse(ref["mc"], exact),
            # receivers that see the whole environment have zero Monte Carlo variance: z over the others
            "mc_rms_z": float(np.sqrt(np.mean(((ref["mc"] - exact)[noisy] / ref["mc_stderr"][noisy]) ** 2))),
            "mc_max_abs_err_zero_variance_rel": float(
                np.max(np.abs(ref["mc"] - exact)[~noisy], initial=0.0) / np.mean(exact)
            ),
            "mc_stderr_rel": float(np.sqrt(np.mean(ref["mc_stderr"] ** 2)) / np.mean(exact)),
            "reference_seconds": float(ref["seconds"]),
        }
        if "closed_form" in ref:
            checks["quadrature_vs_closed_form_rel_rmse"] = rel_rmse(ref["coarse"], ref["closed_form"])
        decomp = {
            fam: {str(n): e for n, e in decomposition(name, args.res, fam, exact).items()} for fam in FAMILIES
        }
        rows = []
        for fam, m in configs(name):
            scene = build(name, args.res, m)
            irr, ms = time_config(scene, "bsv" if name == "sphere" else "analytic", args.runs)
            rows.append(
                {
                    "family": fam,
                    "method": m,
                    "receivers": int(irr.shape[0]),
                    "rel_rmse": rel_rmse(irr, exact),
                    "frame_ms": ms["total_ms"],
                    "stages_ms": ms,
                }
            )
            print(
                f"{name:>6} {fam:>8} n={m['sh_bands']} dirs={m['directions'][0]:2d}² "
                f"grid={m['bsv_grid'][0]:2d}×{m['bsv_grid'][1]:2d}: {100 * rows[-1]['rel_rmse']:6.2f} %  "
                f"{ms['total_ms']:7.1f} ms  (compile+first {ms['first_call_ms'] / 1e3:.1f} s)",
                flush=True,
            )
        smallest = min(r["rel_rmse"] for r in rows)
        checks["smallest_error"] = smallest
        checks["quadrature_error_over_smallest"] = checks["coarse_quadrature_vs_exact_rel_rmse"] / smallest
        front = pareto_front([(r["frame_ms"], r["rel_rmse"]) for r in rows])
        png = FIGURES / f"pareto_{name}.png"
        plot(name, rows, decomp, png)
        data["scenes"][name] = {
            "scene": SCENES[name],
            "reference_checks": checks,
            "decomposition": decomp,
            "rows": rows,
            "pareto_front": [
                rows[i]["method"]
                | {
                    "family": rows[i]["family"],
                    "rel_rmse": rows[i]["rel_rmse"],
                    "frame_ms": rows[i]["frame_ms"],
                }
                for i in front
            ],
            "figure": str(png.relative_to(ROOT)),
            "machine": info,
        }
        print(f"{name}: checks {checks}", flush=True)
    data["settings"] = vars(args)
    data["total_s"] = time.perf_counter() - t_start
    data["machine_after"] = machine()
    path.write_text(json.dumps(data, indent=2))
    print(f"total {data['total_s']:.0f} s")


if __name__ == "__main__":
    main()
