"""The calibration and accuracy experiments' own pieces (experiments/calibration.py, accuracy.py).

* The closed form used as ground truth for a sphere occluder under a constant environment,
  E = π (1 − sin²α cos β), against an independent quadrature of ∫ V max(0, n·ω) dω.
* The sphere-through-BSV calibration of DESIGN.md §2 (8.0 % relative RMSE, 24 % max, up to 8 %
  brighter than unoccluded) as a regression figure of the whole render path.
* The merge of two independent reference runs (weighted mean, standard error).
"""

import importlib.util
import math
import pathlib

import jax.numpy as jnp
import numpy as np
import pytest

from jshadow.compare import frame_errors
from jshadow.entities import SphereOccluder
from jshadow.runner import Renderer

_EXP = pathlib.Path(__file__).resolve().parents[1] / "experiments"


def _module(name):
    spec = importlib.util.spec_from_file_location(f"_exp_{name}", _EXP / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def calibration():
    return _module("calibration")


def _quadrature_sphere_irradiance(point, center, radius, n_theta=400, n_phi=800):
    """∫ V(ω) cos θ dω over the upper hemisphere (normal +y) by the midpoint rule in (θ, φ)."""
    th = (np.arange(n_theta) + 0.5) * (0.5 * math.pi / n_theta)
    ph = (np.arange(n_phi) + 0.5) * (2.0 * math.pi / n_phi)
    th, ph = np.meshgrid(th, ph, indexing="ij")
    w = np.cos(th) * np.sin(th) * (0.5 * math.pi / n_theta) * (2.0 * math.pi / n_phi)
    d = np.stack([np.sin(th) * np.cos(ph), np.cos(th), np.sin(th) * np.sin(ph)], axis=-1)
    oc = np.asarray(center) - np.asarray(point)
    b = d @ oc
    hit = (b > 0) & (b * b - (oc @ oc - radius * radius) >= 0)
    return float(np.sum(w * ~hit))


def test_sphere_closed_form_matches_quadrature(calibration):
    pts = np.array([[0.0, 0.0, 0.0], [1.3, 0.0, -0.4], [-2.0, 0.0, 2.0], [0.3, 0.0, 1.9]])
    exact = calibration.sphere_exact(pts)
    for p, e in zip(pts, exact, strict=True):
        q = _quadrature_sphere_irradiance(p, calibration.SPHERE_CENTER, calibration.SPHERE_RADIUS)
        assert abs(e - q) < 2e-3 * math.pi, (p, e, q)
    # straight below: α = asin(0.5/1.2), β = 0
    assert exact[0] == pytest.approx(math.pi * (1.0 - (0.5 / 1.2) ** 2), rel=1e-12)


def test_sphere_bsv_calibration_reproduces_design(calibration):
    sphere = SphereOccluder(
        jnp.asarray(calibration.SPHERE_CENTER, jnp.float32),
        jnp.asarray(calibration.SPHERE_RADIUS, jnp.float32),
    )
    scene = calibration.scene_with(sphere)
    res, _ = Renderer(scene, "bsv").frame(0)
    a = np.asarray(res.irradiance, np.float64)
    exact = np.repeat(calibration.sphere_exact(np.asarray(res.points))[:, None], 3, axis=1)
    e = frame_errors(a, exact)
    assert e["rel_rmse"] == pytest.approx(0.080, abs=0.003)
    assert e["max_rel_err"] == pytest.approx(0.24, abs=0.01)
    assert np.max(a) / math.pi - 1.0 == pytest.approx(0.08, abs=0.005)  # brighter than unoccluded
    # the analytic sphere path is far better (SH truncation only)
    res_a, _ = Renderer(scene, "analytic").frame(0)
    assert frame_errors(np.asarray(res_a.irradiance, np.float64), exact)["rel_rmse"] < 0.005


def test_merge_of_reference_runs():
    acc = _module("accuracy")
    rng = np.random.default_rng(0)
    x = rng.normal(size=(3000, 5))
    a, b = x[:1000], x[1000:]

    def run(s):
        return s.shape[0], s.mean(axis=0), s.std(axis=0, ddof=1) / math.sqrt(s.shape[0])

    n, m, se = acc.merge(run(a), run(b))
    assert n == 3000
    np.testing.assert_allclose(m, x.mean(axis=0), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(se, x.std(axis=0, ddof=1) / math.sqrt(3000), rtol=0.05)
