"""Sharp shadows of sphere lights from the BSV's occlusion images, against the n-band default.

``experiments/band_limit.py`` shows that on the scenes lit by sphere lights the default is within
0.1–0.3 points of exact n-band visibility: what is left is the band limit, which no extrapolation
model removes. ``[method] light_visibility = "images"`` shadows sphere lights differently: the
visible fraction of each light over ``light_cap`` stratified directions of its cap, each ray looked
up in the BSV's binary occlusion images (:func:`jshadow.visibility.image_ray_visibility`: the ray
enters the shell at p, and beyond p it is the ray (p, ω) that the shell's images sample; bilinear
over the four grid points around p, each read toward the ray's point nearest the occluder's
centre), times the light's exact unoccluded irradiance. The environment keeps the default's path,
unless ``environment_lights`` > 0 splits a lat-long map's radiance above ``environment_threshold``
× its mean off as that many distant lights (median cut, :mod:`jshadow.envlights`) shadowed through
the same images — for the studio map's small lamps, where the n-band floor is 19 %.

For every case of ``experiments/models.py`` with a sphere light or a lat-long map (references
cached there), and an untuned one (``airplane_studio_twist``: the twisted airplane under the
studio map turned by 2 rad), this script renders the default and ``light_visibility = "images"``
at several sizes — the BSV grid and image resolution (``bsv_grid``, ``directions``), the cap
directions (``light_cap``), the images read (``light_images``: the 0/1 pixel samples at the
nearest pixel, or the scan lines' coverage bilinearly), the number of environment lights and
their threshold — with
:class:`jshadow.Renderer` (fresh renderers, BSV and images sampled every frame), and reports the
error against the reference with the time per frame of the same run (``models.timed``: median warm
frame, 32² plane).

Usage (repository root, project environment active)::

    python experiments/light_field.py [--cases ...] [--runs 3]

Writes ``experiments/results/light_field.json`` and ``experiments/figures/light_field_maps.png``.
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import models  # noqa: E402
from _common import git_state  # noqa: E402

from jshadow.config import rotate_latlong_y  # noqa: E402
from jshadow.entities import Environment  # noqa: E402
from jshadow.geometry import make_deformation  # noqa: E402
from jshadow.lights import read_latlong  # noqa: E402

CASES = [
    "spot_sky_light",
    "airplane_bend_last",
    "egg_breathing",
    "spot_sunset",
    "three_occluders",
    "sphere",
    "bunny_studio",
    "airplane_studio_twist",
]
# label -> [method] keys over the default
IMAGES = dict(light_visibility="images")
FINE = dict(light_cap=(8, 16), bsv_grid=(24, 40), directions=(64, 64))  # finer grid, images and cap
ENV32 = dict(IMAGES, environment_lights=32)
ENV64_FINE = dict(IMAGES, environment_lights=64, **FINE)
RAYS = dict(self_visibility="rays")  # the own vertices' bright part by exact rays (self_shadow only)
SETTINGS = {
    "default (n-band)": {},
    "images, cap 2x8": dict(IMAGES, light_cap=(2, 8)),
    "images (12x20, 32², cap 4x8)": IMAGES,
    # the same images made continuous along the scan lines and read bilinearly (exact derivative)
    "images, coverage": dict(IMAGES, light_images="coverage"),
    "images, cap 8x16": dict(IMAGES, light_cap=(8, 16)),
    "images, 24x40, 64², cap 8x16": dict(IMAGES, **FINE),
    # the map's bright part as distant lights through the same images (lat-long maps only)
    "images + 8 env lights": dict(IMAGES, environment_lights=8),
    "images + 32 env lights": ENV32,
    "images + 32 env lights, coverage": dict(ENV32, light_images="coverage"),
    "images + 32 env lights, threshold 1": dict(ENV32, environment_threshold=1.0),
    "images + 32 env lights, threshold 16": dict(ENV32, environment_threshold=16.0),
    "images + 32 env lights, self rays": dict(ENV32, **RAYS),
    "images + 64 env lights, 24x40, 64², cap 8x16, self rays": dict(ENV64_FINE, **RAYS),
    "images + 64 env lights, 24x40, 64², cap 8x16": ENV64_FINE,
}
ROWS = {  # the error maps' rows: (label, setting); a row is left blank where its setting does not apply
    "default (n-band)": "default (n-band)",
    '"images"': "images (12x20, 32², cap 4x8)",
    '"images" + 32 env lights': "images + 32 env lights",
    '"images", coverage': "images, coverage",
}


def _airplane_studio_twist(method: dict, res: int):
    """Untuned for the environment lights: another mesh and deformation under the studio map turned
    by 2 rad about +y (so its lamps fall elsewhere), no sphere light."""
    path = models.ASSETS / "envmaps" / "studio_small_03_512x256.hdr"
    image = rotate_latlong_y(jnp.asarray(read_latlong(path), jnp.float32), 2.0)
    env = Environment(radiance=jnp.ones(3, jnp.float32), image=image, kind="hdr")
    twist = make_deformation("twist", 0.8, axis="x")
    return models._scene(method, [models._mesh("airplane.obj", (0, 1.1, 0), 0.9, twist)], env=env, res=res)


def _airplane_studio_bend(method: dict, res: int):
    """Untuned for a deforming mesh under a map: the airplane bending over its animation (bend
    0 → 0.6 about y toward x), its last frame, under the studio map turned by 2 rad (64 lamps in
    images made every frame by default)."""
    path = models.ASSETS / "envmaps" / "studio_small_03_512x256.hdr"
    image = rotate_latlong_y(jnp.asarray(read_latlong(path), jnp.float32), 2.0)
    env = Environment(radiance=jnp.ones(3, jnp.float32), image=image, kind="hdr")
    bend = make_deformation("bend", (0.0, 0.6), axis="y", toward="x")
    occ = [models._mesh("airplane.obj", (0, 1.1, 0), 0.9, bend)]
    return models._scene(method, occ, env=env, res=res, n_frames=2)


def _bunny_studio_low(method: dict, res: int):
    """Untuned for receivers within a mesh's bounding sphere: the bunny 0.05 above the plane (its
    bounding sphere, radius 0.9, meets the plane in a disc 1.1 across), under the studio map
    turned by 2 rad about +y, the plane its only receiver."""
    path = models.ASSETS / "envmaps" / "studio_small_03_512x256.hdr"
    image = rotate_latlong_y(jnp.asarray(read_latlong(path), jnp.float32), 2.0)
    env = Environment(radiance=jnp.ones(3, jnp.float32), image=image, kind="hdr")
    return models._scene(method, [models._mesh("bunny.obj", (0, 0.715, 0), 0.9)], env=env, res=res)


def _spot_light_low(method: dict, res: int):
    """Untuned for receivers within a mesh's bounding sphere under a sphere light: the spot cow of
    ``spot_sky_light`` lowered to 0.05 above the plane (its bounding sphere, radius 0.7, meets the
    plane in a disc 0.7 across), the same sphere light and sky."""
    occ = [models._mesh("spot.obj", (0.2, 0.6, -0.1), 0.7)]
    sky = models._sky("sky", (0.6, 0.7, 0.9))
    return models._scene(method, occ, [models._sphere_light()], env=sky, res=res)


def _spot_twist_low(method: dict, res: int):
    """Untuned for a deforming mesh at a contact: the spot cow of ``spot_light_low`` (0.05 above
    the plane) twisting about the vertical through its centre (0 → 1.2 rad per bounding radius, which
    keeps its lowest point's height), its last frame, under the same sphere light and sky. Its
    plane's receivers next to the cow keep the field by default ("auto": exact rays would be paid
    every frame)."""
    twist = make_deformation("twist", (0.0, 1.2), axis="y")
    occ = [models._mesh("spot.obj", (0.2, 0.6, -0.1), 0.7, twist)]
    sky = models._sky("sky", (0.6, 0.7, 0.9))
    return models._scene(method, occ, [models._sphere_light()], env=sky, res=res, n_frames=2)


def _spot_self_sky_bend(method: dict, res: int):
    """Untuned for a deforming mesh's self-shadowing: the spot cow bending over its animation (bend
    0 → 0.7 about y toward z), its last frame, under a sky, its 2930 own vertices among the
    receivers ("maps" by default: depth images and local rays made every frame; its 2930 × 5856
    (vertex, face) pairs are over ``jshadow.config.AUTO_SELF_RAYS_PAIRS``)."""
    bend = make_deformation("bend", (0.0, 0.7), axis="y", toward="z")
    occ = [models._mesh("spot.obj", (0.1, 0.9, 0.0), 0.7, bend)]
    return models._scene(
        method, occ, env=models._sky("sky", (0.6, 0.7, 0.9)), res=res, n_frames=2, self_shadow=True
    )


def _bunny_self_sky_bend(method: dict, res: int):
    """Untuned for the own vertices' transfer grid: the bunny bending over its animation (bend
    0 → 0.6 about y toward x), its last frame, under a constant sky, its 1901 own vertices among
    the receivers (cast by rays every frame by default, within ``jshadow.config.AUTO_SELF_RAYS_PAIRS``;
    formerly "maps", max 10.4 %; the sky carries all the light through their transfer)."""
    bend = make_deformation("bend", (0.0, 0.6), axis="y", toward="x")
    occ = [models._mesh("bunny.obj", (0.0, 1.0, 0.0), 0.8, bend)]
    return models._scene(method, occ, env=models._sky(), res=res, n_frames=2, self_shadow=True)


def _cases():
    cases = dict(models._cases())
    cases["airplane_studio_twist"] = (_airplane_studio_twist, 0, "analytic", False)
    cases["bunny_studio_low"] = (_bunny_studio_low, 0, "analytic", False)
    cases["spot_light_low"] = (_spot_light_low, 0, "analytic", False)
    cases["airplane_studio_bend_last"] = (_airplane_studio_bend, 1, "analytic", False)
    cases["spot_twist_low_last"] = (_spot_twist_low, 1, "analytic", False)
    cases["spot_self_sky_bend_last"] = (_spot_self_sky_bend, 1, "analytic", False)
    cases["bunny_self_sky_bend_last"] = (_bunny_self_sky_bend, 1, "analytic", False)
    return cases


def _applies(keys: dict, scene) -> bool:
    """Whether a setting changes anything on a scene: the sphere-light options need sphere lights,
    the environment lights a lat-long map, own-vertex rays self-shadowing (the default always
    applies)."""
    if not keys:
        return True
    if keys.get("self_visibility") == "rays" and not scene.self_shadow:
        return False
    if keys.get("environment_lights"):
        return scene.environment is not None and scene.environment.kind == "hdr"
    return bool(scene.lights)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="*", default=CASES)
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    results = {"git": git_state(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "cases": {}}
    maps = {}
    t_start = time.perf_counter()
    out = models.RESULTS / "light_field.json"
    for name in args.cases:
        build, frame, sphere_path, tuned = _cases()[name]
        base = build(models.VARIANTS["paper"], 32)
        ref = models.reference(name, base, frame, 1e-3, 32768)
        n_plane = int(np.prod(base.receivers.grid_shape))
        rows = {}
        got = {}
        for label, keys in SETTINGS.items():
            if not _applies(keys, base):
                continue
            method = dict(models.VARIANTS[models.DEFAULT_VARIANT], **keys)
            approx, first, warm = models.timed(build(method, 32), frame, sphere_path, args.runs)
            err = models.errors(approx, ref, n_plane)
            err.update(
                first_ms=first,
                warm_ms=warm,
                method={k: list(v) if isinstance(v, tuple) else v for k, v in keys.items()},
            )
            rows[label] = err
            got[label] = approx
            print(
                f"{name:20s} {label:30s} rmse {err['rel_rmse_pct']:6.2f} %"
                f"  max {err['max_rel_err_pct']:6.1f} %"
                f"  excess {err['max_excess_over_unoccluded_pct']:5.2f} %  {warm:7.1f} ms",
                flush=True,
            )
        results["cases"][name] = {"tuned": tuned, "ref_spp": int(ref["spp"]), "settings": rows}
        maps[name] = (
            ref["mean"][:n_plane],
            {row: got[lb][:n_plane] for row, lb in ROWS.items() if lb in got},
        )
        out.write_text(json.dumps(results, indent=1))
        # every setting compiles its own programs: dropped after each case, or a run of all cases
        # runs out of memory for compiled code (LLVM "Cannot allocate memory", 2026-12-06)
        jax.clear_caches()
    results["seconds"] = time.perf_counter() - t_start
    fig, axes = plt.subplots(
        len(ROWS), len(maps), figsize=(2.4 * len(maps), 2.4 * len(ROWS)), dpi=100, squeeze=False
    )
    for j, (name, (ref, rows)) in enumerate(maps.items()):
        side = int(round(math.sqrt(ref.shape[0])))
        for i, label in enumerate(ROWS):
            ax = axes[i, j]
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(name, fontsize=7)
            if j == 0:
                ax.set_ylabel(label, fontsize=8)
            if label not in rows:
                ax.set_frame_on(False)
                continue
            err = ((rows[label] - ref).mean(1) / ref.mean()).reshape(side, side)
            im = ax.imshow(100 * err, cmap="RdBu_r", vmin=-10, vmax=10, origin="lower")
    fig.colorbar(im, ax=axes, shrink=0.8, label="(render − reference) / mean [%]")
    path = models.FIGURES / "light_field_maps.png"
    fig.savefig(path)
    plt.close(fig)
    results["figure"] = str(path.relative_to(models.ROOT))
    out.write_text(json.dumps(results, indent=1))
    print(f"wrote {out} and {path} in {results['seconds']:.0f} s")


if __name__ == "__main__":
    main()
