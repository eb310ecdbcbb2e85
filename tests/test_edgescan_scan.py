"""The edge-scan BSV's scanline derivative (``bsv_gradient = "scanline"``).

Checked in float64 against central differences of the converged forward pass (exact piecewise
integration, never the sampled images), against the ray-cast derivative on a finely tessellated
self-occluding mesh, its boundary signs against the winding number recomputed from the crossings
alone (sorted exactly in float64 on the host), the transpose relation between jvp and grad, exact
invariances, NaN-freedom at a zero-length edge, and its static sizes and their overflow.
"""

import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_bsv_grad import N_BANDS, _cos, _ico, _rel, _smooth_motion, _torus
from test_edgescan_grad import SHELL, _ref_bsv

from jshadow.entities import Method
from jshadow.geometry import load_mesh
from jshadow.visibility import (
    bsv_mesh_diff,
    bsv_mesh_edgescan,
    bsv_mesh_edgescan_scan_diff,
    edgescan_scan_slots,
    edgescan_slots,
)
from jshadow.visibility._edgescan_scan import scan_crossings

ASSETS = Path(__file__).resolve().parents[1] / "assets"


def _scan_jvp(x, f, dx, grid, res, n=N_BANDS, **kw):
    def tangent(v, dv):
        return jax.jvp(
            lambda w: bsv_mesh_edgescan_scan_diff(w, f, n, grid, (res, res), SHELL, **kw), (v,), (dv,)
        )[1]

    return np.asarray(jax.jit(tangent)(jnp.asarray(x), jnp.asarray(dx)))


@pytest.mark.usefixtures("x64")
def test_convex_directional_derivative_vs_converged_differences():
    # Convex: every crossing of the silhouette is a boundary, so only the Riemann sums along the
    # pixel columns and rows separate the derivative from the exact one (measured 1.3 % at 32²,
    # 0.7 % at 64²; columns alone, without the rows' share of steep edges: 20 % and 13 %).
    x, f = _ico(2)
    x = x * np.array([1.0, 0.8, 0.9]) + np.array([0.1, -0.2, 0.05])
    grid, h = (3, 4), 1e-5
    dx = _smooth_motion(np.random.default_rng(1), x)
    fd = (_ref_bsv(x + h * dx, f, grid) - _ref_bsv(x - h * dx, f, grid)) / (2 * h)
    tan = _scan_jvp(x, f, dx, grid, 32).reshape(fd.shape)
    assert _rel(tan, fd) < 0.03, _rel(tan, fd)
    assert _cos(tan.ravel(), fd.ravel()) > 0.9995


@pytest.mark.usefixtures("x64")
def test_finely_tessellated_self_occluding_mesh_matches_the_raycast_derivative():
    # bunny_small's contour zigzags below the pixel size: most crossings lie between two occluded
    # layers (σ = 0). Measured at 32²: cosine 0.9993, norm ratio 1.02 against the ray-cast derivative
    # at 32 nodes per edge (the image-plane derivative: 0.9989, 0.95-1.00).
    m = load_mesh(ASSETS / "bunny_small.obj")
    x, f = np.asarray(m.vertices, np.float64), np.asarray(m.faces)
    dx = _smooth_motion(np.random.default_rng(0), x)
    a = _scan_jvp(x, f, dx, (2, 3), 32).ravel()
    _, b = jax.jvp(
        lambda v: bsv_mesh_diff(v, f, N_BANDS, (2, 3), (8, 8), SHELL, nodes=32),
        (jnp.asarray(x),),
        (jnp.asarray(dx),),
    )
    b = np.asarray(b).ravel()
    assert _cos(a, b) > 0.998, _cos(a, b)
    assert 0.95 < np.linalg.norm(a) / np.linalg.norm(b) < 1.06


def test_boundary_signs_are_those_of_the_exact_winding_number():
    # σ comes from the forward pass's layer count at the pixel centre before each crossing plus the
    # crossings between (sorted by a quantised key). Here the count is recomputed from the crossings
    # alone: along each scan line from the image border, sorted exactly on the host. The row scan's
    # counts are the negated winding number, so the same zero test applies to both scans.
    m = load_mesh(ASSETS / "bunny_small.obj")
    x, f = jnp.asarray(m.vertices, jnp.float32), np.asarray(m.faces)
    c = scan_crossings(x, f, (3, 4), (32, 32), SHELL)
    line = np.stack([c["view"], c["rows"].astype(np.int64), c["line"]], axis=-1)
    order = np.lexsort((c["at"], line[:, 2], line[:, 1], line[:, 0]))
    w = c["w"][order].astype(np.int64)
    key = line[order]
    new = np.ones(len(order), bool)
    new[1:] = np.any(key[1:] != key[:-1], axis=-1)
    csum = np.cumsum(w)
    start = np.maximum.accumulate(np.where(new, np.arange(len(order)), 0))
    below = csum - w - (csum[start] - w[start])
    above = below + w
    sigma = np.zeros(len(order))
    sigma[order] = ((below != 0) & (above == 0)).astype(float) - ((below == 0) & (above != 0))
    assert np.all(above[np.r_[new[1:], True]] == 0)  # every line ends outside the silhouette
    assert np.count_nonzero(sigma != c["sigma"]) <= 1e-3 * len(sigma)
    assert 0.05 < np.mean(sigma != 0) < 0.6  # both kinds occur: the test is not vacuous
    assert np.any(c["rows"]) and np.any(~c["rows"])


@pytest.mark.usefixtures("x64")
def test_primal_is_the_edgescan_and_grad_is_the_transposed_jvp(rng):
    x, f = _torus()
    grid = (3, 4)

    def bsv(v):
        return bsv_mesh_edgescan_scan_diff(v, f, N_BANDS, grid, (32, 32), SHELL)

    np.testing.assert_array_equal(
        np.asarray(bsv(jnp.asarray(x))),
        np.asarray(bsv_mesh_edgescan(x, f, N_BANDS, grid, (32, 32), SHELL).coeffs),
    )
    w = jnp.asarray(rng.normal(size=(*grid, N_BANDS**2)))
    dx = jnp.asarray(_smooth_motion(rng, x))
    jvp = jax.jit(lambda v, dv: jax.jvp(bsv, (v,), (dv,))[1])
    tan = jvp(jnp.asarray(x), dx)
    grad = jax.jit(jax.grad(lambda v: jnp.sum(w * bsv(v))))(jnp.asarray(x))
    assert grad.shape == x.shape and bool(jnp.all(jnp.isfinite(grad)))
    lhs, rhs = float(jnp.sum(grad * dx)), float(jnp.sum(w * tan))
    assert abs(lhs - rhs) <= 1e-10 * abs(rhs) and abs(rhs) > 1e-3
    # an eager derivative (concrete pose in the rule) is the jitted one
    eager = jax.jvp(bsv, (jnp.asarray(x),), (dx,))[1]
    np.testing.assert_allclose(np.asarray(eager), np.asarray(tan), rtol=1e-9, atol=1e-12)
    # translation and uniform scaling about the centre leave the BSV unchanged: exactly zero
    scale = jnp.asarray(x - 0.5 * (x.min(0) + x.max(0)))
    for motion in (jnp.broadcast_to(jnp.asarray(rng.normal(size=3)), x.shape), scale):
        t = jvp(jnp.asarray(x), motion)
        assert float(jnp.max(jnp.abs(t))) <= 1e-12 * float(jnp.max(jnp.abs(tan)))


@pytest.mark.usefixtures("x64")
def test_zero_length_edge_is_nan_free():
    # two vertices of an octahedron on the same point: that edge projects to a point in every view
    # and crosses no scan line; the others' slopes stay finite, and nothing is NaN
    x = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)
    f = np.array(
        [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]], np.int32
    )
    x[4] = x[0] * 1.0
    slots = edgescan_slots(x, f, (3, 4), (16, 16), SHELL)

    def loss(v):
        return jnp.sum(bsv_mesh_edgescan_scan_diff(v, f, N_BANDS, (3, 4), (16, 16), SHELL, slots=slots) ** 2)

    g = jax.jit(jax.grad(loss))(jnp.asarray(x))
    assert bool(jnp.all(jnp.isfinite(g))) and float(jnp.max(jnp.abs(g))) > 0


def test_compaction_keeps_the_gradient_and_overflow_raises():
    # scan_slots = (row S, S2, S3, K, boundary): only boundary crossings (σ ≠ 0) are carried into
    # the linear part; None carries every crossing. Same derivative; too few slots raise under
    # jax.jit(jax.grad(...)), where the primal is dead code.
    m = load_mesh(ASSETS / "bunny_small.obj")
    x, f = jnp.asarray(m.vertices, jnp.float32), np.asarray(m.faces)
    grid, res = (3, 4), (32, 32)
    slots = edgescan_slots(x, f, grid, res, SHELL)
    sizes = edgescan_scan_slots(x, f, grid, res, SHELL, slots=slots)
    assert len(sizes) == 5 and sizes[4] < 2 * (slots[0] + slots[1])
    w = jnp.asarray(np.random.default_rng(1).normal(size=(*grid, N_BANDS**2)), jnp.float32)

    def grad(scan_slots):
        def loss(v):
            bsv = bsv_mesh_edgescan_scan_diff(
                v, f, N_BANDS, grid, res, SHELL, slots=slots, scan_slots=scan_slots
            )
            return jnp.sum(w * bsv)

        return np.asarray(jax.jit(jax.grad(loss))(x))

    compact, every = grad(sizes), grad(None)
    assert np.abs(every).max() > 0
    np.testing.assert_allclose(compact, every, rtol=1e-5, atol=1e-5 * np.abs(every).max())
    with pytest.raises(Exception, match="scanline derivative"):
        grad((*sizes[:4], 32))
    with pytest.raises(Exception, match="scanline derivative"):
        grad((32, *sizes[1:]))


def test_callable_scan_slots_are_called_only_by_a_derivative():
    x, f = _ico(1)
    x = jnp.asarray(x, jnp.float32)
    calls = []

    def measure():
        calls.append(1)
        return None  # the column slots for the rows, no compaction

    def loss(v):
        return jnp.sum(bsv_mesh_edgescan_scan_diff(v, f, 2, (2, 3), (8, 8), SHELL, scan_slots=measure) ** 2)

    jax.block_until_ready(jax.jit(loss)(x))
    assert not calls
    g = np.asarray(jax.grad(jax.jit(loss))(x))
    assert len(calls) == 1
    assert np.all(np.isfinite(g)) and np.abs(g).max() > 0
    assert math.isfinite(float(loss(x)))


def test_input_validation():
    x, f = _ico(1)
    with pytest.raises(ValueError, match="refine"):
        bsv_mesh_edgescan_scan_diff(x, f, refine=0)
    with pytest.raises(ValueError, match="scan_slots"):
        bsv_mesh_edgescan_scan_diff(x, f, scan_slots=(1, 2, 3))
    with pytest.raises(ValueError, match="shell > 1"):
        bsv_mesh_edgescan_scan_diff(x, f, shell=1.0)
    with pytest.raises(ValueError, match="sort key"):
        bsv_mesh_edgescan_scan_diff(x, f, directions=(512, 512))
    with pytest.raises(ValueError, match="shell > 1"):
        Method(shell=1.0, bsv_gradient="scanline")
    from jshadow.scene import bsv_gradient_mode

    assert bsv_gradient_mode(Method(bsv_gradient="scanline"), f) == "scanline"
