"""The shipped studio bunny with the default method and with the map's lamps as distant lights, side by side.

Renders ``configs/bunny_studio.toml`` as shipped (n-band environment) and with ``[method]
light_visibility = "images"``, ``environment_lights = 32`` and ``self_visibility = "rays"``
(:mod:`jshadow.envlights`), draws both the way ``jshadow render`` does at one common exposure (the
default's), and writes them side by side. The errors of the two settings against the Monte Carlo
reference are measured by ``experiments/light_field.py`` (22.4 % and 3.9 % relative RMSE at 32²).

Usage (repository root, project environment active)::

    python experiments/studio_lamps.py

Writes ``experiments/figures/bunny_studio_lamps.png`` and, in
``experiments/results/studio_lamps.json``, how concentrated the studio map's energy is: the share
of ∫ L dω (luminance, the mean of the channels) in the brightest 0.05 %, 0.5 % and 2 % of the
sphere.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import tempfile

import imageio.v3 as iio
import numpy as np

from jshadow import Renderer
from jshadow.config import build_scene, load_config
from jshadow.picture import draw_scene, exposure_for

ROOT = pathlib.Path(__file__).resolve().parents[1]
OUT = ROOT / "experiments" / "figures" / "bunny_studio_lamps.png"
RESULT = ROOT / "experiments" / "results" / "studio_lamps.json"


def concentration(image: np.ndarray, shares=(0.0005, 0.005, 0.02)) -> dict:
    """Share of a lat-long map's ∫ L dω held by its brightest pixels covering each given share of
    the sphere (exact pixel solid angles; luminance = the mean of the channels)."""
    h, w = image.shape[:2]
    edges = np.cos(np.pi * np.arange(h + 1) / h)
    omega = np.broadcast_to(((edges[:-1] - edges[1:]) * 2.0 * np.pi / w)[:, None], (h, w)).ravel()
    lum = np.asarray(image, np.float64).mean(-1).ravel()
    order = np.argsort(-lum)
    energy = np.cumsum((lum * omega)[order]) / np.sum(lum * omega)
    area = np.cumsum(omega[order]) / (4.0 * np.pi)
    return {f"{100 * a:g} % of the sphere": float(energy[np.searchsorted(area, a)]) for a in shares}


def main() -> None:
    base = build_scene(load_config(ROOT / "configs" / "bunny_studio.toml"))
    shares = concentration(np.asarray(base.environment.image))
    print("share of the studio map's energy:", {k: round(v, 3) for k, v in shares.items()})
    RESULT.write_text(json.dumps({"energy_share_of_brightest": shares}, indent=1))
    lamps = dataclasses.replace(
        base,
        method=dataclasses.replace(
            base.method, light_visibility="images", environment_lights=32, self_visibility="rays"
        ),
    )
    results = {}
    for label, scene in (("default (n-band)", base), ("32 environment lights", lamps)):
        res, times = Renderer(scene).frame(0)
        results[label] = (scene, res)
        print(f"{label}: {times['total_ms']:.0f} ms (first frame, with compilation)")
    n_plane = base.receivers.points.shape[0]
    exposure = exposure_for(np.asarray(results["default (n-band)"][1].radiance)[:n_plane])
    panels = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, (label, (scene, res)) in enumerate(results.items()):
            path = pathlib.Path(tmp) / f"{i}.png"
            draw_scene(path, scene, res, 0.0, exposure=exposure, title=f"bunny_studio: {label}")
            panels.append(iio.imread(path))
    OUT.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(OUT, np.concatenate(panels, axis=1))
    print(f"wrote {OUT.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
