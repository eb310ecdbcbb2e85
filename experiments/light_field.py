"""Sharp shadows of sphere lights from the BSV's occlusion images, against the n-band default.

``experiments/band_limit.py`` shows that on the scenes lit by sphere lights the default is within
0.1–0.3 points of exact n-band visibility: what is left is the band limit, which no extrapolation
model removes. ``[method] light_visibility = "images"`` shadows sphere lights differently: the
visible fraction of each light over ``light_cap`` stratified directions of its cap, each ray looked
up in the BSV's binary occlusion images (:func:`jshadow.visibility.image_ray_visibility`: the ray
enters the shell at p, and beyond p it is the ray (p, ω) that the shell's images sample; bilinear
over the four grid points around p, each read toward the ray's point nearest the occluder's
centre), times the light's exact unoccluded irradiance. The environment keeps the default's path.

For every case of ``experiments/models.py`` with a sphere light (references cached there), this
script renders the default and ``light_visibility = "images"`` at several sizes — the BSV grid and
image resolution (``bsv_grid``, ``directions``) and the cap directions (``light_cap``) — with
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

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import models  # noqa: E402
from _common import git_state  # noqa: E402

CASES = ["spot_sky_light", "airplane_bend_last", "egg_breathing", "spot_sunset", "three_occluders", "sphere"]
# label -> [method] keys over the default
SETTINGS = {
    "default (n-band)": {},
    "images, cap 2x8": dict(light_visibility="images", light_cap=(2, 8)),
    "images (12x20, 32², cap 4x8)": dict(light_visibility="images"),
    "images, cap 8x16": dict(light_visibility="images", light_cap=(8, 16)),
    "images, 24x40, 64², cap 8x16": dict(
        light_visibility="images", light_cap=(8, 16), bsv_grid=(24, 40), directions=(64, 64)
    ),
}
MAPPED = "images (12x20, 32², cap 4x8)"


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
        build, frame, sphere_path, tuned = models._cases()[name]
        base = build(models.VARIANTS["paper"], 32)
        ref = models.reference(name, base, frame, 1e-3, 32768)
        n_plane = int(np.prod(base.receivers.grid_shape))
        rows = {}
        got = {}
        for label, keys in SETTINGS.items():
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
        maps[name] = (ref["mean"][:n_plane], got["default (n-band)"][:n_plane], got[MAPPED][:n_plane])
        out.write_text(json.dumps(results, indent=1))
    results["seconds"] = time.perf_counter() - t_start
    fig, axes = plt.subplots(2, len(maps), figsize=(2.4 * len(maps), 4.8), dpi=100, squeeze=False)
    for j, (name, (ref, dflt, lf)) in enumerate(maps.items()):
        side = int(round(math.sqrt(ref.shape[0])))
        for i, (label, approx) in enumerate((("default (n-band)", dflt), ('"images"', lf))):
            err = ((approx - ref).mean(1) / ref.mean()).reshape(side, side)
            im = axes[i, j].imshow(100 * err, cmap="RdBu_r", vmin=-10, vmax=10, origin="lower")
            axes[i, j].set_xticks([])
            axes[i, j].set_yticks([])
            if i == 0:
                axes[i, j].set_title(name, fontsize=7)
            if j == 0:
                axes[i, j].set_ylabel(label, fontsize=8)
    fig.colorbar(im, ax=axes, shrink=0.8, label="(render − reference) / mean [%]")
    path = models.FIGURES / "light_field_maps.png"
    fig.savefig(path)
    plt.close(fig)
    results["figure"] = str(path.relative_to(models.ROOT))
    out.write_text(json.dumps(results, indent=1))
    print(f"wrote {out} and {path} in {results['seconds']:.0f} s")


if __name__ == "__main__":
    main()
