"""The edge-scan BSV's image-plane vertex derivative (``bsv_gradient = "image"``).

Checked in float64 against central differences of the converged forward pass of test_bsv_grad.py
(exact piecewise integration, never the sampled images), against the ray-cast derivative on a
finely tessellated self-occluding mesh (where the image visibility is biased: the test pins the
measured bias), for the transpose relation between jvp and grad, exact invariances, NaN-freedom
at a zero-length edge, and through a full render.
"""

import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_bsv_grad import N_BANDS, _cos, _ico, _rel, _smooth_motion, _torus, _visibility_ref

from jshadow.entities import Method
from jshadow.geometry import load_mesh
from jshadow.visibility import bsv_mesh_diff, bsv_mesh_edgescan, bsv_mesh_edgescan_diff, edgescan_slots
from jshadow.visibility._bsv import bsv_sample_points

ASSETS = Path(__file__).resolve().parents[1] / "assets"
SHELL = 1.5


def _ref_bsv(v, f, grid, shell=SHELL):
    """Converged BSV (T·P, n²) with the sample points of the bounding sphere of v."""
    c = 0.5 * (v.min(0) + v.max(0))
    r = np.linalg.norm(v - c, axis=1).max()
    pts, frames = bsv_sample_points(jnp.asarray(c), jnp.asarray(r), grid, shell)
    pts, frames = np.asarray(pts).reshape(-1, 3), np.asarray(frames).reshape(-1, 3, 3)
    return np.stack([_visibility_ref(v, f, q, fr) for q, fr in zip(pts, frames, strict=True)])


def _image_jvp(x, f, dx, grid, res, nodes=2, n=N_BANDS):
    # under jit: one compilation instead of an op-by-op eager trace (most of these tests' time)
    def tangent(v, dv):
        return jax.jvp(
            lambda w: bsv_mesh_edgescan_diff(w, f, n, grid, (res, res), SHELL, nodes=nodes), (v,), (dv,)
        )[1]

    return np.asarray(jax.jit(tangent)(jnp.asarray(x), jnp.asarray(dx)))


@pytest.mark.usefixtures("x64")
def test_convex_directional_derivative_vs_converged_differences(rng):
    # convex: every silhouette edge is visible, and only the bilinear Y·J table separates the
    # image-plane term from the exact derivative (measured 3.5e-4 at 64²)
    x, f = _ico(2)
    x = x * np.array([1.0, 0.8, 0.9]) + np.array([0.1, -0.2, 0.05])
    grid, h = (3, 4), 1e-5
    dx = _smooth_motion(rng, x)
    fd = (_ref_bsv(x + h * dx, f, grid) - _ref_bsv(x - h * dx, f, grid)) / (2 * h)
    tan = _image_jvp(x, f, dx, grid, 64).reshape(fd.shape)
    assert _rel(tan, fd) < 2e-3, _rel(tan, fd)
    assert _cos(tan.ravel(), fd.ravel()) > 1 - 1e-5


@pytest.mark.usefixtures("x64")
def test_self_occluding_torus_converges_to_the_raycast_derivative(rng):
    # The torus's few large faces make partly visible silhouette edges long: with enough nodes and
    # pixels the image-plane term converges to the ray-cast one (itself checked against converged
    # differences in test_bsv_grad.py). Measured over four motions: 0.5-2.1 % at 16 nodes and 128²;
    # 2.7-12 % (cosine >= 0.993) at the default 2 nodes and 32².
    x, f = _torus()
    x = x * np.array([1.0, 0.8, 0.9]) + np.array([0.1, -0.2, 0.05])
    grid = (3, 4)
    dx = _smooth_motion(rng, x)
    _, ray = jax.jvp(
        lambda v: bsv_mesh_diff(v, f, N_BANDS, grid, (8, 8), SHELL, nodes=32),
        (jnp.asarray(x),),
        (jnp.asarray(dx),),
    )
    ray = np.asarray(ray).ravel()
    fine = _image_jvp(x, f, dx, grid, 128, nodes=16).ravel()
    coarse = _image_jvp(x, f, dx, grid, 32).ravel()
    assert _rel(fine, ray) < 0.03, _rel(fine, ray)
    assert _cos(coarse, ray) > 0.99, _cos(coarse, ray)


@pytest.mark.usefixtures("x64")
def test_bias_on_a_finely_tessellated_self_occluding_mesh():
    # The contour of a fine mesh zigzags below the pixel size: silhouette edges folded back under
    # their neighbours by less than a pixel read as visible in the image. Measured on bunny_small
    # (1000 faces) at 32² against the ray-cast derivative at 32 nodes (itself ~1 % from converged):
    # cosine 0.977-0.985, magnitude 1.21-1.26x. This pins the documented bias.
    m = load_mesh(ASSETS / "bunny_small.obj")
    x, f = np.asarray(m.vertices, np.float64), np.asarray(m.faces)
    dx = _smooth_motion(np.random.default_rng(0), x)
    a = _image_jvp(x, f, dx, (2, 3), 32).ravel()
    _, b = jax.jvp(
        lambda v: bsv_mesh_diff(v, f, N_BANDS, (2, 3), (8, 8), SHELL, nodes=32),
        (jnp.asarray(x),),
        (jnp.asarray(dx),),
    )
    b = np.asarray(b).ravel()
    assert _cos(a, b) > 0.95
    assert 1.0 < np.linalg.norm(a) / np.linalg.norm(b) < 1.5


@pytest.mark.usefixtures("x64")
def test_primal_is_the_edgescan_and_grad_is_the_transposed_jvp(rng):
    x, f = _torus()
    grid = (3, 4)

    def bsv(v):
        return bsv_mesh_edgescan_diff(v, f, N_BANDS, grid, (32, 32), SHELL)

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
    # translation and uniform scaling about the centre leave the BSV unchanged: exactly zero
    scale = jnp.asarray(x - 0.5 * (x.min(0) + x.max(0)))
    for motion in (jnp.broadcast_to(jnp.asarray(rng.normal(size=3)), x.shape), scale):
        t = jvp(jnp.asarray(x), motion)
        assert float(jnp.max(jnp.abs(t))) <= 1e-12 * float(jnp.max(jnp.abs(tan)))


@pytest.mark.usefixtures("x64")
def test_zero_length_edge_is_nan_free():
    # two vertices of an octahedron on the same point: that edge projects to a point in every view
    # (n₃ = 0, no outward normal); its terms must vanish without NaN
    x = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64)
    f = np.array(
        [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]], np.int32
    )
    x[4] = x[0] * 1.0  # edge (0, 4) has zero length
    slots = edgescan_slots(x, f, (3, 4), (16, 16), SHELL)  # measured: traced defaults assume a larger mesh

    def loss(v):
        return jnp.sum(bsv_mesh_edgescan_diff(v, f, N_BANDS, (3, 4), (16, 16), SHELL, slots=slots) ** 2)

    g = jax.jit(jax.grad(loss))(jnp.asarray(x))
    assert bool(jnp.all(jnp.isfinite(g))) and float(jnp.max(jnp.abs(g))) > 0


def test_input_validation():
    x, f = _ico(1)
    with pytest.raises(ValueError, match="nodes"):
        bsv_mesh_edgescan_diff(x, f, nodes=0)
    with pytest.raises(ValueError, match="grad_slots"):
        bsv_mesh_edgescan_diff(x, f, grad_slots=0)
    with pytest.raises(ValueError, match="shell > 1"):
        bsv_mesh_edgescan_diff(x, f, shell=1.0)
    with pytest.raises(ValueError, match="bsv_gradient"):
        Method(bsv_gradient="smooth")
    with pytest.raises(ValueError, match="shell > 1"):
        Method(shell=1.0, bsv_gradient="image")


def test_traced_overflow_of_gradient_slots_raises():
    x, f = _ico(2)
    x = jnp.asarray(x, jnp.float32)

    @jax.jit
    def loss(v):
        return jnp.sum(bsv_mesh_edgescan_diff(v, f, 3, (3, 4), (16, 16), SHELL, grad_slots=32))

    with pytest.raises(Exception, match="gradient slots overflowed"):
        jax.block_until_ready(jax.grad(loss)(x))
    assert math.isfinite(float(loss(x)))  # the primal alone does not need the slots


def _fan_faces(f):
    """Per edge of ``f``: the faces _ring_fans encodes, and every face touching an end point except
    the edge's own two, both as sets of sorted vertex triples."""
    from jshadow.visibility._edgescan import build_edge_table
    from jshadow.visibility._edgescan_grad import _ring_fans

    table = build_edge_table(f)
    rim, at_b, face = _ring_fans(np.asarray(f, np.int32), table)
    a, b, t1, t2 = (np.asarray(x) for x in (table.a, table.b, table.t1, table.t2))
    for e in range(table.num_edges):
        centre = np.where(at_b[e], b[e], a[e])
        fans = {
            tuple(sorted((centre[i], rim[e, i], rim[e, i + 1])))
            for i in range(rim.shape[1] - 1)
            if face[e, i]
        }
        assert all(centre[i] == centre[i + 1] for i in range(rim.shape[1] - 1) if face[e, i])
        ring = {
            tuple(sorted(t))
            for k, t in enumerate(f.tolist())
            if (a[e] in t or b[e] in t) and k not in (t1[e], t2[e])
        }
        yield fans, ring


def test_fans_hold_the_faces_around_an_edge():
    # the node visibility test walks the faces around each end point as fans; they must be exactly
    # the faces touching a or b other than the edge's own two (bunny_small; and a vertex whose faces
    # form two separate fans: two tetrahedra sharing one vertex)
    m = load_mesh(ASSETS / "bunny_small.obj")
    pairs = list(_fan_faces(np.asarray(m.faces)))
    assert len(pairs) == 1500 and all(fans == ring for fans, ring in pairs)
    tet = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    bowtie = np.concatenate([tet, np.where(tet == 0, 0, tet + 3)])  # vertex 0 in both
    pairs = list(_fan_faces(bowtie))
    assert len(pairs) == 12 and all(fans == ring for fans, ring in pairs)
    # edge (0, 1): tetrahedron 1's other two faces and all three of tetrahedron 2 at vertex 0
    assert max(len(ring) for _, ring in pairs) == 5


def test_node_compaction_keeps_the_gradient_and_overflow_raises():
    # grad_slots = (pairs, nodes): only the nodes that pass the image test get a slot for the
    # face test; an int gives every node one. Same derivative; too few node slots raise, also
    # under jax.jit(jax.grad(...)), where the primal (and a check on it alone) is dead code.
    from jshadow.visibility import edgescan_grad_slots

    m = load_mesh(ASSETS / "bunny_small.obj")
    x, f = jnp.asarray(m.vertices, jnp.float32), np.asarray(m.faces)
    grid, res = (3, 4), (32, 32)
    pairs, nodes = edgescan_grad_slots(x, f, grid, SHELL, directions=res)
    assert nodes < 2 * pairs
    w = jnp.asarray(np.random.default_rng(1).normal(size=(*grid, N_BANDS**2)), jnp.float32)

    def grad(slots):
        def loss(v):
            return jnp.sum(w * bsv_mesh_edgescan_diff(v, f, N_BANDS, grid, res, SHELL, grad_slots=slots))

        return np.asarray(jax.jit(jax.grad(loss))(x))

    compact, every = grad((pairs, nodes)), grad(pairs)
    assert np.abs(every).max() > 0
    np.testing.assert_allclose(compact, every, rtol=1e-5, atol=1e-5 * np.abs(every).max())
    with pytest.raises(Exception, match="gradient slots overflowed"):
        grad((pairs, 32))
