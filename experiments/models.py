"""Extrapolation models against the Monte Carlo reference: the paper's method and better ones.

The deformable-shadow-fields paper extrapolates the base-sphere visibility (BSV) to a receiver at
distance d with M_k built from a square-silhouette rescaling f_k, samples the BSV on the bounding
sphere itself and warps visibility that was already truncated to the lighting's n bands; Zhou et
al. 2005 combine everything as n-band SH products. This script measures, per scene, the error of
that method and of the options :class:`jshadow.entities.Method` offers beyond it:

* ``shell`` — sample the BSV on a shell of ``shell`` × the bounding radius (no sample point on the
  surface; enables the edge-scan sampler);
* ``model="sphere"`` — the concentric-sphere rescaling ``asin(k sin θ)`` instead of f_k;
* ``bsv_bands`` — sample and extrapolate visibility with more bands than the lighting, truncating
  after M_k;
* ``shading="ratio"`` — exact unoccluded irradiance (closed form for sphere lights, a tabulated
  irradiance map for the environment) times the SH occluded/unoccluded ratio clamped to [0, 1].

Scenes: the two calibration scenes of DESIGN.md §2 (bunny and a BSV-path sphere under a constant
sky), every shipped render config (receiver plane reduced to ``--res``²; bunny_studio keeps its
self-shadowed vertices, reported separately) and scenes no option was tuned on (other meshes,
deformations, sphere lights, several occluders, self-shadowing under a constant sky). References
are Monte Carlo (:func:`jshadow.reference`, exact visibility; projected spherical caps for sphere
lights) with spp raised until the reference's RMS standard error is at most ``--target`` of the
mean irradiance; they are cached in
``experiments/results/refs/`` (delete a file to recompute it). The sphere calibration uses its
closed form instead.

Errors are relative to the mean reference irradiance (RGB): relative RMSE, max error, and the
largest excess over the *unoccluded* irradiance (the reference of the scene without occluders) in %
— ringing that makes shadowed scenes brighter than unlit ones. Times: median warm frame (BSV +
field + combination, each stage compiled once) of :class:`jshadow.runner.Renderer` on fresh
renderers, so BSV sampling is included; measured in the same run for every variant.

Usage (repository root, project environment active)::

    python experiments/models.py [--res 32] [--target 0.001] [--cases ...] [--variants ...]

Writes ``experiments/results/models.json``, ``experiments/figures/models_pareto.png`` (error against
time per frame, per scene) and ``experiments/figures/models_maps.png`` (error maps of the paper and
the default).
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import pathlib
import platform
import time
import tomllib

import jax
import jax.numpy as jnp
import matplotlib
import matplotlib.ticker
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import jshadow  # noqa: E402
from jshadow import sh  # noqa: E402
from jshadow.config import build_scene, config_from_dict  # noqa: E402
from jshadow.config._build import plane_receivers  # noqa: E402
from jshadow.entities import Environment, MeshOccluder, Method, Scene, SphereLight, SphereOccluder  # noqa: E402
from jshadow.geometry import egg, load_mesh, make_deformation, normalize_to_unit_sphere  # noqa: E402
from jshadow.runner import Renderer  # noqa: E402
from jshadow.scene import clear_pose_caches  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"
ASSETS = ROOT / "assets"
RESULTS = ROOT / "experiments" / "results"
REFS = RESULTS / "refs"
FIGURES = ROOT / "experiments" / "figures"

# method variants: label -> [method] keys (on top of the scene's own sizes: bands, grid, directions)
VARIANTS = {
    "paper": dict(shell=1.0, model="paper", bsv_bands=4, shading="product", bsv_center="box"),
    "shell1.5": dict(shell=1.5, model="paper", bsv_bands=4, shading="product"),
    "sphere": dict(shell=1.5, model="sphere", bsv_bands=4, shading="product"),
    "sphere+b5": dict(shell=1.5, model="sphere", bsv_bands=5, shading="product"),
    "ratio": dict(shell=1.5, model="paper", bsv_bands=4, shading="ratio"),
    "sphere+ratio": dict(shell=1.5, model="sphere", bsv_bands=4, shading="ratio"),
    "sphere+b5+ratio": dict(shell=1.5, model="sphere", bsv_bands=5, shading="ratio"),
    # diagnostics: the default with more lighting bands (is the rest of the error band-limited?)
    "default n6": dict(sh_bands=6, shell=1.5, model="sphere", bsv_bands=7, shading="ratio"),
    "default n8": dict(sh_bands=8, shell=1.5, model="sphere", bsv_bands=8, shading="ratio"),
}
DEFAULT_VARIANT = "sphere+b5+ratio"


# ---- scenes ----------------------------------------------------------------------------------------


def _plane(res: int, size: float = 4.0):
    return plane_receivers(
        jnp.zeros(3, jnp.float32),
        jnp.asarray([size, size], jnp.float32),
        (res, res),
        jnp.asarray([0.8, 0.8, 0.8], jnp.float32),
    )


def _mesh(file: str, center, radius, deform=None) -> MeshOccluder:
    m = load_mesh(ASSETS / file, dtype=jnp.float32) if isinstance(file, str) else file
    return MeshOccluder(
        unit_vertices=normalize_to_unit_sphere(m.vertices),
        faces=m.faces,
        center=jnp.asarray(center, jnp.float32),
        radius=jnp.asarray(radius, jnp.float32),
        deform=deform,
        name=file if isinstance(file, str) else "mesh",
    )


def _scene(method: dict, occluders, lights=(), env=None, res=32, n_frames=1, self_shadow=False) -> Scene:
    return Scene(
        method=Method(**method),
        receivers=_plane(res),
        occluders=tuple(occluders),
        lights=tuple(lights),
        environment=env,
        self_shadow=self_shadow,
        n_frames=n_frames,
    )


def _sky(kind="constant", rgb=(1.0, 1.0, 1.0)):
    return Environment(radiance=jnp.asarray(rgb, jnp.float32), kind=kind)


def _config_scene(file: str, res: int, method: dict):
    path = CONFIGS / file
    d = copy.deepcopy(tomllib.loads(path.read_text()))
    d.setdefault("receiver", {})["resolution"] = [res, res]
    m = d.setdefault("method", {})
    m.update({k: v for k, v in method.items() if v is not None})
    if method.get("bsv_bands") is None:
        m.pop("bsv_bands", None)
    # the variants are Method keywords, whose light path is the n-band one unless they say otherwise
    # (a config's "auto" would take the occlusion images where they apply, experiments/defaults.py)
    m.setdefault("light_visibility", "sh")
    m.setdefault("environment_lights", 0)
    return build_scene(config_from_dict(d, source=str(path), root=path.parent))


def _sphere_light():
    return SphereLight(
        center=jnp.asarray([1.6, 3.2, 0.8], jnp.float32),
        radius=jnp.asarray(0.6, jnp.float32),
        radiance=jnp.asarray([6.0, 6.0, 6.0], jnp.float32),
    )


# name -> (builder(method, res) -> Scene, frame, sphere_path, tuned?)
def _cases():
    cal = 40  # the calibration grid of DESIGN.md §2
    return {
        "calib_bunny": (
            lambda m, r: _scene(m, [_mesh("bunny.obj", (0, 1, 0), 0.8)], env=_sky(), res=cal),
            0,
            "analytic",
            True,
        ),
        "calib_sphere_bsv": (
            lambda m, r: _scene(
                m, [SphereOccluder(jnp.asarray([0, 1.2, 0.0]), jnp.asarray(0.5))], env=_sky(), res=cal
            ),
            0,
            "bsv",
            True,
        ),
        "sphere": (lambda m, r: _config_scene("sphere.toml", r, m), 0, "analytic", False),
        "bunny_studio": (lambda m, r: _config_scene("bunny_studio.toml", r, m), 0, "analytic", False),
        "spot_sunset": (lambda m, r: _config_scene("spot_sunset.toml", r, m), 0, "analytic", False),
        "airplane_bend_last": (lambda m, r: _config_scene("airplane_bend.toml", r, m), 23, "analytic", False),
        "egg_breathing": (lambda m, r: _config_scene("egg_breathing.toml", r, m), 0, "analytic", False),
        # its last frame (twist 0.8), with the bunny's 1901 own vertices among the receivers
        "bunny_animated_last": (
            lambda m, r: _config_scene("bunny_animated.toml", r, m),
            47,
            "analytic",
            False,
        ),
        # untuned: other meshes / deformations / lights / several occluders
        "spot_sky_light": (
            lambda m, r: _scene(
                m,
                [_mesh("spot.obj", (0.2, 0.9, -0.1), 0.7)],
                [_sphere_light()],
                env=_sky("sky", (0.6, 0.7, 0.9)),
                res=r,
            ),
            0,
            "analytic",
            False,
        ),
        "twisted_airplane_sky": (
            lambda m, r: _scene(
                m,
                [_mesh("airplane.obj", (0, 1.1, 0), 0.9, make_deformation("twist", 0.8, axis="x"))],
                env=_sky("sky"),
                res=r,
            ),
            0,
            "analytic",
            False,
        ),
        # self-shadowing under smooth lighting: the bunny's own 1901 vertices are receivers too
        "bunny_self_sky": (
            lambda m, r: _scene(m, [_mesh("bunny.obj", (0, 1, 0), 0.8)], env=_sky(), res=r, self_shadow=True),
            0,
            "analytic",
            False,
        ),
        # the same, twisted (a constant deformation: the shape differs from the rest pose)
        "bunny_self_sky_twist": (
            lambda m, r: _scene(
                m,
                [_mesh("bunny.obj", (0, 1, 0), 0.8, make_deformation("twist", 1.2, axis="y"))],
                env=_sky(),
                res=r,
                self_shadow=True,
            ),
            0,
            "analytic",
            False,
        ),
        "three_occluders": (
            lambda m, r: _scene(
                m,
                [
                    _mesh("bunny_small.obj", (-0.9, 0.8, 0.3), 0.55),
                    _mesh(egg(2, dtype=jnp.float32), (0.8, 0.7, -0.4), 0.45),
                    SphereOccluder(jnp.asarray([0.3, 1.6, 0.9]), jnp.asarray(0.35)),
                ],
                [_sphere_light()],
                env=_sky(),
                res=r,
            ),
            0,
            "bsv",
            False,
        ),
    }


# ---- reference -------------------------------------------------------------------------------------


def _sphere_exact(points: np.ndarray) -> np.ndarray:
    c = np.asarray([0, 1.2, 0.0])
    v = c - np.asarray(points, np.float64)
    d = np.linalg.norm(v, axis=-1)
    return np.repeat((math.pi * (1.0 - (0.5 / d) ** 2 * v[:, 1] / d))[:, None], 3, 1)


def _bare(scene: Scene) -> Scene:
    return Scene(
        method=scene.method,
        receivers=scene.receivers,
        occluders=(),
        lights=scene.lights,
        environment=scene.environment,
        self_shadow=False,
        n_frames=scene.n_frames,
    )


def _mc(scene, frame, target, max_spp, seed):
    """Monte Carlo mean and stderr with spp doubled until stderr_rms ≤ target · mean."""
    spp, acc = 0, None
    step = 1024
    while True:
        r = jshadow.reference(scene, step, jax.random.PRNGKey(seed + spp), frame=frame)
        m, s = np.asarray(r.irradiance, np.float64), np.asarray(r.irradiance_stderr, np.float64)
        if acc is None:
            acc = (step, m, s)
        else:
            n0, m0, s0 = acc
            n = n0 + step
            acc = (n, (n0 * m0 + step * m) / n, np.sqrt((n0 * s0) ** 2 + (step * s) ** 2) / n)
        spp = acc[0]
        ratio = float(np.sqrt(np.mean(acc[2] ** 2)) / np.mean(acc[1]))
        if ratio <= target or spp >= max_spp:
            return acc, ratio
        step = spp


def reference(name, scene, frame, target, max_spp, seed=0):
    """Cached reference of a case: dict(mean, stderr, spp, unoccluded, seconds)."""
    REFS.mkdir(parents=True, exist_ok=True)
    path = REFS / f"{name}.npz"
    if path.exists():
        z = np.load(path)
        return {k: z[k] for k in z.files}
    t0 = time.perf_counter()
    if name == "calib_sphere_bsv":
        pts, _ = jshadow.entities.receivers_at(scene, frame)
        mean = _sphere_exact(np.asarray(pts))
        out = dict(mean=mean, stderr=np.zeros_like(mean), spp=np.asarray(0), ratio=np.asarray(0.0))
        out["unoccluded"] = np.full_like(mean, math.pi)
    else:
        (spp, mean, stderr), ratio = _mc(scene, frame, target, max_spp, seed)
        (_, un, _), _ = _mc(_bare(scene), frame, target, max_spp // 4, seed + 7)
        out = dict(mean=mean, stderr=stderr, spp=np.asarray(spp), ratio=np.asarray(ratio), unoccluded=un)
    out["seconds"] = np.asarray(time.perf_counter() - t0)
    np.savez_compressed(path, **out)
    return out


# ---- measurement -----------------------------------------------------------------------------------


def _fresh_frame(scene, frame, sphere_path):
    """A fresh renderer's frame, nothing kept from an earlier one of the same pose."""
    clear_pose_caches()
    return Renderer(scene, sphere_path).frame(frame)


# a timing's warm samples are taken until they sum to this many ms (at least `runs`, at most
# MAX_SAMPLES): a sub-millisecond frame's median of 3 varied by 1.36-1.65x between runs
MIN_SAMPLED_MS = 200.0
MAX_SAMPLES = 401


def sampled_ms(sample, runs: int) -> float:
    """Median of the ms that ``sample()`` returns, over ``runs`` calls or as many more as make
    :data:`MIN_SAMPLED_MS` in all (at most :data:`MAX_SAMPLES`)."""
    ms = [sample() for _ in range(runs)]
    while sum(ms) < MIN_SAMPLED_MS and len(ms) < MAX_SAMPLES:
        ms.append(sample())
    return float(np.median(ms))


def timed(scene, frame, sphere_path, runs=3):
    """The frame's irradiance, its first call's ms (trace and compile included) and the median ms
    of its fresh warm frames (:func:`sampled_ms`)."""
    t0 = time.perf_counter()
    res, _ = _fresh_frame(scene, frame, sphere_path)
    first = 1e3 * (time.perf_counter() - t0)
    warm = sampled_ms(lambda: _fresh_frame(scene, frame, sphere_path)[1]["total_ms"], runs)
    return np.asarray(res.irradiance, np.float64), first, warm


def errors(approx, ref, n_plane):
    mean = float(np.mean(ref["mean"]))
    diff = approx - ref["mean"]
    out = {
        "rel_rmse_pct": 100 * float(np.sqrt(np.mean(diff**2))) / mean,
        "max_rel_err_pct": 100 * float(np.max(np.abs(diff))) / mean,
        "ref_stderr_pct": 100 * float(np.sqrt(np.mean(ref["stderr"] ** 2))) / mean,
    }
    p = slice(0, n_plane)
    mp = float(np.mean(ref["mean"][p]))
    out["plane_rel_rmse_pct"] = 100 * float(np.sqrt(np.mean(diff[p] ** 2))) / mp
    out["plane_max_rel_err_pct"] = 100 * float(np.max(np.abs(diff[p]))) / mp
    excess = (approx[p] - ref["unoccluded"]) / mp
    out["max_excess_over_unoccluded_pct"] = 100 * float(max(np.max(excess), 0.0))
    if approx.shape[0] > n_plane:
        v = slice(n_plane, None)
        mv = float(np.mean(ref["mean"][v]))
        out["vertices_rel_rmse_pct"] = 100 * float(np.sqrt(np.mean(diff[v] ** 2))) / mv
        out["vertices_max_rel_err_pct"] = 100 * float(np.max(np.abs(diff[v]))) / mv
    return out


def plot(results: dict) -> list[str]:
    """Pareto plot (error against time per frame, one panel per scene) and error maps."""
    FIGURES.mkdir(parents=True, exist_ok=True)
    cases = [c for c in _cases() if c in results["cases"]]
    cols = 4
    rows = -(-len(cases) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 2.9 * rows), dpi=100, squeeze=False)
    marks = dict(zip(VARIANTS, "osD^v<>Px", strict=False))
    for ax, name in zip(axes.flat, cases, strict=False):
        for label, v in results["cases"][name]["variants"].items():
            ax.scatter(
                v["warm_ms"],
                v["rel_rmse_pct"],
                marker=marks.get(label, "x"),
                s=28,
                label=label,
                edgecolor="k" if label == DEFAULT_VARIANT else None,
            )
        ax.set_xscale("log")
        ax.set_yscale("log")
        for axis in (ax.xaxis, ax.yaxis):  # minor-tick labels of short log ranges overlap
            axis.set_major_locator(matplotlib.ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
            axis.set_minor_formatter(matplotlib.ticker.NullFormatter())
            axis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.axhline(1.0, color="0.6", lw=0.8, ls="--")
        ax.set_title(name + ("" if results["cases"][name]["tuned"] is False else " (tuned on)"), fontsize=8)
        ax.set_xlabel("ms per frame (warm)", fontsize=7)
        ax.set_ylabel("rel. RMSE [%]", fontsize=7)
        ax.tick_params(labelsize=6)
    for ax in list(axes.flat)[len(cases) :]:
        ax.axis("off")
    axes.flat[0].legend(fontsize=6, loc="best")
    fig.tight_layout()
    paths = [FIGURES / "models_pareto.png"]
    fig.savefig(paths[0])
    plt.close(fig)
    maps = [c for c in cases if (REFS / f"{c}.default.npy").exists() and (REFS / f"{c}.paper.npy").exists()]
    fig, axes = plt.subplots(2, len(maps), figsize=(2.3 * len(maps), 4.6), dpi=100, squeeze=False)
    for j, name in enumerate(maps):
        ref = np.load(REFS / f"{name}.npz")["mean"]
        n_plane = results["cases"][name]["plane_receivers"]
        side = int(round(math.sqrt(n_plane)))
        for i, label in enumerate(("paper", "default")):
            approx = np.load(REFS / f"{name}.{label}.npy")
            err = ((approx - ref)[:n_plane].mean(1) / ref[:n_plane].mean()).reshape(side, side)
            im = axes[i, j].imshow(100 * err, cmap="RdBu_r", vmin=-10, vmax=10, origin="lower")
            axes[i, j].set_xticks([])
            axes[i, j].set_yticks([])
            if i == 0:
                axes[i, j].set_title(name, fontsize=7)
            if j == 0:
                axes[i, j].set_ylabel("paper" if i == 0 else "default", fontsize=8)
    fig.colorbar(im, ax=axes, shrink=0.8, label="(render − reference) / mean [%]")
    paths.append(FIGURES / "models_maps.png")
    fig.savefig(paths[1])
    plt.close(fig)
    return [str(p.relative_to(ROOT)) for p in paths]


def srf_study() -> dict:
    """Sphere-light radiance fields (the SRF path) against the closed form, on the light's axis.

    A unit-radiance light of radius 1 at distance d faces a receiver; the exact irradiance is
    π sin²α = π/d². Rows: the paper's SRF (f_k with its Jacobian, shell 1), the concentric-sphere
    model without a Jacobian (shell 1 and 1.5, table bands 4, 5 and 8, truncated to 4 after M_k; and
    the m = 0 block alone in 48 bands, :func:`jshadow.scaling.mk_zonal_table`), and the closed-form cap
    in 4 bands (its only error is the truncated cosine).
    """
    from jshadow.lights import sphere_light_sh, sphere_light_srf
    from jshadow.scaling import mk_table, mk_zonal_table

    dists = [1.05, 1.2, 1.6, 2.0, 3.0, 4.0, 6.0, 10.0, 16.0, 24.0, 32.0, 48.0]
    settings = {
        "paper (f_k, Jacobian, shell 1)": ("paper", "radiance_jacobian", 1.0, 4),
        "sphere model, shell 1, 4 bands": ("sphere", "radiance", 1.0, 4),
        "sphere model, shell 1.5, 5 bands": ("sphere", "radiance", 1.5, 5),
        "sphere model, shell 1.5, 8 bands": ("sphere", "radiance", 1.5, 8),
        "sphere model, shell 1.5, 48 zonal bands": ("sphere", "radiance", 1.5, "zonal"),
    }
    normal = jnp.asarray([0.0, 0.0, 1.0])
    cosine = sh.clamped_cosine(normal, 4)
    out = {"distances": dists, "exact": [math.pi / d**2 for d in dists], "relative_error_pct": {}}
    for name, (model, kind, shell, bands) in settings.items():
        if bands == "zonal":  # the m = 0 block alone (the light's radiance is zonal), 64 distances
            table = mk_zonal_table(48, num=64, d_min=0.2, d_max=32.0, kind=kind, model=model)
        else:
            table = mk_table(n=bands, num=32, d_min=0.2, d_max=16.0, kind=kind, model=model)
        errs = []
        for d in dists:
            l_sh = sphere_light_srf(
                jnp.asarray([0.0, 0.0, d]), 1.0, jnp.ones(3), jnp.zeros(3), 4, table, shell
            )
            errs.append(100 * (float((cosine @ l_sh)[0]) * d**2 / math.pi - 1.0))
        out["relative_error_pct"][name] = errs
    cap = [
        float((cosine @ sphere_light_sh(jnp.asarray([0.0, 0.0, d]), 1.0, jnp.ones(3), jnp.zeros(3), 4))[0])
        for d in dists
    ]
    out["relative_error_pct"]["closed-form cap, 4 bands"] = [
        100 * (c * d**2 / math.pi - 1.0) for c, d in zip(cap, dists, strict=True)
    ]
    # against the analytic counterpart (the same 4-band clamped cosine on both sides)
    closed = out["relative_error_pct"]["closed-form cap, 4 bands"]
    out["relative_to_closed_form_pct"] = {
        name: [100 * ((1 + e / 100) / (1 + c / 100) - 1) for e, c in zip(errs, closed, strict=True)]
        for name, errs in out["relative_error_pct"].items()
        if name != "closed-form cap, 4 bands"
    }
    for name, errs in out["relative_to_closed_form_pct"].items():
        print(f"SRF against the closed form, {name:36s} " + "  ".join(f"{e:+7.2f} %" for e in errs))
    for name, errs in out["relative_error_pct"].items():
        print(
            f"SRF {name:36s} " + "  ".join(f"d={d:g}: {e:+8.1f} %" for d, e in zip(dists, errs, strict=True))
        )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--res", type=int, default=32, help="receiver plane resolution of shipped/untuned scenes")
    ap.add_argument("--target", type=float, default=0.001, help="reference stderr_rms / mean irradiance")
    ap.add_argument("--max-spp", type=int, default=32768)
    ap.add_argument("--cases", nargs="*", default=None)
    ap.add_argument("--variants", nargs="*", default=None)
    ap.add_argument("--runs", type=int, default=3, help="warm frames timed per variant")
    ap.add_argument("--plot-only", action="store_true", help="redraw the figures from models.json")
    ap.add_argument("--srf-only", action="store_true", help="only the sphere-light SRF study")
    args = ap.parse_args()
    out_path = RESULTS / "models.json"
    if args.srf_only:
        results = json.loads(out_path.read_text())
        results["srf"] = srf_study()
        out_path.write_text(json.dumps(results, indent=1))
        return
    if args.plot_only:
        results = json.loads(out_path.read_text())
        results["figures"] = plot(results)
        out_path.write_text(json.dumps(results, indent=1))
        return
    cases = _cases()
    names = args.cases or list(cases)
    variants = args.variants or list(VARIANTS)
    results = json.loads(out_path.read_text()) if out_path.exists() else {"cases": {}}
    t_start = time.perf_counter()
    for name in names:
        build, frame, sphere_path, tuned = cases[name]
        base = build(VARIANTS["paper"], args.res)
        ref = reference(name, base, frame, args.target, args.max_spp)
        n_plane = int(np.prod(base.receivers.grid_shape))
        row = results["cases"].setdefault(name, {"variants": {}})
        row.update(
            tuned=tuned,
            frame=frame,
            receivers=int(ref["mean"].shape[0]),
            plane_receivers=n_plane,
            ref_spp=int(ref["spp"]),
            ref_stderr_pct=100 * float(np.sqrt(np.mean(ref["stderr"] ** 2)) / np.mean(ref["mean"])),
            ref_seconds=float(ref["seconds"]),
        )
        for label in variants:
            scene = build(VARIANTS[label], args.res)
            approx, first, warm = timed(scene, frame, sphere_path, args.runs)
            e = errors(approx, ref, n_plane)
            e.update(first_ms=first, warm_ms=warm, method=VARIANTS[label])
            row["variants"][label] = e
            if label == "paper":
                np.save(REFS / f"{name}.paper.npy", approx)
            if label == DEFAULT_VARIANT:
                np.save(REFS / f"{name}.default.npy", approx)
            print(
                f"{name:22s} {label:18s} rmse {e['rel_rmse_pct']:6.2f} %  max {e['max_rel_err_pct']:6.1f} %  "
                f"excess {e['max_excess_over_unoccluded_pct']:5.2f} %  {warm:7.1f} ms",
                flush=True,
            )
        RESULTS.mkdir(parents=True, exist_ok=True)
        out_path.write_text(json.dumps(results, indent=1))  # after every case: a crash keeps the rest
    results["srf"] = srf_study()
    results["settings"] = dict(
        res=args.res, target=args.target, max_spp=args.max_spp, default_variant=DEFAULT_VARIANT
    )
    results["machine"] = dict(platform=platform.platform(), jax=jax.__version__, devices=str(jax.devices()))
    results["seconds"] = time.perf_counter() - t_start
    RESULTS.mkdir(parents=True, exist_ok=True)
    results["figures"] = plot(results)
    out_path.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
