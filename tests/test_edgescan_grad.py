"""The edge-scan BSV's image-plane vertex derivative (``bsv_gradient = "image"``).

Checked in float64 against central differences of the converged forward pass of test_bsv_grad.py
(exact piecewise integration, never the sampled images), against the ray-cast derivative on
self-occluding meshes (a torus; the finely tessellated bunny_small, whose contour zigzags below the
pixel size), node visibility against a dense winding-number reference, the transpose relation
between jvp and grad, exact invariances, NaN-freedom at a zero-length edge, static sizes measured
only when a derivative is traced, and their overflow.
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
def test_finely_tessellated_self_occluding_mesh_matches_the_raycast_derivative():
    # The contour of a fine mesh zigzags below the pixel size; node visibility read off the sampled
    # image made the derivative 1.21-1.26x too large here (cosine 0.977-0.985). The winding number
    # of the silhouette at each node is exact: measured over two motions at 32² and 2 nodes, cosine
    # 0.9987-0.9989, norm ratio 0.95-1.00 (1.1-1.8 % apart at 128² and 8 nodes) against the
    # ray-cast derivative at 32 nodes.
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
    assert _cos(a, b) > 0.997, _cos(a, b)
    assert 0.93 < np.linalg.norm(a) / np.linalg.norm(b) < 1.07


def _dense_winding_chi(pair, total):
    """χ of every node from all silhouette edges of its view (no pixel lists, no layer image)."""
    p = {k: np.asarray(x, np.float64)[:total] for k, x in pair.items()}
    view = np.asarray(pair["view"])[:total]
    chi = np.zeros(p["node_x"].shape, bool)
    for g in np.unique(view):
        i = np.flatnonzero(view == g)
        ax, ay, bx, by, w = (p[k][i] for k in ("ax", "ay", "bx", "by", "w"))
        qx, qy = p["node_x"][i][..., None], p["node_y"][i][..., None]  # (n, nodes, 1) against (n,)
        inside = (np.minimum(ax, bx) <= qx) & (qx < np.maximum(ax, bx))
        below = ((bx - ax) * (qy - ay) - (by - ay) * (qx - ax)) * np.sign(bx - ax) > 0
        own = np.eye(len(i), dtype=bool)[:, None, :]
        below_count = np.sum(np.where(inside & below & ~own, w * np.sign(bx - ax), 0.0), axis=-1)
        chi[i] = (below_count == 0) | (below_count + (w * np.sign(bx - ax))[:, None] == 0)
    return chi


def _bunny_small_nodes():
    """bunny_small at 3 × 4 views of 32² pixels: prepared vertices, faces, edge table, layer counts,
    the measured gradient sizes and the keyword arguments of ``_visible_nodes`` (without tiers)."""
    from jshadow.visibility import _edgescan_grad
    from jshadow.visibility._edgescan import _prepare

    m = load_mesh(ASSETS / "bunny_small.obj")
    x, f = np.asarray(m.vertices, np.float32), np.asarray(m.faces, np.int32)
    grid, res = (3, 4), (32, 32)
    gs = _edgescan_grad.edgescan_grad_slots(x, f, grid, SHELL, directions=res)
    v, fj, table = _prepare(x, f, None)
    counts = _edgescan_grad._counts_of(v, fj, table, grid, res, SHELL)
    kw = dict(grid=grid, directions=res, shell=SHELL, slots=gs[0], nodes=2, piece_slots=gs[2], window=gs[3])
    return v, fj, table, counts, gs, kw


def test_node_visibility_is_the_winding_number_of_the_silhouette(monkeypatch):
    # the per-pixel lists and the layer count at the pixel centre give, at every node, the count of
    # the trapezoid rule over all silhouette edges of the view (float32 against float64: a few
    # nodes within rounding of another edge may differ)
    from jshadow.visibility import _edgescan_grad

    v, fj, table, counts, gs, kw = _bunny_small_nodes()

    def visible(v, counts):
        return _edgescan_grad._visible_nodes(v, fj, table, counts, **kw, long_slots=(gs[4], gs[5]))

    pair, chi, total, over, _ = jax.jit(visible)(v, counts)
    total = int(total)
    assert not bool(over) and total > 1000
    chi = np.asarray(chi)[:total]
    ref = _dense_winding_chi(pair, total)
    assert 0.1 < ref.mean() < 0.9  # both visible and hidden nodes occur
    assert np.sum(chi != ref) <= 2, np.sum(chi != ref)
    # the nodes of long lists read the rest of them: the same with every list read in one tier
    assert gs[4] > 0
    monkeypatch.setattr(_edgescan_grad, "_TIERS", (4 * gs[3], 32))
    # (a new function: jax.jit(visible) would reuse its trace with the old tiers)
    _, chi_one, _, _, _ = jax.jit(lambda v, c: visible(v, c))(v, counts)
    np.testing.assert_array_equal(np.asarray(chi_one)[:total], chi)
    # too small a list, window or tier raises the overflow flag (bsv_mesh_edgescan_diff raises on it);
    # the third tier is exercised with tiers of 4 entries
    every = gs[0] * 2
    cases = [("piece_slots", 64, (16, 32)), ("window", 8, (16, 32)), ("long_slots", (32, gs[5]), (16, 32))]
    for key, value, tiers in [*cases, ("long_slots", (every, 32), (4, 4))]:
        monkeypatch.setattr(_edgescan_grad, "_TIERS", tiers)
        small = {**kw, "long_slots": (gs[4], gs[5]), key: value}
        flag = jax.jit(lambda v, c, small=small: _edgescan_grad._visible_nodes(v, fj, table, c, **small)[3])
        assert bool(flag(v, counts)), key


def test_node_visibility_in_blocks_skips_only_padding(monkeypatch):
    # the tiers of list reading run in blocks, and a block wholly past the live rows (the padding of
    # the static sizes) is not computed: χ must be exactly the unsplit one, with blocks skipped
    from jshadow.visibility import _edgescan_grad

    v, fj, table, counts, gs, kw = _bunny_small_nodes()

    outs = {}
    for blocks in (1, 4, 7):  # a new function each time: jax.jit would reuse the first trace

        def visible(v, counts):
            return _edgescan_grad._visible_nodes(v, fj, table, counts, **kw, long_slots=(gs[4], gs[5]))

        monkeypatch.setattr(_edgescan_grad, "_live_blocks", lambda rows, b=blocks: b)
        outs[blocks] = jax.jit(visible)(v, counts)
    total = int(outs[1][2])
    assert 2 * total < 0.75 * 2 * gs[0]  # the last of 4 blocks of tier 1 holds padding only: skipped
    assert int(outs[1][4][1][0]) < 0.75 * gs[4]  # likewise the second tier's last block
    for blocks in (4, 7):
        np.testing.assert_array_equal(np.asarray(outs[blocks][1]), np.asarray(outs[1][1]))
        assert int(outs[blocks][2]) == total and not bool(outs[blocks][3])


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


def test_auto_gradient_is_image_where_the_forward_pass_is_the_edgescan():
    from jshadow.scene import bsv_gradient_mode

    _, f = _ico(1)
    open_mesh = f[1:]  # one face removed: not closed, the edge-scan does not apply
    assert Method().bsv_gradient == "auto"
    assert bsv_gradient_mode(Method(), f) == "image"
    assert bsv_gradient_mode(Method(bsv_method="edgescan"), f) == "image"
    for method, faces in (
        (Method(), open_mesh),
        (Method(shell=1.0), f),
        (Method(bsv_method="brute"), f),
        (Method.paper(), f),
        (Method(bsv_gradient="raycast"), f),
    ):
        assert bsv_gradient_mode(method, faces) == "raycast", method
    assert bsv_gradient_mode(Method(bsv_gradient="image"), f) == "image"


def test_traced_overflow_of_gradient_slots_raises():
    x, f = _ico(2)
    x = jnp.asarray(x, jnp.float32)

    @jax.jit
    def loss(v):
        return jnp.sum(bsv_mesh_edgescan_diff(v, f, 3, (3, 4), (16, 16), SHELL, grad_slots=32))

    with pytest.raises(Exception, match="gradient slots overflowed"):
        jax.block_until_ready(jax.grad(loss)(x))
    assert math.isfinite(float(loss(x)))  # the primal alone does not need the slots


def test_callable_grad_slots_are_measured_when_a_derivative_is_traced():
    # grad_slots may be a function: a forward pass never calls it; a derivative calls it once per
    # trace, outside the trace (here grad of jit, where the derivative rule is traced after the
    # forward; eager and jit-of-grad at scene level: test_render_grad.py)
    x, f = _ico(1)
    x = jnp.asarray(x, jnp.float32)
    calls = []

    def measure():
        calls.append(1)
        return 256  # pairs (every node keeps a slot): no counting passes to compile here

    def loss(v):
        return jnp.sum(bsv_mesh_edgescan_diff(v, f, 2, (2, 3), (8, 8), SHELL, grad_slots=measure) ** 2)

    jax.block_until_ready(jax.jit(loss)(x))
    assert not calls
    g = np.asarray(jax.grad(jax.jit(loss))(x))
    assert len(calls) == 1
    assert np.all(np.isfinite(g)) and np.abs(g).max() > 0


def test_node_compaction_keeps_the_gradient_and_overflow_raises():
    # grad_slots = (pairs, nodes, pieces, window, long, longer): only the visible nodes get a slot in the
    # linear part; an int gives every node one (and generous pixel lists). Same derivative; too few
    # slots raise, also under jax.jit(jax.grad(...)), where the primal (and a check on it alone) is
    # dead code (the pixel lists' sizes: test_node_visibility_is_the_winding_number_of_the_silhouette).
    from jshadow.visibility import edgescan_grad_slots

    m = load_mesh(ASSETS / "bunny_small.obj")
    x, f = jnp.asarray(m.vertices, jnp.float32), np.asarray(m.faces)
    grid, res = (3, 4), (32, 32)
    slots = edgescan_grad_slots(x, f, grid, SHELL, directions=res)
    pairs, nodes, pieces, window, long, longer = slots
    assert nodes < 2 * pairs and longer <= long < 2 * pairs
    w = jnp.asarray(np.random.default_rng(1).normal(size=(*grid, N_BANDS**2)), jnp.float32)

    def grad(slots):
        def loss(v):
            return jnp.sum(w * bsv_mesh_edgescan_diff(v, f, N_BANDS, grid, res, SHELL, grad_slots=slots))

        return np.asarray(jax.jit(jax.grad(loss))(x))

    compact, every = grad(slots), grad(pairs)
    assert np.abs(every).max() > 0
    np.testing.assert_allclose(compact, every, rtol=1e-5, atol=1e-5 * np.abs(every).max())
    with pytest.raises(Exception, match="gradient slots overflowed"):
        grad((pairs, 32, pieces, window, long, longer))


def test_small_divmod_is_exact_up_to_its_bound():
    # the pixel lists split an entry's index in its box into row and column through a float32
    # quotient; exact for 0 <= a < 2^20 (every box of up to 1024² pixels)
    from jshadow.visibility._edgescan_grad import _small_divmod

    b = np.repeat(np.arange(1, 65, dtype=np.int32), 64 * 64)
    a = (np.arange(b.size, dtype=np.int32) % (64 * 64)) * b // 64  # a spread of a < 64·b for each b
    rng = np.random.default_rng(0)
    b2 = rng.integers(1, 1025, 200_000).astype(np.int32)
    a2 = rng.integers(0, 1 << 20, 200_000).astype(np.int32)
    edge = np.arange(1, 1025, dtype=np.int32)
    a3 = np.concatenate([((1 << 20) // edge) * edge - 1, ((1 << 20) // edge - 1) * edge])  # k·b − 1, k·b
    b3 = np.concatenate([edge, edge])
    for aa, bb in ((a, b), (a2, b2), (a3, b3)):
        q, r = jax.jit(_small_divmod, static_argnums=2)(jnp.asarray(aa), jnp.asarray(bb), 1 << 20)
        np.testing.assert_array_equal(q, aa // bb)
        np.testing.assert_array_equal(r, aa % bb)
    q, r = _small_divmod(jnp.asarray([7]), jnp.asarray([3]), 1 << 21)  # above the bound: integers
    assert (int(q[0]), int(r[0])) == (2, 1)


def test_crossing_counts_of_pixel_relative_entries_match_a_direct_count():
    # _entries stores each list entry relative to its pixel centre C, oriented with C on its right,
    # with its count change and pair slot in one number; _crossings then counts the signed
    # crossings of C → q. Against the direct formula Σ w'·(sgn s'(q) − sgn s'(C))/2 over the edges
    # that cross the segment, leaving out the node's own pair; edges through C never count
    from jshadow.visibility._edgescan_grad import _centre, _crossings, _entries

    rng = np.random.default_rng(3)
    nx = ny = 4
    shell = 1.5
    tan_a = 1.0 / math.sqrt(shell * shell - 1.0)
    s, width = 64, 64
    pair = {k: jnp.asarray(rng.uniform(-tan_a, tan_a, s), jnp.float32) for k in ("ax", "ay", "bx", "by")}
    pair["w"] = jnp.asarray(rng.choice([-1.0, 1.0], s), jnp.float32)
    pix = 5  # every entry listed in pixel (row 1, col 1)
    c = _centre(jnp.asarray(1), tan_a, 4, jnp.float32)
    cx = cy = float(c)
    for i, axis in enumerate("xxyy"):  # C on the lines of four edges: x = C_x or y = C_y, exactly
        for end in "ab":
            pair[end + axis] = pair[end + axis].at[i].set(c)
    skey = jnp.full(s, pix, jnp.int32)
    sowner = jnp.arange(s, dtype=jnp.int32)
    table = _entries(pair, skey, sowner, directions=(ny, nx), shell=shell, window=width)
    assert np.all(np.asarray(table)[:4, 4] == 0) and np.all(np.asarray(table)[4:s, 4] != 0)  # c = 0 on C
    m = 200
    qx = cx + rng.uniform(-0.5, 0.5, m) * (2 * tan_a / nx)
    qy = cy + rng.uniform(-0.5, 0.5, m) * (2 * tan_a / ny)
    sid = rng.integers(0, s, m).astype(np.int32)
    got = _crossings(
        table,
        jnp.zeros(m, jnp.int32),
        jnp.full(m, s, jnp.int32),
        jnp.asarray(sid),
        jnp.asarray(qx - cx, jnp.float32),
        jnp.asarray(qy - cy, jnp.float32),
        lo=0,
        width=width,
    )
    p = {k: np.asarray(v, np.float64) for k, v in pair.items()}

    def orient(ax, ay, bx, by, x, y):
        return (bx - ax) * (y - ay) - (by - ay) * (x - ax)

    want = np.zeros(m)
    for j in range(m):
        for e in range(s):
            if e == sid[j]:
                continue
            a_x, a_y, b_x, b_y = p["ax"][e], p["ay"][e], p["bx"][e], p["by"][e]
            s_c, s_q = orient(a_x, a_y, b_x, b_y, cx, cy), orient(a_x, a_y, b_x, b_y, qx[j], qy[j])
            d_a, d_b = orient(cx, cy, qx[j], qy[j], a_x, a_y), orient(cx, cy, qx[j], qy[j], b_x, b_y)
            if s_c * s_q < 0 and d_a * d_b < 0:
                want[j] += 0.5 * p["w"][e] * (np.sign(s_q) - np.sign(s_c))
    assert np.abs(want).max() >= 2  # several crossings per segment, of both signs
    np.testing.assert_array_equal(np.asarray(got), want)
