"""Smoke tests of the paper-reproduction experiments' cores, at tiny sizes (experiments/*.py)."""

import math
import pathlib
import sys

import jax.numpy as jnp
import numpy as np
import pytest

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "experiments"))

import full_field  # noqa: E402
import pareto  # noqa: E402
import shrink_pictures  # noqa: E402
import table1  # noqa: E402
from _common import unit_mesh  # noqa: E402

from jshadow.geometry import icosphere  # noqa: E402
from jshadow.sh import sh_basis  # noqa: E402
from jshadow.visibility import bsv_mesh, hemisphere_directions  # noqa: E402


def test_table1_split_adds_up_to_the_fused_brute_force_bsv():
    v, f = unit_mesh("bunny_small")
    kw = dict(grid=(3, 4), directions=(6, 6), shell=1.0)
    fused = bsv_mesh(v, f, n=3, method="brute", **kw).coeffs
    occ = table1.brute_occlusion(v, f, **kw)
    local, w = hemisphere_directions(6, 6, dtype=v.dtype)
    split = table1.project(occ, sh_basis(local, 3) * w[:, None]).reshape(fused.shape)
    assert bool(jnp.any(occ)) and not bool(jnp.all(occ))
    np.testing.assert_allclose(np.asarray(split), np.asarray(fused), atol=1e-5)


def test_shrink_study_is_exact_on_the_shell_and_approximate_beyond():
    out, images = shrink_pictures.study("bunny_small", (math.pi / 2, 0.0), [1.0, 2.0], 1.0, 3, 8)
    on, off = out["rows"]
    assert on["binary_mismatch_rel"] == 0.0 and on["sh_l2_err_rel"] < 1e-6  # k = 1: M_k = I
    assert 0.0 < off["binary_mismatch_rel"] < 1.0 and 0.0 < off["sh_l2_err_rel"] < 5.0
    assert off["true_occluded_sr"] < on["true_occluded_sr"]  # the occluder looks smaller from afar
    assert all(im.shape == (8, 8) for im in images[2.0])


def test_quadrature_irradiance_matches_the_sphere_closed_form():
    ico = icosphere(3, dtype=jnp.float32)
    center, radius = np.array([0.0, 1.2, 0.0]), 0.5
    pts = jnp.asarray([[0.0, 0.0, 0.0], [0.7, 0.0, 0.3], [-1.5, 0.0, 1.0]], jnp.float32)
    e = pareto.quadrature_irradiance(
        pts, jnp.asarray(center, jnp.float32) + radius * ico.vertices, ico.faces, 32, 64
    )
    exact = pareto.sphere_exact(np.asarray(pts), center, radius)
    assert exact[0] < 0.9 * math.pi  # the first point is in the shadow
    np.testing.assert_allclose(e, exact, rtol=2e-2)


def test_full_field_of_identical_shells_reproduces_the_shell():
    rng = np.random.default_rng(0)
    c = jnp.asarray(rng.normal(size=(3, 4, 9)), jnp.float32)
    coeffs = jnp.stack([c, c, c])
    radii = jnp.asarray([0.5, 1.0, 2.0], jnp.float32)
    pts = jnp.asarray([[0.3, 0.2, 0.9], [1.5, -0.2, 0.1], [5.0, 0.0, 0.0]], jnp.float32)
    out = full_field.full_field_eval(coeffs, radii, jnp.zeros(3, jnp.float32), jnp.float32(1.0), pts)
    single = full_field.full_field_eval(
        coeffs[:2], radii[:2] * 2, jnp.zeros(3, jnp.float32), jnp.float32(1.0), pts
    )
    np.testing.assert_allclose(np.asarray(out[:2]), np.asarray(single[:2]), atol=1e-5)
    np.testing.assert_allclose(np.asarray(out[2]), [math.sqrt(4 * math.pi)] + [0.0] * 8, atol=1e-6)  # beyond


@pytest.mark.parametrize("fam", pareto.FAMILIES)
def test_pareto_families_and_front(fam):
    m = pareto.family(fam, 4)
    assert m["bsv_bands"] >= 4 and m["shell"] >= 1.0
    front = pareto.pareto_front([(1.0, 0.5), (2.0, 0.6), (3.0, 0.2), (0.5, 0.9)])
    assert front == [3, 0, 2]
