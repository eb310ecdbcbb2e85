"""Edge-scan BSV: pixel-exact against brute-force rays through the same pixel centres, closed forms."""

import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jshadow._numerics import eps
from jshadow.geometry import bounding_sphere, icosphere, load_mesh
from jshadow.sh import sh_basis
from jshadow.visibility import ray_triangle_any_hit
from jshadow.visibility._bsv import BSV, bsv_mesh, bsv_sample_points
from jshadow.visibility._directions import cap_sh_projection
from jshadow.visibility._edgescan import (
    EdgeTable,
    bsv_mesh_edgescan,
    build_edge_table,
    edgescan_cone_directions,
    edgescan_occlusion,
    edgescan_slots,
)

ASSETS = Path(__file__).resolve().parents[1] / "assets"
GRID = (6, 10)
SHELL = 1.5


@pytest.fixture(scope="module")
def bunny_small():
    m = load_mesh(ASSETS / "bunny_small.obj")
    return m.vertices, m.faces


def _twist(vertices, amount):
    """Rotate each slice y = const about the y axis by ``amount · y`` radians (bunny spans y ∈ ~[-1, 1])."""
    v = jnp.asarray(vertices)
    ang = amount * v[:, 1]
    c, s = jnp.cos(ang), jnp.sin(ang)
    return jnp.stack([c * v[:, 0] + s * v[:, 2], v[:, 1], -s * v[:, 0] + c * v[:, 2]], axis=-1)


def _brute_image(vertices, faces, grid, directions, shell):
    """Occlusion of the pixel-centre rays by the watertight brute-force caster: (T, P, Ny, Nx)."""
    center, radius = bounding_sphere(vertices)
    points, frames = bsv_sample_points(center, radius, grid, shell)
    local, _ = edgescan_cone_directions(directions, shell, vertices.dtype)
    world = jnp.einsum("tpab,kb->tpka", frames, local)
    hit = ray_triangle_any_hit(points[:, :, None, :], world, vertices, faces)
    return np.asarray(hit).reshape(*grid, *directions)


def _mismatches(vertices, faces, grid=GRID, directions=(32, 32), shell=SHELL):
    occ, overflow = edgescan_occlusion(vertices, faces, grid, directions, shell)
    ref = _brute_image(vertices, faces, grid, directions, shell)
    assert not bool(overflow)
    assert occ.shape == ref.shape == (*grid, *directions)
    frac = float(np.mean(ref))
    assert 0.05 < frac < 0.95  # the comparison is not vacuous
    return int(np.sum(np.asarray(occ) != ref))


# ---------------------------------------------------------------------------------------------
# edge table
# ---------------------------------------------------------------------------------------------


def test_edge_table_icosphere():
    m = icosphere(1)
    table = build_edge_table(m.faces)
    assert isinstance(table, EdgeTable)
    nf = m.faces.shape[0]
    assert table.num_edges == 3 * nf // 2
    assert table.a.shape[0] % 32 == 0 and table.a.shape[0] > table.num_edges
    f = np.asarray(m.faces)
    a, b, t1, t2 = (np.asarray(x)[: table.num_edges] for x in (table.a, table.b, table.t1, table.t2))
    for e in range(0, table.num_edges, 7):  # a→b is a half-edge of t1, b→a of t2
        r1, r2 = list(f[t1[e]]), list(f[t2[e]])
        assert any(r1[k] == a[e] and r1[(k + 1) % 3] == b[e] for k in range(3))
        assert any(r2[k] == b[e] and r2[(k + 1) % 3] == a[e] for k in range(3))
    pad = np.asarray(table.a)[table.num_edges :]
    assert np.all(pad == 0) and np.all(
        np.asarray(table.t1)[table.num_edges :] == np.asarray(table.t2)[table.num_edges :]
    )


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda f: f[1:], "not closed"),
        (lambda f: np.concatenate([f[:1, ::-1], f[1:]]), "consistently wound"),
        (lambda f: np.concatenate([f, f[:1]]), "consistently wound"),
        (lambda f: np.concatenate([f, [[0, 0, 1]]]), "repeat a vertex"),
        (lambda f: f.astype(np.float32), "int array"),
    ],
)
def test_edge_table_rejects(edit, match):
    f = np.asarray(icosphere(1).faces)
    with pytest.raises(ValueError, match=match):
        build_edge_table(edit(f))


# ---------------------------------------------------------------------------------------------
# pixel-exact occlusion
# ---------------------------------------------------------------------------------------------


def test_icosphere_pixel_exact():
    m = icosphere(2)
    assert _mismatches(m.vertices, m.faces, directions=(16, 24)) == 0


def test_bunny_small_pixel_exact(bunny_small):
    v, f = bunny_small
    assert _mismatches(v, f) == 0


def test_twisted_bunny_small_pixel_exact(bunny_small):
    v, f = bunny_small
    assert _mismatches(_twist(v, 1.0), f, shell=1.25) == 0


def test_cone_directions_and_weights():
    d, w = edgescan_cone_directions((24, 20), SHELL)
    assert d.shape == (480, 3) and w.shape == (480,)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(d), axis=-1), 1.0, rtol=1e-6)
    # solid angle of the square image: a pyramid of half-width a at unit distance, 4·asin(a²/(1 + a²))
    a2 = 1.0 / (SHELL * SHELL - 1.0)
    np.testing.assert_allclose(float(jnp.sum(w)), 4.0 * math.asin(a2 / (1.0 + a2)), rtol=1e-5)
    # every direction of the cone sin α = 1/shell lies inside the square image
    corner = np.asarray(d)[0]
    assert corner[2] < math.sqrt(1.0 - 1.0 / SHELL**2)  # the corner pixel lies outside the cone
    # row-major: row index along local y, column along local x
    dd = np.asarray(d).reshape(24, 20, 3)
    assert np.all(np.diff(dd[:, 0, 1]) > 0) and np.all(np.diff(dd[0, :, 0]) > 0)


# ---------------------------------------------------------------------------------------------
# the BSV
# ---------------------------------------------------------------------------------------------


@pytest.mark.usefixtures("x64")
def test_sphere_matches_cap_closed_form():
    """A finely tessellated unit sphere: V = 1 − cap(α), sin α = r/R, projected in closed form."""
    m = icosphere(4, dtype=jnp.float64)
    n = 3
    bsv = bsv_mesh_edgescan(m.vertices, m.faces, n=n, grid=(3, 4), directions=(64, 64), shell=SHELL)
    assert isinstance(bsv, BSV)
    assert bsv.coeffs.shape == (3, 4, n * n) and bsv.coeffs.dtype == jnp.float64
    np.testing.assert_allclose(float(bsv.shell_radius), SHELL * float(bsv.radius), rtol=1e-12)
    full = jnp.zeros(n * n, jnp.float64).at[0].set(math.sqrt(4.0 * math.pi))
    expected = full - cap_sh_projection(jnp.asarray(math.sqrt(1.0 - 1.0 / SHELL**2)), n)
    # the inscribed polyhedron is slightly smaller than the sphere and the pixels are finite
    np.testing.assert_allclose(np.asarray(bsv.coeffs), np.broadcast_to(expected, bsv.coeffs.shape), atol=0.02)
    assert float(jnp.max(jnp.abs(bsv.coeffs - expected))) > 0  # not trivially equal


def test_bsv_coeffs_equal_projection_of_brute_image(bunny_small):
    v, f = bunny_small
    n = 4
    bsv = bsv_mesh_edgescan(v, f, n=n, grid=GRID, directions=(32, 32), shell=SHELL)
    ref = _brute_image(v, f, GRID, (32, 32), SHELL).reshape(*GRID, -1)
    d, w = edgescan_cone_directions((32, 32), SHELL)
    full = np.zeros(n * n, np.float32)
    full[0] = math.sqrt(4.0 * math.pi)
    expected = full - ref.astype(np.float32) @ (np.asarray(sh_basis(d, n)) * np.asarray(w)[:, None])
    np.testing.assert_allclose(np.asarray(bsv.coeffs), expected, atol=1e-4)
    c, r = bounding_sphere(v)
    np.testing.assert_allclose(np.asarray(bsv.center), np.asarray(c))
    np.testing.assert_allclose(float(bsv.radius), float(r))


def test_overflow_is_repaired_and_traced_overflow_raises(bunny_small):
    v, f = bunny_small
    table = build_edge_table(f)
    slots = edgescan_slots(v, f, GRID, (16, 16), SHELL, edge_table=table)
    good = bsv_mesh_edgescan(v, f, 2, GRID, (16, 16), SHELL, edge_table=table, slots=slots).coeffs
    tiny = bsv_mesh_edgescan(v, f, 2, GRID, (16, 16), SHELL, edge_table=table, slots=(1, 1, 1, 1)).coeffs
    np.testing.assert_array_equal(np.asarray(tiny), np.asarray(good))
    occ, overflow = edgescan_occlusion(v, f, GRID, (16, 16), SHELL, edge_table=table, slots=(1, 1, 1, 1))
    assert not bool(overflow)

    def coeffs(verts, slots):
        return bsv_mesh_edgescan(verts, f, 2, GRID, (16, 16), SHELL, edge_table=table, slots=slots).coeffs

    traced = jax.jit(lambda x: coeffs(x, slots))(v)
    np.testing.assert_allclose(np.asarray(traced), np.asarray(good), atol=eps(jnp.float32))
    with pytest.raises(Exception, match="overflowed"):
        jax.block_until_ready(jax.jit(lambda x: coeffs(x, (32, 1, 1, 1)))(v))
    default = jax.jit(lambda x: coeffs(x, None))(v)  # traced without slots: generous defaults
    np.testing.assert_allclose(np.asarray(default), np.asarray(good), atol=eps(jnp.float32))


def test_traced_overflow_can_fall_back_to_rays(bunny_small):
    # on_overflow="brute": a traced call whose slots overflow returns the brute-force BSV of the
    # same pose (rays over the Gauss-Legendre hemisphere) instead of raising; without overflow the
    # edge-scan's own result
    v, f = bunny_small
    table = build_edge_table(f)
    slots = edgescan_slots(v, f, GRID, (16, 16), SHELL, edge_table=table)

    def coeffs(verts, slots):
        kw = dict(edge_table=table, slots=slots, on_overflow="brute")
        return bsv_mesh_edgescan(verts, f, 2, GRID, (16, 16), SHELL, **kw).coeffs

    good = bsv_mesh_edgescan(v, f, 2, GRID, (16, 16), SHELL, edge_table=table, slots=slots).coeffs
    brute = bsv_mesh(v, f, 2, GRID, (16, 16), SHELL, method="brute").coeffs
    fine = jax.jit(lambda x: coeffs(x, slots))(v)
    np.testing.assert_allclose(np.asarray(fine), np.asarray(good), atol=eps(jnp.float32))
    fell_back = jax.jit(lambda x: coeffs(x, (32, 1, 1, 1)))(v)
    np.testing.assert_allclose(np.asarray(fell_back), np.asarray(brute), atol=eps(jnp.float32))
    assert float(jnp.max(jnp.abs(brute - good))) > 1e-3  # the two quadratures differ: it did switch
    with pytest.raises(ValueError, match="on_overflow"):
        bsv_mesh_edgescan(v, f, 2, GRID, (16, 16), SHELL, on_overflow="ignore")


def test_similarity_invariance(bunny_small):
    v, f = bunny_small
    a = bsv_mesh_edgescan(v, f, 2, GRID, (16, 16), SHELL).coeffs
    b = bsv_mesh_edgescan(
        0.5 * v + jnp.asarray([0.25, -2.0, 0.5], v.dtype), f, 2, GRID, (16, 16), SHELL
    ).coeffs
    # identical images up to pixel centres within rounding of an edge: at most a few pixels differ
    _, w = edgescan_cone_directions((16, 16), SHELL)
    assert float(jnp.max(jnp.abs(a - b))) <= 3 * float(jnp.max(w))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(shell=1.0), "shell > 1"),
        (dict(directions=(0, 8)), "directions"),
        (dict(grid=(4,)), "grid"),
        (dict(n=0), "bands"),
        (dict(slots=(4, 4)), "slots"),
    ],
)
def test_bad_arguments(kwargs, match):
    m = icosphere(0)
    with pytest.raises(ValueError, match=match):
        bsv_mesh_edgescan(m.vertices, m.faces, **kwargs)


def test_wrong_edge_table():
    with pytest.raises(ValueError, match="edge_table"):
        bsv_mesh_edgescan(
            icosphere(1).vertices, icosphere(1).faces, edge_table=build_edge_table(icosphere(0).faces)
        )


def test_edge_table_first_built_inside_a_derivative_rule_under_jit_is_concrete():
    # a topology first seen inside a custom_jvp rule under jax.jit(jax.grad(...)) (a deforming mesh
    # whose BSV input has the placed centre's six anchors: a vertex count no forward pass had
    # cached) came out of ensure_compile_time_eval as tracers and was cached as such, breaking the
    # next call that read the table on the host
    from jshadow.visibility._edgescan import _TABLES, _cached_edge_table, _topology_key

    faces = np.asarray(icosphere(1).faces, np.int32)
    rows = 977  # no other test's vertex count
    _TABLES.pop(_topology_key(faces, rows), None)
    seen = []

    @jax.custom_jvp
    def identity(x):
        return x

    @identity.defjvp
    def _jvp(primals, tangents):
        seen.append(_cached_edge_table(faces, rows).a)
        return primals[0], tangents[0]

    jax.jit(jax.grad(lambda x: identity(x).sum()))(jnp.ones(3))
    assert seen and not any(isinstance(a, jax.core.Tracer) for a in seen)
    assert not isinstance(_TABLES[_topology_key(faces, rows)].a, jax.core.Tracer)
