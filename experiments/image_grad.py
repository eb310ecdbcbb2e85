"""Derivatives through the occlusion images against central differences of exact ray casts.

With ``[method] light_visibility = "images"`` a sphere light's visible fraction at a receiver is the
mean over the light's cap directions of lookups in the occluder's binary occlusion images; its
derivative is that of the pixel-box-filtered images (``jshadow.visibility._images``: the silhouette
term of the vertices per pixel, the read points' motion over the images, the bounding sphere's cut).
This checks it where it matters — summed over a plane of receivers — against the *converged*
forward pass of the same quantity: the visible fraction of the light from exact ray casts over 32 ×
64 stratified cap directions per receiver (the images are not involved), by central differences.

For each config (its middle frame, its plane at 32² receivers, images on), the loss is
``Σ_receivers w_i F(x_i)`` (fixed random weights in [0.5, 1.5]) and four directions are checked:
the config's deformation amount, a smooth random motion of the rest vertices (as
``experiments/frame_grad_fd.py``), a translation of the occluder and one of the light (random unit
directions). Differences at two steps (h and h/2) show the reference's own noise. Reports the
relative error against the mean of the two differences.

Usage (repository root, project environment active)::

    python experiments/image_grad.py [--configs configs/egg_breathing.toml ...] [--strata 32 64]

``--light-images samples coverage`` (default: both) checks the derivative of the lookups of the
0/1 samples (an estimate) and of the coverage images (``light_images = "coverage"``: the exact
derivative of what they compute) against the same differences.

Writes ``experiments/results/image_grad.json`` and prints a table.
"""

from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import time
import tomllib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from frame_grad_fd import _smooth_motion  # the script's folder is on sys.path

from jshadow.config import build_scene, config_from_dict
from jshadow.entities import frame_time
from jshadow.sampling import stratified_cone_components
from jshadow.scene import light_visible_fractions, scene_images
from jshadow.visibility import ray_fan_any_hit

ROOT = pathlib.Path(__file__).resolve().parents[1]
DEFAULT = ["configs/egg_breathing.toml", "configs/airplane_bend.toml"]
STEPS = {"deform": 0.05, "offsets": 0.4, "occluder": 0.1, "light": 0.1}


def _scene(path: str, resolution: int, light_images: str = "samples"):
    d = tomllib.loads((ROOT / path).read_text())
    d.setdefault("method", {})["light_visibility"] = "images"
    d["method"]["light_images"] = light_images
    d["receiver"]["resolution"] = [resolution, resolution]
    return build_scene(config_from_dict(d, source=path, root=(ROOT / path).parent))


def _moved(scene, kind: str, a, motion):
    """The scene with parameter set ``kind`` moved by ``a`` along ``motion``."""
    if kind == "deform":
        return eqx.tree_at(
            lambda s: (s.occluders[0].deform.amount_start, s.occluders[0].deform.amount_end),
            scene,
            (scene.occluders[0].deform.amount_start + a, scene.occluders[0].deform.amount_end + a),
        )
    if kind == "offsets":
        occ = scene.occluders[0]
        return eqx.tree_at(lambda s: s.occluders[0].unit_vertices, scene, occ.unit_vertices + a * motion)
    if kind == "occluder":
        return eqx.tree_at(lambda s: s.occluders[0].center, scene, scene.occluders[0].center + a * motion)
    if kind == "light":
        return eqx.tree_at(lambda s: s.lights[0].center, scene, scene.lights[0].center + a * motion)
    raise ValueError(kind)


def _exact_loss(scene, t, weights, strata) -> float:
    """Σ w_i F(x_i), F from exact ray casts over the light caps' ``strata`` directions."""
    occ = scene.occluders[0]
    v, faces = occ.vertices(t), occ.faces
    pts, nrm = scene.receivers.points, scene.receivers.normals
    total = 0.0
    for light in scene.lights:
        dx, dy, dz = stratified_cone_components(light.center - pts, light.radius, strata)
        dirs = jnp.stack([dx, dy, dz], -1)
        vis = 1.0 - ray_fan_any_hit(pts, dirs, v, faces).astype(pts.dtype)
        cos = jnp.maximum(jnp.einsum("nkc,nc->nk", dirs, nrm), 0.0)
        den = jnp.sum(cos, -1)
        frac = jnp.where(den > 0, jnp.sum(vis * cos, -1) / jnp.where(den > 0, den, 1.0), 1.0)
        total += float(jnp.sum(weights * frac))
    return total


def check(path: str, strata: tuple[int, int], resolution: int, light_images=("samples",)) -> list[dict]:
    scene = _scene(path, resolution)
    scenes = {li: _scene(path, resolution, li) for li in light_images}
    t = frame_time(scene.n_frames // 2, scene.n_frames)
    n = scene.receivers.points.shape[0]
    weights = jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, n), scene.dtype)
    rng = np.random.default_rng(3)
    occ = scene.occluders[0]
    unit = rng.normal(size=(2, 3))
    unit = unit / np.linalg.norm(unit, axis=1, keepdims=True)
    motions = {
        "deform": None,
        "offsets": jnp.asarray(_smooth_motion(rng, np.asarray(occ.unit_vertices), 0.05), scene.dtype),
        "occluder": jnp.asarray(unit[0], scene.dtype),
        "light": jnp.asarray(unit[1], scene.dtype),
    }
    rows = []
    for kind, motion in motions.items():
        h = STEPS[kind]

        def exact(a, kind=kind, motion=motion):
            return _exact_loss(_moved(scene, kind, jnp.asarray(a, scene.dtype), motion), t, weights, strata)

        fd = {step: (exact(step) - exact(-step)) / (2 * step) for step in (h, h / 2)}
        ref = float(np.mean(list(fd.values())))
        for li, sc in scenes.items():

            def ours(a, kind=kind, motion=motion, sc=sc):
                s = _moved(sc, kind, a, motion)
                pts, nrm = s.receivers.points, s.receivers.normals
                fr = light_visible_fractions(s, scene_images(s, t), pts, nrm)
                return sum(jnp.sum(weights * f) for f in fr)

            zero = jnp.zeros((), scene.dtype)
            ours(zero)  # a concrete pose first: the derivative's static sizes are measured on it
            start = time.perf_counter()
            g = float(jax.jit(jax.grad(ours))(zero))
            seconds = time.perf_counter() - start
            rows.append(
                {
                    "config": path,
                    "motion": kind,
                    "light_images": li,
                    "images": g,
                    "exact_differences": {str(k): v for k, v in fd.items()},
                    "relative_error": abs(g - ref) / abs(ref),
                    "reference_spread": abs(fd[h] - fd[h / 2]) / abs(ref),
                    "gradient_seconds_with_compile": seconds,
                }
            )
            r = rows[-1]
            print(
                f"{path:28s} {kind:9s} {li:8s} {g:10.4f}   exact h={h}: {fd[h]:10.4f}  h/2: {fd[h / 2]:10.4f}"
                f"   error {r['relative_error']:6.1%} (reference spread {r['reference_spread']:5.1%})",
                flush=True,
            )
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", nargs="*", default=DEFAULT)
    ap.add_argument("--strata", nargs=2, type=int, default=[32, 64])
    ap.add_argument("--resolution", type=int, default=32)
    ap.add_argument("--json", default=str(ROOT / "experiments" / "results" / "image_grad.json"))
    ap.add_argument(
        "--light-images",
        nargs="*",
        default=["samples", "coverage"],
        choices=["samples", "coverage"],
        help="[method] light_images settings whose derivatives are checked (same differences)",
    )
    args = ap.parse_args(argv)
    rows = []
    for c in args.configs:
        rows += check(c, tuple(args.strata), args.resolution, tuple(args.light_images))
    meta = {
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "device": str(jax.devices()[0]),
        "strata": args.strata,
        "resolution": args.resolution,
        "light_images": args.light_images,
    }
    pathlib.Path(args.json).write_text(json.dumps({"meta": meta, "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
