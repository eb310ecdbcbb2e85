"""The default method against the paper's on every shipped render config, against the Monte Carlo
references that ``experiments/defaults.py`` measures with (``experiments/results/refs/``: converged
references of each config at a 32² plane, computed once and committed).

Claims tested: for every shipped config but the fit configs, the config as shipped (the default
``[method]``, whose "auto" light path takes the occlusion images where they apply) renders closer
to the reference than the paper's method (``experiments/models.py``'s "paper" variant: shell r,
the paper's f_k, 4 bands, the paper's products), by at least the factor recorded in BENCHMARKS.md
("The default against the paper"), and within the issue's 1 % relative RMSE on every one of
them; never brighter than unoccluded by more than 1 %.
"""

import pathlib
import sys
import tomllib

import numpy as np
import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "experiments"))
import models  # noqa: E402

from jshadow import render  # noqa: E402
from jshadow.config import build_scene, config_from_dict  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
REFS = models.REFS
PAPER = models.VARIANTS["paper"]  # the paper's method as experiments/defaults.py renders it

# config -> (reference case, frame, relative RMSE the default must reach [%], paper / default at least);
# the comments give paper / default relative RMSE as this test measures them (2026-12-07, e847e2e)
CASES = {
    "sphere.toml": ("sphere", 0, 1.0, 10.0),  # 7.76 / 0.18 %
    "bunny_studio.toml": ("bunny_studio", 0, 1.0, 20.0),  # 20.86 / 0.58 % (lamp images, cast transfer)
    "spot_sunset.toml": ("spot_sunset", 0, 1.0, 5.0),  # 7.32 / 0.78 %
    "airplane_bend.toml": ("airplane_bend_last", 23, 1.0, 10.0),  # 8.97 / 0.64 %
    "egg_breathing.toml": ("egg_breathing", 0, 1.0, 20.0),  # 14.61 / 0.67 %
    # 21.00 / 0.64 % (64 lamps in images with their regions' penumbrae, the own vertices' "maps",
    # made every frame)
    "bunny_animated.toml": ("bunny_animated_last", 47, 1.0, 15.0),
}


def _scene(file: str, method: dict):
    path = ROOT / "configs" / file
    d = tomllib.loads(path.read_text())
    d["receiver"]["resolution"] = [32, 32]
    d.setdefault("method", {}).update(method)
    return build_scene(config_from_dict(d, source=str(path), root=path.parent))


def _errors(scene, frame, ref):
    e = np.asarray(render(scene, frame).irradiance, np.float64)
    mean = float(np.mean(ref["mean"]))
    rmse = 100 * float(np.sqrt(np.mean((e - ref["mean"]) ** 2))) / mean
    n_plane = scene.receivers.points.shape[0]
    excess = 100 * float(np.max((e[:n_plane] - ref["unoccluded"]) / np.mean(ref["mean"][:n_plane])))
    return rmse, excess


def test_every_shipped_render_config_is_covered():
    shipped = {p.name for p in (ROOT / "configs").glob("*.toml") if not p.name.startswith("fit_")}
    assert shipped == set(CASES)


@pytest.mark.parametrize("file", list(CASES))
def test_default_is_more_accurate_than_the_paper(file):
    case, frame, target, factor = CASES[file]
    z = np.load(REFS / f"{case}.npz")
    ref = {k: z[k] for k in z.files}
    default, excess = _errors(_scene(file, {}), frame, ref)
    paper, _ = _errors(_scene(file, PAPER), frame, ref)
    print(f"{file}: paper {paper:.2f} %, default {default:.2f} % (excess {excess:.2f} %)")
    assert default <= target
    assert paper >= factor * default
    assert excess <= 1.0
