"""Meshes: shipped assets, loading, validation, manifold test, bounding sphere, normals, procedural."""

import re
import subprocess
import sys
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import BATCH_SHAPES, subprocess_env

from jshadow._numerics import eps
from jshadow.geometry import (
    NORMAL_FALLBACK,
    Mesh,
    MeshWarning,
    bounding_sphere,
    egg,
    face_areas,
    face_normals,
    icosphere,
    load_mesh,
    mesh_is_closed_manifold,
    normalize_to_unit_sphere,
    point_mesh_distance2,
    point_triangle_distance2,
    remove_degenerate_faces,
    save_mesh,
    signed_volume,
    validate_mesh,
    vertex_normals,
    with_center_anchors,
)

ASSETS = Path(__file__).resolve().parents[1] / "assets"


def _sources_table():
    """Rows (file, V, F) of the mesh table in assets/SOURCES.md."""
    rows = []
    for line in (ASSETS / "SOURCES.md").read_text().splitlines():
        m = re.match(r"\|\s*`([^`]+\.(?:obj|ply))`\s*\|\s*(\d+)\s*\|\s*(\d+)\s*\|\s*(\w+)", line)
        if m:
            rows.append((m.group(1), int(m.group(2)), int(m.group(3)), m.group(4) == "yes"))
    return rows


def _cube():
    v = np.array([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)])
    # outward-wound triangles of the unit cube (vertex index = 4x + 2y + z)
    f = np.array(
        [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
         [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
    )  # fmt: skip
    return v, f


def _write(path, text):
    path.write_text(text)
    return path


# ---------------------------------------------------------------- shipped assets


def test_sources_table_lists_every_shipped_mesh():
    rows = _sources_table()
    listed = {r[0] for r in rows}
    shipped = {p.name for p in ASSETS.iterdir() if p.suffix in (".obj", ".ply")}
    assert listed == shipped == {"bunny.obj", "bunny_small.obj", "spot.obj", "airplane.obj"}
    text = (ASSETS / "SOURCES.md").read_text()
    for credit in ("Stanford", "CC BY 3.0", "YahooJAPAN", "Oded Stein", "Keenan Crane", "Poly Haven", "CC0"):
        assert credit in text


@pytest.mark.parametrize("row", _sources_table(), ids=lambda r: r[0])
def test_shipped_mesh_loads_with_the_counts_in_sources(row):
    name, nv, nf, closed = row
    mesh = load_mesh(ASSETS / name)  # warnings are errors: a clean mesh loads silently
    assert mesh.vertices.shape == (nv, 3) and mesh.faces.shape == (nf, 3)
    assert mesh.faces.dtype == jnp.int32 and mesh.vertices.dtype == jnp.result_type(float)
    assert mesh_is_closed_manifold(mesh.faces) == closed
    assert float(signed_volume(mesh.vertices, mesh.faces)) > 0  # outward winding
    # vertex order is the file's (process=False): compare with the raw "v" lines
    lines = (ASSETS / name).read_text().splitlines()
    raw = np.array([ln.split()[1:4] for ln in lines if ln.startswith("v ")]).astype(np.float64)
    np.testing.assert_allclose(np.asarray(mesh.vertices), raw, rtol=eps(np.float32))


@pytest.mark.parametrize("name", ["venice_sunset_512x256.hdr", "studio_small_03_512x256.hdr"])
def test_shipped_envmaps_are_radiance_files_of_the_stated_size(name):
    head = (ASSETS / "envmaps" / name).read_bytes()[:400]
    assert head.startswith(b"#?RADIANCE")
    assert b"-Y 256 +X 512" in head


# ---------------------------------------------------------------- loading and validation


@pytest.mark.parametrize("ext", ["ply", "stl", "obj", "glb"])
def test_round_trip_through_trimesh(tmp_path, ext):
    mesh = icosphere(1, dtype=jnp.float32)
    path = tmp_path / f"ball.{ext}"
    save_mesh(mesh, path)
    back = load_mesh(path)
    assert back.faces.shape == mesh.faces.shape and back.vertices.shape == mesh.vertices.shape
    assert mesh_is_closed_manifold(back.faces)
    if ext in ("ply", "obj", "glb"):  # indexed formats keep the vertex order
        np.testing.assert_allclose(back.vertices, mesh.vertices, atol=eps(np.float32))
        np.testing.assert_array_equal(back.faces, mesh.faces)
    else:  # STL has no shared vertices: merged in first-occurrence order; same triangles
        tri = np.asarray(mesh.vertices)[np.asarray(mesh.faces)]
        tri_back = np.asarray(back.vertices)[np.asarray(back.faces)]
        np.testing.assert_allclose(tri_back, tri, atol=eps(np.float32))
    np.testing.assert_allclose(
        signed_volume(back.vertices, back.faces),
        signed_volume(mesh.vertices, mesh.faces),
        rtol=eps(np.float32, 10),
    )


def test_quads_are_triangulated(tmp_path):
    v, _ = _cube()
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    text = "".join(f"v {a} {b} {c}\n" for a, b, c in v) + "".join(
        "f " + " ".join(str(i + 1) for i in q) + "\n" for q in quads
    )
    mesh = load_mesh(_write(tmp_path / "cube.obj", text))
    assert mesh.faces.shape == (12, 3)
    assert mesh_is_closed_manifold(mesh.faces)
    np.testing.assert_allclose(float(signed_volume(mesh.vertices, mesh.faces)), 1.0, rtol=eps(np.float32))


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n", "non-finite"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 inf\nf 1 2 3\n", "non-finite"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 5\n", "out of range"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\n", "no faces"),
        ("", "no faces"),
        ("v 0 0 0\nv 1 0 0\nv 2 0 0\nv 0 0 0\nf 1 2 3\nf 1 4 2\n", "degenerate"),
    ],
)
def test_load_errors_name_the_file_and_the_problem(tmp_path, text, problem):
    path = _write(tmp_path / "broken_mesh.obj", text)
    with pytest.raises(ValueError, match=problem) as info:
        load_mesh(path)
    assert "broken_mesh.obj" in str(info.value)


def test_ply_with_out_of_range_index(tmp_path):
    text = (
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n"
    )
    with pytest.raises(ValueError, match=r"bad_index\.ply.*out of range.*\[0, 1, 7\]"):
        load_mesh(_write(tmp_path / "bad_index.ply", text))


def test_missing_and_unreadable_files(tmp_path):
    with pytest.raises(ValueError, match=r"not found.*nowhere\.obj"):
        load_mesh(tmp_path / "nowhere.obj")
    with pytest.raises(ValueError, match=r"cannot read mesh file .*junk\.ply"):
        load_mesh(_write(tmp_path / "junk.ply", "this is not a ply file\n"))


def test_validate_mesh_errors_directly():
    v, f = _cube()
    validate_mesh(v, f, "cube")  # clean: no error, no warning
    with pytest.raises(ValueError, match=r"cube: .*non-finite.*vertex 2"):
        validate_mesh(np.where(np.arange(8)[:, None] == 2, np.nan, v), f, "cube")
    with pytest.raises(ValueError, match=r"cube: face index out of range: face 3 is \[4, 7, -1\]"):
        validate_mesh(v, np.where(np.arange(12)[:, None] == 3, [[4, 7, -1]], f), "cube")
    with pytest.raises(ValueError, match=r"cube: mesh has no faces"):
        validate_mesh(v, np.zeros((0, 3), np.int64), "cube")
    with pytest.raises(ValueError, match=r"cube: all 2 faces are degenerate"):
        validate_mesh(v, np.array([[0, 0, 1], [0, 1, 1]]), "cube")
    with pytest.raises(ValueError, match=r"cube: face indices must be integers"):
        validate_mesh(v, f.astype(np.float64), "cube")
    with pytest.raises(ValueError, match=r"cube: vertices must have shape \(V, 3\)"):
        validate_mesh(v[:, :2], f, "cube")


def test_open_mesh_warns_but_loads(tmp_path):
    sphere = icosphere(1)
    open_faces = np.asarray(sphere.faces)[1:]  # one hole
    path = tmp_path / "holey.ply"
    save_mesh(Mesh(sphere.vertices, open_faces), path)
    with pytest.warns(MeshWarning, match=r"holey\.ply.*open or non-manifold"):
        mesh = load_mesh(path)
    assert mesh.faces.shape == (79, 3)
    n = vertex_normals(mesh.vertices, mesh.faces)  # and it still works
    assert bool(jnp.all(jnp.isfinite(n)))
    with pytest.warns(MeshWarning, match="open or non-manifold"):
        validate_mesh(sphere.vertices, open_faces, "holey")


def test_degenerate_faces_are_removed_with_a_warning(tmp_path):
    v, f = _cube()
    v = np.concatenate([v, [[0.5, 0.0, 0.0]]])  # vertex 8 on the edge 0-4
    f = np.concatenate([f, [[0, 8, 4], [0, 0, 1]]])  # a collinear sliver and a repeated index
    mesh = Mesh(v, f, name="cube+slivers")
    with pytest.warns(MeshWarning, match=r"cube\+slivers: removed 2 degenerate"):
        clean = remove_degenerate_faces(mesh)
    np.testing.assert_array_equal(clean.faces, f[:12])
    assert remove_degenerate_faces(clean) is clean  # nothing to do: no warning
    path = tmp_path / "slivers.obj"
    save_mesh(mesh, path)
    with pytest.warns(MeshWarning) as record:
        loaded = load_mesh(path)
    messages = " ".join(str(w.message) for w in record)
    assert "removed 2 degenerate" in messages
    assert loaded.faces.shape == (12, 3)


def test_closed_manifold_detection():
    v, f = _cube()
    assert mesh_is_closed_manifold(f)
    flipped = f.copy()
    flipped[0] = flipped[0, ::-1]
    assert not mesh_is_closed_manifold(flipped)  # inconsistent winding
    assert not mesh_is_closed_manifold(f[1:])  # open
    assert not mesh_is_closed_manifold(np.concatenate([f, f[:1]]))  # an edge in three faces
    assert not mesh_is_closed_manifold(np.zeros((0, 3), np.int64))
    two_cubes = np.concatenate([f, f + 8])  # closed but two components: still closed manifold
    assert mesh_is_closed_manifold(two_cubes)


def test_mesh_checks_shapes():
    v, f = _cube()
    with pytest.raises(ValueError, match=r"vertices must have shape \(V, 3\)"):
        Mesh(v[:, :2], f)
    with pytest.raises(ValueError, match=r"faces must have shape \(F, 3\)"):
        Mesh(v, f[:, :2])
    with pytest.raises(ValueError, match="integer"):
        Mesh(v, f.astype(np.float32))
    assert Mesh(v, f.astype(np.int64)).faces.dtype == jnp.int32


# ---------------------------------------------------------------- bounding sphere


@pytest.mark.usefixtures("x64")
def test_bounding_sphere_of_known_point_sets():
    box = np.array([[x, y, z] for x in (-1.0, 3.0) for y in (0.0, 2.0) for z in (5.0, 6.0)])
    c, r = bounding_sphere(box)
    np.testing.assert_allclose(c, [1.0, 1.0, 5.5])
    np.testing.assert_allclose(r, np.sqrt(4.0 + 1.0 + 0.25))
    # the AABB centre, not the minimal sphere: a far point on one side pulls the centre
    pts = np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0], [1.0, 1.0, 0.0], [1.0, -1.0, 0.0]])
    c, r = bounding_sphere(pts)
    np.testing.assert_allclose(c, [2.0, 0.0, 0.0])
    np.testing.assert_allclose(r, 2.0)
    c, r = bounding_sphere(np.array([[1.0, 2.0, 3.0]]))
    np.testing.assert_allclose(c, [1.0, 2.0, 3.0])
    assert float(r) == 0.0


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_bounding_sphere_batches_and_contains_all_vertices(rng, batch):
    v = rng.normal(size=(*batch, 17, 3))
    c, r = bounding_sphere(v)
    assert c.shape == (*batch, 3) and r.shape == batch
    flat_v = v.reshape(-1, 17, 3)
    for i, (ci, ri) in enumerate(zip(np.reshape(c, (-1, 3)), np.reshape(r, (-1,)))):
        cc, rr = bounding_sphere(flat_v[i])
        np.testing.assert_allclose(ci, cc, rtol=eps(np.float64))
        np.testing.assert_allclose(ri, rr, rtol=eps(np.float64))
        d = np.linalg.norm(flat_v[i] - ci, axis=-1)
        assert d.max() <= ri * (1 + eps(np.float64)) and np.isclose(d.max(), ri)


@pytest.mark.usefixtures("x64")
def test_bounding_sphere_gradient_matches_finite_differences(rng):
    v = rng.normal(size=(9, 3))
    w = rng.normal(size=3)

    def f(v):
        c, r = bounding_sphere(v)
        return jnp.dot(c, w) + 2.0 * r

    g = jax.grad(f)(v)
    h = 1e-6
    fd = np.zeros_like(v)
    for i in range(v.shape[0]):
        for k in range(3):
            e = np.zeros_like(v)
            e[i, k] = h
            fd[i, k] = (f(v + e) - f(v - e)) / (2 * h)
    np.testing.assert_allclose(g, fd, atol=1e-7)
    # only the extreme vertices (per-axis min/max, farthest) receive gradient
    extreme = set(np.argmin(v, 0)) | set(np.argmax(v, 0))
    far = int(np.argmax(np.linalg.norm(v - np.asarray(bounding_sphere(v)[0]), axis=-1)))
    touched = set(np.flatnonzero(np.abs(g).sum(-1) > 0))
    assert touched <= extreme | {far} and far in touched


@pytest.mark.usefixtures("x64")
def test_bounding_sphere_gradient_with_ties_and_zero_radius_is_finite():
    # two vertices tie for the maximum x and for the farthest distance
    v = jnp.array([[-1.0, 0.0, 0.0], [1.0, 0.5, 0.0], [1.0, -0.5, 0.0]])
    g = jax.grad(lambda v: bounding_sphere(v)[1] + bounding_sphere(v)[0][0])(v)
    assert bool(jnp.all(jnp.isfinite(g)))
    # d(center_x)/d(max x) = 1/2, split equally between the two tied vertices
    gx = jax.grad(lambda v: bounding_sphere(v)[0][0])(v)
    np.testing.assert_array_equal(gx[:, 0], [0.5, 0.25, 0.25])
    single = jnp.zeros((4, 3))  # all vertices equal: radius 0
    g0 = jax.grad(lambda v: bounding_sphere(v)[1])(single)
    assert bool(jnp.all(jnp.isfinite(g0)))


@pytest.mark.usefixtures("x64")
def test_center_anchors_centre_the_bounding_sphere_on_a_given_point(rng):
    # the box of vertices + anchors is c ± h: its centre is c, its radius the farthest vertex from c
    for trial in range(20):
        v = rng.normal(size=(7, 3)) * rng.uniform(0.1, 3.0, size=3)
        c = v.mean(0) + rng.normal(size=3) * 0.3 * (trial % 4)
        anchored = with_center_anchors(v, c)
        assert anchored.shape == (13, 3)
        np.testing.assert_array_equal(np.asarray(anchored[:7]), v)  # faces still index the vertices
        center, radius = bounding_sphere(anchored)
        np.testing.assert_allclose(np.asarray(center), c, rtol=0, atol=1e-14)
        np.testing.assert_allclose(float(radius), np.linalg.norm(v - c, axis=-1).max(), rtol=1e-14)
    # at the box centre, the sphere is the box-centred one
    box_c, box_r = bounding_sphere(v)
    center, radius = bounding_sphere(with_center_anchors(v, box_c))
    np.testing.assert_allclose(np.asarray(center), np.asarray(box_c), atol=1e-14)
    np.testing.assert_allclose(float(radius), float(box_r), rtol=1e-14)
    with pytest.raises(ValueError, match="vertices of shape"):
        with_center_anchors(np.zeros((0, 3)), c)
    with pytest.raises(ValueError, match="centre of shape"):
        with_center_anchors(v, np.zeros(2))


@pytest.mark.usefixtures("x64")
def test_center_anchors_sphere_gradient_matches_finite_differences(rng):
    # radius = max |v - c|, centre = c: d/dv reaches only the farthest vertex, d/dc is -unit + identity
    v = rng.normal(size=(9, 3))
    c = rng.normal(size=3) * 0.2
    w = rng.normal(size=3)

    def f(v, c):
        center, radius = bounding_sphere(with_center_anchors(v, c))
        return jnp.dot(center, w) + 2.0 * radius

    gv, gc = jax.grad(f, argnums=(0, 1))(v, c)
    far = int(np.argmax(np.linalg.norm(v - c, axis=-1)))
    unit = (v[far] - c) / np.linalg.norm(v[far] - c)
    expect_v = np.zeros_like(v)
    expect_v[far] = 2.0 * unit
    np.testing.assert_allclose(np.asarray(gv), expect_v, atol=1e-12)
    np.testing.assert_allclose(np.asarray(gc), w - 2.0 * unit, atol=1e-12)
    # a flat point set (h_y = 0: two anchors on c) and a single point (radius 0): finite
    flat = v.copy()
    flat[:, 1] = c[1]
    for pts in (flat, np.tile(c, (3, 1))):
        g = jax.grad(f, argnums=(0, 1))(pts, c)
        assert all(bool(jnp.all(jnp.isfinite(x))) for x in g)


_FUSED_MAX_SCRIPT = """
import jax, jax.numpy as jnp, numpy as np
from jshadow.geometry import bounding_sphere

def size(u):
    c, r = bounding_sphere(jnp.asarray([0.0, 1.0, 0.0]) + 0.6 * u)
    return jnp.sum(c) + r

f = jax.jit(jax.grad(size))
us = [np.random.default_rng(s).normal(size=(42, 3)).astype(np.float32) for s in range(20)]
print("non-finite seeds:", [s for s, u in enumerate(us) if not np.isfinite(np.asarray(f(u))).all()])
"""


def test_bounding_sphere_gradient_is_finite_when_xla_recomputes_the_extremes_differently():
    # jnp.max's derivative divides by the number of elements equal to the maximum. At XLA:CPU's
    # backend level 0 (with XLA's default kernel emitters) the kernel that takes the maximum and
    # the one that compares with it round c + 0.6·u differently, none is equal, and the gradient
    # was inf/NaN for 18 of these 20 point sets (and for a vertex of tests/test_stress.py).
    # bounding_sphere gathers at the argmax instead. The child's flags replace the suite's.
    env = subprocess_env()
    env["XLA_FLAGS"] = "--xla_cpu_multi_thread_eigen=false --xla_backend_optimization_level=0"
    p = subprocess.run(
        [sys.executable, "-c", _FUSED_MAX_SCRIPT], capture_output=True, text=True, timeout=300, env=env
    )
    assert p.returncode == 0, p.stderr
    assert "non-finite seeds: []" in p.stdout, p.stdout


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_normalize_to_unit_sphere(rng, batch):
    v = rng.normal(size=(*batch, 11, 3)) * 3.0 + 7.0
    u = normalize_to_unit_sphere(v)
    c, r = bounding_sphere(u)
    np.testing.assert_allclose(c, 0.0, atol=eps(np.float64))
    np.testing.assert_allclose(r, 1.0, rtol=eps(np.float64))
    c0, r0 = bounding_sphere(v)
    placed = np.asarray(c0)[..., None, :] + np.asarray(r0)[..., None, None] * u
    np.testing.assert_allclose(placed, v, rtol=eps(np.float64, 10))
    # a single point maps to the origin with a finite gradient
    p = jnp.ones((1, 3))
    np.testing.assert_array_equal(normalize_to_unit_sphere(p), 0.0)
    assert bool(jnp.all(jnp.isfinite(jax.grad(lambda p: normalize_to_unit_sphere(p).sum())(p))))


def test_normalized_bunny_is_inside_unit_sphere():
    mesh = load_mesh(ASSETS / "bunny_small.obj")
    u = normalize_to_unit_sphere(mesh.vertices)
    d = jnp.linalg.norm(u, axis=-1)
    assert float(d.max()) == pytest.approx(1.0, abs=eps(jnp.float32))
    np.testing.assert_allclose(0.5 * (u.min(0) + u.max(0)), 0.0, atol=eps(jnp.float32))


# ---------------------------------------------------------------- normals, areas, volume


def test_vertex_normals_of_icosphere_are_the_positions():
    errs = []
    for subdivisions in (1, 2, 3):
        s = icosphere(subdivisions)
        n = vertex_normals(s.vertices, s.faces)
        np.testing.assert_allclose(jnp.linalg.norm(n, axis=-1), 1.0, rtol=eps(jnp.float32))
        # the 12 valence-5 vertices of the icosahedron sit on symmetry axes: exact there
        np.testing.assert_allclose(n[:12], s.vertices[:12], atol=eps(jnp.float32))
        errs.append(float(jnp.max(jnp.linalg.norm(n - s.vertices, axis=-1))))
    # one subdivision is still vertex-transitive: exact; beyond, unequal face areas tilt the
    # average, an error that halves with each subdivision (first order in the edge length)
    assert errs[0] < eps(jnp.float32)
    assert errs[1] < 0.03
    assert 0.4 < errs[2] / errs[1] < 0.6


@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_vertex_normals_batch_and_jit(rng, batch):
    s = icosphere(1)
    scale = jnp.asarray(rng.uniform(0.5, 2.0, size=(*batch, 1, 3)), jnp.float32)
    v = s.vertices * scale
    n = jax.jit(vertex_normals)(v, s.faces)
    assert n.shape == (*batch, 42, 3)
    ref = vertex_normals(v.reshape(-1, 42, 3)[0], s.faces)
    np.testing.assert_allclose(n.reshape(-1, 42, 3)[0], ref, atol=eps(jnp.float32))


@pytest.mark.usefixtures("x64")
def test_vertex_normals_area_weighting_closed_form():
    # two triangles sharing vertex 0: one in the z=0 plane (area 2), one in the x=0 plane (area 1/2)
    v = jnp.array([[0.0, 0, 0], [2.0, 0, 0], [0.0, 2, 0], [0.0, 0, 1], [0.0, 1, 0]])
    f = jnp.array([[0, 1, 2], [0, 4, 3]], dtype=jnp.int32)
    n = vertex_normals(v, f)
    expected = np.array([0.5, 0.0, 2.0]) / np.hypot(0.5, 2.0)  # 2·(0,0,1) + 0.5·(1,0,0), normalised
    np.testing.assert_allclose(n[0], expected, rtol=eps(np.float64))
    np.testing.assert_allclose(n[1], [0.0, 0.0, 1.0])


@pytest.mark.usefixtures("x64")
def test_vertex_normal_fallback_and_gradients():
    s = icosphere(1, dtype=jnp.float64)
    v = jnp.concatenate([s.vertices, jnp.array([[5.0, 5.0, 5.0]])])  # vertex 42 is unreferenced
    n = vertex_normals(v, s.faces)
    np.testing.assert_array_equal(n[42], NORMAL_FALLBACK)
    w = jnp.asarray(np.random.default_rng(0).normal(size=v.shape))

    def f(v):
        return jnp.sum(vertex_normals(v, s.faces) * w)

    g = jax.grad(f)(v)
    assert bool(jnp.all(jnp.isfinite(g)))
    np.testing.assert_array_equal(g[42], 0.0)
    d = jnp.asarray(np.random.default_rng(1).normal(size=v.shape))
    _, jvp = jax.jvp(f, (v,), (d,))  # forward and reverse mode agree
    np.testing.assert_allclose(jnp.sum(g * d), jvp, rtol=eps(np.float64, 100))
    h = 1e-6
    fd = (f(v + h * d) - f(v - h * d)) / (2 * h)
    np.testing.assert_allclose(jvp, fd, rtol=1e-7)
    # a face that collapses to a point gives a zero vector sum: fallback, finite gradient
    tiny = jnp.zeros((3, 3))
    g0 = jax.grad(lambda v: vertex_normals(v, jnp.array([[0, 1, 2]], jnp.int32)).sum())(tiny)
    assert bool(jnp.all(jnp.isfinite(g0)))


@pytest.mark.usefixtures("x64")
def test_areas_volume_and_face_normals():
    v, f = _cube()
    v = jnp.asarray(v)
    f = jnp.asarray(f, jnp.int32)
    np.testing.assert_allclose(face_areas(v, f), 0.5)
    np.testing.assert_allclose(signed_volume(v, f), 1.0)
    np.testing.assert_allclose(signed_volume(v, f[:, ::-1]), -1.0)
    np.testing.assert_allclose(signed_volume(2.0 * v + 3.0, f), 8.0)  # translation-invariant
    centroid = v[f].mean(axis=1) - 0.5
    nrm = face_normals(v, f)
    np.testing.assert_allclose(jnp.sum(nrm * centroid, -1), 0.5)  # outward, unit, face-centred
    s = icosphere(4, dtype=jnp.float64)
    area = float(face_areas(s.vertices, s.faces).sum())
    vol = float(signed_volume(s.vertices, s.faces))
    assert 4 * np.pi * 0.99 < area < 4 * np.pi and 4 / 3 * np.pi * 0.98 < vol < 4 / 3 * np.pi


# ---------------------------------------------------------------- procedural meshes


@pytest.mark.parametrize("subdivisions", [0, 1, 2])
def test_icosphere_and_egg_are_closed_and_outward(subdivisions):
    for mesh in (icosphere(subdivisions), egg(subdivisions)):
        assert mesh.vertices.shape == (10 * 4**subdivisions + 2, 3)
        assert mesh.faces.shape == (20 * 4**subdivisions, 3)
        assert mesh_is_closed_manifold(mesh.faces)
        validate_mesh(mesh.vertices, mesh.faces, mesh.name)  # no error, no warning
        c = 0.5 * (mesh.vertices.min(0) + mesh.vertices.max(0))
        centroid = mesh.vertices[mesh.faces].mean(axis=1) - c
        assert bool(jnp.all(jnp.sum(face_normals(mesh.vertices, mesh.faces) * centroid, -1) > 0))
    s = icosphere(subdivisions)
    np.testing.assert_allclose(jnp.linalg.norm(s.vertices, axis=-1), 1.0, rtol=eps(jnp.float32))


def test_egg_shape():
    s, e = icosphere(3), egg(3, stretch=0.2)
    assert float(e.vertices[:, 1].max()) == pytest.approx(1.4, rel=eps(jnp.float32))
    assert float(e.vertices[:, 1].min()) == pytest.approx(-1.0, rel=eps(jnp.float32))
    np.testing.assert_array_equal(e.vertices[:, [0, 2]], s.vertices[:, [0, 2]])
    # one end stretched: the top half is longer than the bottom half
    assert float(signed_volume(e.vertices, e.faces)) > float(signed_volume(s.vertices, s.faces))
    with pytest.raises(ValueError, match="stretch"):
        egg(1, stretch=1.5)
    with pytest.raises(ValueError, match="subdivisions"):
        icosphere(-1)


def test_loading_does_not_warn_for_clean_meshes(tmp_path):
    path = tmp_path / "egg.obj"
    save_mesh(egg(1), path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mesh = load_mesh(path)
    assert mesh_is_closed_manifold(mesh.faces)


def test_dtype_option(tmp_path):
    path = tmp_path / "ball.ply"
    save_mesh(icosphere(0), path)
    # float64 without x64 falls back to float32 quietly (warnings are errors here)
    assert load_mesh(path, dtype="float64").vertices.dtype == jnp.float32
    with jax.enable_x64(True):
        assert load_mesh(path, dtype="float64").vertices.dtype == jnp.float64
        assert load_mesh(path).vertices.dtype == jnp.float64
        assert egg(0, dtype=jnp.float32).vertices.dtype == jnp.float32
    with pytest.raises(ValueError, match="floating-point dtype"):
        icosphere(0, dtype="int32")


def _sampled_d2(p, tri, n=301):
    """Squared distance to a dense barycentric sampling of each triangle (an upper bound)."""
    u = np.linspace(0.0, 1.0, n)
    a, b = np.meshgrid(u, u)
    keep = a + b <= 1.0
    a, b = a[keep], b[keep]
    pts = (
        tri[:, None, 0]
        + a[:, None] * (tri[:, None, 1] - tri[:, None, 0])
        + b[:, None] * (tri[:, None, 2] - tri[:, None, 0])
    )
    return ((pts - p[:, None]) ** 2).sum(-1).min(1)


def test_point_triangle_distance_matches_a_dense_sampling(rng):
    tri = rng.normal(size=(300, 3, 3))
    p = 2.0 * rng.normal(size=(300, 3))
    got = np.asarray(point_triangle_distance2(jnp.asarray(p), jnp.asarray(tri)), np.float64)
    want = _sampled_d2(p, tri)
    # the sampling's spacing bounds its excess; float32 rounding the other side
    assert np.all(got <= want + 1e-5) and np.all(want - got <= 0.01 * np.maximum(want, 1e-2))
    # closed forms: above the inside (the plane's distance), beside an edge, beyond a corner
    t = jnp.asarray([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], jnp.float32)
    q = jnp.asarray([[0.2, 0.2, 0.5], [0.5, -1.0, 2.0], [2.0, 2.0, 0.0], [-1.0, -1.0, -1.0]], jnp.float32)
    np.testing.assert_allclose(point_triangle_distance2(q, t), [0.25, 5.0, 4.5, 3.0], rtol=1e-6)


@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_point_triangle_distance_batches(rng, batch):
    tri = rng.normal(size=(*batch, 3, 3)).astype(np.float32)
    p = rng.normal(size=(*batch, 3)).astype(np.float32)
    got = point_triangle_distance2(p, tri)
    assert got.shape == batch
    flat = point_triangle_distance2(p.reshape(-1, 3), tri.reshape(-1, 3, 3))
    np.testing.assert_allclose(np.asarray(got).reshape(-1), flat, rtol=1e-6)


def test_point_triangle_distance_is_finite_at_its_singular_points():
    """A degenerate triangle (no inside: its edges), a zero-length edge, and a point on a corner,
    an edge and the inside: finite values and gradients (jax.grad through the guarded divisions)."""
    flat = jnp.asarray([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]], jnp.float32)
    point = jnp.asarray([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]], jnp.float32)
    tri = jnp.asarray([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], jnp.float32)
    np.testing.assert_allclose(point_triangle_distance2(jnp.asarray([1.0, 1.0, 0.0]), flat), 1.0, rtol=1e-6)
    np.testing.assert_allclose(point_triangle_distance2(jnp.asarray([0.0, 2.0, 0.0]), point), 4.0, rtol=1e-6)
    for corners in (flat, point, tri):
        for p in ([0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.25, 0.25, 0.0], [1.0, 1.0, 0.0]):
            p = jnp.asarray(p, jnp.float32)
            gp, gt = jax.grad(lambda x, t: point_triangle_distance2(x, t), argnums=(0, 1))(p, corners)
            assert np.all(np.isfinite(gp)) and np.all(np.isfinite(gt))


def test_point_mesh_distance_is_the_nearest_face_and_zero_on_the_surface():
    m = icosphere(2)
    v, f = np.asarray(m.vertices, np.float64), np.asarray(m.faces)
    p = np.asarray([[0.0, 0.0, 2.0], [0.0, 3.0, 0.0], [0.1, 0.0, 0.0]], np.float32)
    got = np.asarray(point_mesh_distance2(p, v.astype(np.float32), f))
    each = np.asarray(point_triangle_distance2(p[:, None], v[f][None].astype(np.float32)))
    np.testing.assert_allclose(got, each.min(1), rtol=1e-6)
    # outside a unit icosphere the distance lies between the circumscribed sphere's and the faces'
    # inscribed one's; inside (to the surface, not the volume) likewise
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    r_in = float(np.min(np.abs(np.einsum("fi,fi->f", n, v[f[:, 0]])) / np.linalg.norm(n, axis=1)))
    d = np.sqrt(got)
    assert 1.0 - 1e-6 <= d[0] <= 2.0 - r_in + 1e-6 and 2.0 - 1e-6 <= d[1] <= 3.0 - r_in + 1e-6
    assert r_in - 0.1 - 1e-6 <= d[2] <= 0.9 + 1e-6
    assert float(point_mesh_distance2(v[:5].astype(np.float32), v.astype(np.float32), f).max()) < 1e-10
