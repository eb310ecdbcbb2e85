"""Scene configs: loading, validation errors, build_scene, parameter paths, shipped configs."""

import dataclasses
import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jshadow.config import (
    Config,
    ConfigError,
    build_scene,
    config_from_dict,
    get_param,
    load_config,
    param_paths,
    plane_receivers,
    rotate_latlong_y,
    set_param,
)
from jshadow.entities import Environment, MeshOccluder, Method, SphereLight, SphereOccluder

REPO = pathlib.Path(__file__).resolve().parents[1]
CONFIGS = sorted((REPO / "configs").glob("*.toml"))

BASE = """
[method]
sh_bands = 4

[environment]
type = "constant"
radiance = [1.0, 0.8, 0.6]

[[occluder]]
type = "sphere"
center = [0.2, 1.0, 0.0]
radius = 0.4

[[light]]
type = "sphere"
center = [1.0, 3.0, 0.5]
radius = 0.3
radiance = [10.0, 10.0, 10.0]

[receiver]
type = "plane"
center = [0.0, 0.0, 0.0]
size = [3.0, 3.0]
resolution = [9, 7]
albedo = [0.5, 0.5, 0.5]

[animation]
frames = 3
"""

OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 2\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


def base_dict(**tables):
    d = {
        "environment": {"type": "constant", "radiance": [1.0, 0.8, 0.6]},
        "occluder": [{"type": "sphere", "center": [0.2, 1.0, 0.0], "radius": 0.4}],
        "light": [
            {"type": "sphere", "center": [1.0, 3.0, 0.5], "radius": 0.3, "radiance": [10.0, 10.0, 10.0]}
        ],
        "receiver": {
            "center": [0.0, 0.0, 0.0],
            "size": [3.0, 3.0],
            "resolution": [9, 7],
            "albedo": [0.5] * 3,
        },
    }
    d.update(tables)
    return d


@pytest.fixture
def tmp_assets(tmp_path):
    (tmp_path / "tet.obj").write_text(OBJ)
    (tmp_path / "broken.obj").write_text("v 0 0 0\nv 1 0 0\nf 1 2 9\n")
    return tmp_path


# --- loading ---------------------------------------------------------------------------------------
def test_load_mirrors_toml(tmp_path):
    p = tmp_path / "scene.toml"
    p.write_text(BASE)
    cfg = load_config(p)
    assert isinstance(cfg, Config) and cfg.source == str(p)
    assert cfg.method.sh_bands == 4 and cfg.method.bsv_grid == (12, 20) and cfg.method.dtype == "float32"
    assert isinstance(cfg.occluder, tuple) and len(cfg.occluder) == 1 and len(cfg.light) == 1
    np.testing.assert_array_equal(cfg.occluder[0].center, np.float32([0.2, 1.0, 0.0]))
    assert cfg.receiver.resolution == (9, 7) and cfg.receiver.self_shadow is False
    assert cfg.animation.frames == 3 and cfg.fit is None
    assert cfg.environment.type == "constant" and float(cfg.environment.rotation_y) == 0.0


def test_numbers_are_float_leaves_and_the_rest_is_static(tmp_path):
    cfg = config_from_dict(base_dict())
    leaves = jax.tree_util.tree_leaves(cfg)
    assert len(leaves) == 10  # environment 2, occluder 2, light 3, receiver 3 (centre, size, albedo)
    assert all(isinstance(x, jax.Array) and x.dtype == jnp.float32 for x in leaves)
    assert cfg.occluder[0].radius.shape == () and cfg.light[0].radiance.shape == (3,)
    assert isinstance(cfg.receiver.resolution[0], int)
    # static fields are not leaves: resolution, type strings, method options
    assert 9 not in [np.asarray(x).tolist() for x in leaves]


def test_config_is_frozen():
    cfg = config_from_dict(base_dict())
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.receiver = None
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.occluder[0].radius = jnp.float32(1.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.method.sh_bands = 3


def test_defaults_and_float64(x64):
    d = base_dict(method={"dtype": "float64", "shell": 1.5, "bsv_method": "brute"})
    del d["environment"]
    cfg = config_from_dict(d)
    assert cfg.environment is None and cfg.animation.frames == 1
    assert cfg.occluder[0].radius.dtype == jnp.float64
    m = build_scene(cfg).method
    assert m.bsv_center == "placed"
    paper = config_from_dict(base_dict(method={"preset": "paper"})).method.to_method()
    assert (paper.bsv_center, paper.shell) == ("box", 1.0) and paper == Method.paper()
    placed = config_from_dict(base_dict(method={"preset": "paper", "bsv_center": "placed"}))
    assert placed.method.to_method().bsv_center == "placed"
    assert (m.sh_bands, m.directions, m.shell, m.bsv_method, m.dtype) == (
        4,
        (32, 32),
        1.5,
        "brute",
        "float64",
    )


# --- errors ----------------------------------------------------------------------------------------
def _sub(old, new):
    assert old in BASE
    return BASE.replace(old, new)


BAD = [
    # (toml text, substrings the one-line message must contain)
    (
        _sub("resolution = [9, 7]", "resolution = [9, 7]\nresolutoin = [1, 1]"),
        ["unknown key 'resolutoin' in [receiver]", "did you mean 'resolution'"],
    ),
    (_sub("[receiver]", "[recever]"), ["unknown key 'recever'", "did you mean 'receiver'"]),
    (_sub("radius = 0.4", "radius = -1.0"), ["occluder[0].radius", "positive", "-1.0"]),
    (_sub("radius = 0.4", 'radius = "big"'), ["occluder[0].radius", "expected a number", "string"]),
    (_sub("radius = 0.4", "radius = true"), ["occluder[0].radius", "boolean"]),
    (_sub("center = [0.2, 1.0, 0.0]", "center = [0.2, 1.0]"), ["occluder[0].center", "3 numbers", "2"]),
    (_sub("radiance = [10.0, 10.0, 10.0]", "radiance = [nan, 1.0, 1.0]"), ["light[0].radiance", "finite"]),
    (_sub("radius = 0.3", "radius = inf"), ["light[0].radius", "finite"]),
    (_sub("resolution = [9, 7]", "resolution = [0, 7]"), ["receiver.resolution", ">= 1"]),
    (_sub("resolution = [9, 7]", "resolution = [9.5, 7]"), ["receiver.resolution", "integer"]),
    (_sub("size = [3.0, 3.0]", "size = [3.0, 0.0]"), ["receiver.size", "positive"]),
    (_sub("radius = 0.4\n", "\n"), ["occluder[0].radius", "missing required key"]),
    (BASE.split("[receiver]")[0], ["receiver", "missing"]),
    (
        _sub('type = "sphere"\ncenter = [0.2', 'type = "cube"\ncenter = [0.2'),
        ["occluder[0].type", "'mesh'", "cube"],
    ),
    (_sub('type = "constant"', 'type = "hdri"'), ["environment.type", "did you mean 'hdr'"]),
    (_sub("frames = 3", "frames = 0"), ["animation.frames", ">= 1"]),
    (_sub("sh_bands = 4", "sh_bands = 9"), ["method.sh_bands", "1..8"]),
    (_sub("sh_bands = 4", "shell = 0.5"), ["method.shell", ">= 1"]),
    (_sub("sh_bands = 4", 'dtype = "float16"'), ["method.dtype", "float32"]),
    (_sub("sh_bands = 4", 'bsv_center = "centroid"'), ["method.bsv_center", "placed"]),
    (
        _sub("albedo = [0.5, 0.5, 0.5]", 'albedo = [0.5, 0.5, 0.5]\nself_shadow = "yes"'),
        ["receiver.self_shadow", "true or false"],
    ),
    (
        _sub("radius = 0.4", "radius = 0.4\ndeform = { type = 'bend', amount = 0.1 }"),
        ["occluder[0].deform", "only a mesh"],
    ),
    (_sub("radius = 0.4", "radius = = 0.4"), ["TOML syntax error", "line 12"]),
]


@pytest.mark.parametrize("text, expected", BAD, ids=[f"bad{i}" for i in range(len(BAD))])
def test_bad_inputs_raise_one_line_naming_the_key(tmp_path, text, expected):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(p)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(f"{p}: ")
    for s in expected:
        assert s in msg, msg
    assert isinstance(info.value, ValueError)


MESH_BAD = [
    (
        {"type": "mesh", "file": "nope.obj", "center": [0, 1, 0], "radius": 1},
        ["occluder[0].file", "not found"],
    ),
    (
        {"type": "mesh", "file": "broken.obj", "center": [0, 1, 0], "radius": 1},
        ["occluder[0].file", "broken.obj"],
    ),
    ({"type": "mesh", "center": [0, 1, 0], "radius": 1}, ["occluder[0].file", "exactly one"]),
    ({"type": "mesh", "shape": "cube", "center": [0, 1, 0], "radius": 1}, ["occluder[0].shape", "egg"]),
    (
        {
            "type": "mesh",
            "shape": "egg",
            "center": [0, 1, 0],
            "radius": 1,
            "deform": {"type": "bendy", "amount": 1},
        },
        ["occluder[0].deform.type", "did you mean 'bend'"],
    ),
    (
        {
            "type": "mesh",
            "shape": "egg",
            "center": [0, 1, 0],
            "radius": 1,
            "deform": {"type": "bend", "amont": 1},
        },
        ["unknown key 'amont'", "did you mean 'amount'"],
    ),
    (
        {
            "type": "mesh",
            "shape": "egg",
            "center": [0, 1, 0],
            "radius": 1,
            "deform": {"type": "bend", "amount": [1, 2, 3]},
        },
        ["occluder[0].deform.amount", "2 numbers"],
    ),
    (
        {
            "type": "mesh",
            "shape": "egg",
            "center": [0, 1, 0],
            "radius": 1,
            "deform": {"type": "squash_stretch", "amount": -1.5},
        },
        ["occluder[0].deform", "> -1"],
    ),
    (
        {
            "type": "mesh",
            "shape": "egg",
            "center": [0, 1, 0],
            "radius": 1,
            "deform": {"type": "bend", "amount": 1, "period": 2.0},
        },
        ["unknown key 'period'", "'bend'"],
    ),
]


@pytest.mark.filterwarnings("ignore::jshadow.geometry.MeshWarning")
@pytest.mark.parametrize("occ, expected", MESH_BAD, ids=[f"mesh{i}" for i in range(len(MESH_BAD))])
def test_bad_mesh_occluders(tmp_assets, occ, expected):
    with pytest.raises(ConfigError) as info:
        config_from_dict(base_dict(occluder=[occ]), source="cfg", root=tmp_assets)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith("cfg: ")
    for s in expected:
        assert s in msg, msg


def test_structural_errors():
    with pytest.raises(ConfigError, match=r"occluder: expected an array of tables \[\[occluder\]\]"):
        config_from_dict(base_dict(occluder={"type": "sphere"}))
    with pytest.raises(ConfigError, match=r"receiver: expected a table \[receiver\]"):
        config_from_dict(base_dict(receiver=[1, 2]))
    with pytest.raises(ConfigError, match=r"light\[1\]\.radius: missing required key"):
        config_from_dict(
            base_dict(light=[base_dict()["light"][0], {"center": [0, 1, 0], "radiance": [1, 1, 1]}])
        )


def test_hdr_needs_an_existing_file(tmp_path):
    env = {"type": "hdr", "file": "missing.hdr"}
    with pytest.raises(ConfigError, match=r"environment\.file: .*not found"):
        config_from_dict(base_dict(environment=env), root=tmp_path)
    with pytest.raises(ConfigError, match=r"environment\.file: .*only an environment of type 'hdr'"):
        config_from_dict(base_dict(environment={"type": "constant", "file": "x.hdr"}))
    (tmp_path / "junk.hdr").write_bytes(b"not a radiance file\n" * 4)
    with pytest.raises(ConfigError, match=r"environment\.file: .*junk\.hdr"):
        config_from_dict(base_dict(environment={"type": "hdr", "file": "junk.hdr"}), root=tmp_path)
    with pytest.raises(ConfigError, match=r"config file not found"):
        load_config(tmp_path / "nothing.toml")


# --- fit section and parameter paths -------------------------------------------------------------
FIT_BAD = [
    ({"params": ["occluder.0.radus"], "target_values": [1.0]}, ["fit.params[0]", "did you mean 'radius'"]),
    ({"params": ["receiver.resolution"], "target_values": [1.0]}, ["fit.params[0]", "static"]),
    ({"params": ["occluder.3.radius"], "target_values": [1.0]}, ["fit.params[0]", "out of range"]),
    ({"params": ["light.0.center"], "target_values": [1.0]}, ["fit.target_values[0]", "3 numbers"]),
    ({"params": ["light.0.radius"], "target_values": [1.0, 2.0]}, ["fit.target_values", "1 value"]),
    ({"params": ["light.0.radius"]}, ["fit.target_values", "exactly one"]),
    ({"params": ["light.0.radius"], "target_values": [1.0], "stesp": 3}, ["did you mean 'steps'"]),
    ({"params": ["light.0.radius"], "target_values": ["1.0"]}, ["fit.target_values[0]", "string"]),
    ({"params": ["light.0.radius"], "target_values": [1.0], "frame": 1}, ["fit.frame", "0..0"]),
    ({"params": "light.0.radius", "target_values": [1.0]}, ["fit.params", "list of strings"]),
    (
        {"params": ["light.0.radius"], "target_values": [1.0], "learning_rate": 0},
        ["fit.learning_rate", "positive"],
    ),
]


@pytest.mark.parametrize("fit, expected", FIT_BAD, ids=[f"fit{i}" for i in range(len(FIT_BAD))])
def test_bad_fit_sections(fit, expected):
    with pytest.raises(ConfigError) as info:
        config_from_dict(base_dict(fit=fit))
    for s in expected:
        assert s in str(info.value), str(info.value)


def test_fit_section_and_param_paths():
    fit = {
        "params": ["light.0.center", "occluder.0.radius"],
        "target_values": [[1.0, 2.0, 3.0], 0.5],
        "init": [[0.0, 3.0, 0.0], 0.3],
        "steps": 7,
        "regularization": 0.1,
    }
    cfg = config_from_dict(base_dict(fit=fit))
    assert cfg.fit.params == ("light.0.center", "occluder.0.radius") and cfg.fit.steps == 7
    assert cfg.fit.learning_rate == 0.05 and cfg.fit.regularization == 0.1
    np.testing.assert_array_equal(cfg.fit.target_values[0], np.float32([1, 2, 3]))
    assert cfg.fit.init[1].shape == ()
    paths = param_paths(cfg)
    assert {"light.0.center", "occluder.0.radius", "receiver.size", "environment.radiance"} <= set(paths)
    for p in paths:
        assert get_param(cfg, p) is not None
    assert get_param(cfg, "light.0.center") is cfg.light[0].center

    new = set_param(cfg, "occluder.0.radius", 0.25)
    assert float(new.occluder[0].radius) == 0.25 and float(cfg.occluder[0].radius) == np.float32(0.4)
    assert new.occluder[0].radius.dtype == jnp.float32
    np.testing.assert_array_equal(new.light[0].center, cfg.light[0].center)  # nothing else moved
    with pytest.raises(ConfigError, match=r"light\.0\.center: expected shape \(3,\)"):
        set_param(cfg, "light.0.center", 1.0)
    with pytest.raises(ConfigError, match="finite"):
        set_param(cfg, "occluder.0.radius", float("nan"))
    with pytest.raises(ConfigError, match=r"occluder\.0\.radius: expected positive"):
        set_param(cfg, "occluder.0.radius", -0.5)
    with pytest.raises(ConfigError, match="is a list: expected an index"):
        get_param(cfg, "occluder.center")


# --- build_scene -----------------------------------------------------------------------------------
def test_build_scene_entities():
    cfg = config_from_dict(base_dict(animation={"frames": 5}))
    scene = build_scene(cfg)
    (occ,), (light,) = scene.occluders, scene.lights
    assert isinstance(occ, SphereOccluder) and isinstance(light, SphereLight)
    np.testing.assert_array_equal(occ.center, cfg.occluder[0].center)
    np.testing.assert_array_equal(light.radiance, np.float32([10, 10, 10]))
    assert isinstance(scene.environment, Environment) and scene.environment.kind == "constant"
    assert scene.n_frames == 5 and scene.self_shadow is False
    sky = build_scene(config_from_dict(base_dict(environment={"type": "sky"})))
    assert sky.environment.kind == "sky"
    np.testing.assert_array_equal(sky.environment.radiance, np.ones(3, np.float32))


@pytest.mark.parametrize("nx, nz", [(9, 7), (1, 4), (2, 1)])
def test_plane_receivers_count_order_spacing_normals(nx, nz):
    c, size = np.float32([0.5, -0.25, 2.0]), np.float32([3.0, 2.0])
    rec = plane_receivers(jnp.asarray(c), jnp.asarray(size), (nx, nz), jnp.full((3,), 0.5, jnp.float32))
    p = np.asarray(rec.points)
    assert p.shape == (nx * nz, 3) and rec.grid_shape == (nz, nx)
    np.testing.assert_array_equal(np.asarray(rec.normals), np.tile(np.float32([0, 1, 0]), (nx * nz, 1)))
    np.testing.assert_array_equal(p[:, 1], np.full(nx * nz, c[1]))
    grid = p.reshape(nz, nx, 3)
    # rows run along z, columns along x: x varies within a row only, z across rows only
    np.testing.assert_allclose(grid[:, :, 0], np.broadcast_to(grid[0:1, :, 0], (nz, nx)))
    np.testing.assert_allclose(grid[:, :, 2], np.broadcast_to(grid[:, 0:1, 2], (nz, nx)))
    for n, axis, k in ((nx, 1, 0), (nz, 0, 1)):
        coords = np.take(grid[..., 2 * k], 0, axis=1 - axis)  # the varying coordinate along its axis
        if n == 1:
            np.testing.assert_allclose(coords, [c[2 * k]], atol=1e-6)
        else:
            np.testing.assert_allclose(np.diff(coords), size[k] / (n - 1), rtol=1e-5)
            np.testing.assert_allclose(
                [coords[0], coords[-1]], [c[2 * k] - size[k] / 2, c[2 * k] + size[k] / 2], atol=1e-6
            )
    # the mean of the grid is the centre
    np.testing.assert_allclose(p.mean(0), c, atol=1e-6)


def test_jvp_through_build_scene_receiver_and_light(x64):
    cfg = config_from_dict(base_dict(method={"dtype": "float64"}))

    def points_of(center, size):
        c = eqx.tree_at(lambda c: c.receiver.center, cfg, center)
        c = eqx.tree_at(lambda c: c.receiver.size, c, size)
        return build_scene(c).receivers.points

    c0, s0 = cfg.receiver.center, cfg.receiver.size
    dc = jnp.asarray([0.3, -0.2, 0.7])
    _, tan = jax.jvp(points_of, (c0, s0), (dc, jnp.zeros(2)))
    np.testing.assert_allclose(tan, np.broadcast_to(dc, tan.shape), rtol=1e-12)
    ds = jnp.asarray([1.0, 0.0])
    _, tan = jax.jvp(points_of, (c0, s0), (jnp.zeros(3), ds))
    offsets = np.linspace(-0.5, 0.5, 9)
    np.testing.assert_allclose(tan[:, 0], np.tile(offsets, 7), atol=1e-12)
    np.testing.assert_allclose(tan[:, 1:], 0.0, atol=0)

    def light_center(a):
        return build_scene(set_param(cfg, "light.0.center", a)).lights[0].center

    _, tan = jax.jvp(light_center, (cfg.light[0].center,), (jnp.asarray([0.0, 1.0, 0.0]),))
    np.testing.assert_array_equal(tan, [0.0, 1.0, 0.0])


@pytest.mark.filterwarnings("ignore::jshadow.geometry.MeshWarning")
def test_mesh_occluder_deform_jvp_matches_finite_differences(x64, tmp_assets):
    occ = {
        "type": "mesh",
        "shape": "egg",
        "subdivisions": 1,
        "center": [0.0, 1.1, 0.0],
        "radius": 0.8,
        "deform": {"type": "bend", "amount": [0.2, 0.6], "axis": "y", "toward": "x"},
    }
    cfg = config_from_dict(base_dict(occluder=[occ], method={"dtype": "float64"}))
    scene = build_scene(cfg)
    (m,) = scene.occluders
    assert isinstance(m, MeshOccluder) and m.deforms and m.name == "egg"
    r = np.linalg.norm(np.asarray(m.unit_vertices), axis=1)
    assert np.isclose(r.max(), 1.0)  # normalised to the unit bounding sphere

    def verts(a, t=0.5):
        c = eqx.tree_at(lambda c: c.occluder[0].deform.amount, cfg, a)
        return build_scene(c).occluders[0].vertices(t)

    a0, da = cfg.occluder[0].deform.amount, jnp.asarray([1.0, 0.5])
    _, tan = jax.jvp(verts, (a0,), (da,))
    h = 1e-6
    fd = (verts(a0 + h * da) - verts(a0 - h * da)) / (2 * h)
    np.testing.assert_allclose(tan, fd, atol=1e-7)
    assert np.abs(np.asarray(tan)).max() > 1e-2  # the amount really moves the vertices


@pytest.mark.filterwarnings("ignore::jshadow.geometry.MeshWarning")
def test_mesh_file_up_axis_and_placement(tmp_assets, x64):
    occ = {"type": "mesh", "file": "tet.obj", "center": [1.0, 2.0, 3.0], "radius": 0.5}
    ys = build_scene(
        config_from_dict(base_dict(occluder=[occ], method={"dtype": "float64"}), root=tmp_assets)
    )
    zs = build_scene(
        config_from_dict(
            base_dict(occluder=[dict(occ, up="z")], method={"dtype": "float64"}), root=tmp_assets
        )
    )
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 2.0]])
    for scene, w in ((ys, v), (zs, np.stack([v[:, 0], v[:, 2], -v[:, 1]], axis=1))):
        lo, hi = w.min(0), w.max(0)
        mid = (lo + hi) / 2
        rad = np.linalg.norm(w - mid, axis=1).max()
        expect = np.asarray([1.0, 2.0, 3.0]) + 0.5 * (w - mid) / rad
        np.testing.assert_allclose(scene.occluders[0].vertices(0.0), expect, atol=1e-12)
        assert scene.occluders[0].name == "tet"


def test_rotate_latlong_y_direction_and_interpolation():
    h, w = 4, 8
    img = np.zeros((h, w, 3), np.float32)
    img[:, 1] = 1.0  # a bright column around φ = 2π·1.5/8
    env0 = Environment(jnp.ones(3, jnp.float32), jnp.asarray(img), kind="hdr")
    alpha = 2 * np.pi * 2 / w  # two columns
    env1 = Environment(jnp.ones(3, jnp.float32), rotate_latlong_y(jnp.asarray(img), alpha), kind="hdr")
    phi = 2 * np.pi * 1.5 / w
    d = np.float32([np.cos(phi), 0.3, -np.sin(phi)])
    d /= np.linalg.norm(d)
    c, s = np.cos(alpha), np.sin(alpha)
    ry = np.float32([[c, 0, s], [0, 1, 0], [-s, 0, c]])  # right-handed rotation about +y
    np.testing.assert_allclose(env1.radiance_at(jnp.asarray(ry @ d)), env0.radiance_at(jnp.asarray(d)))
    np.testing.assert_allclose(env1.radiance_at(jnp.asarray(ry @ d)), [1.0, 1.0, 1.0])
    np.testing.assert_allclose(np.asarray(rotate_latlong_y(jnp.asarray(img), alpha)), np.roll(img, 2, axis=1))
    half = np.asarray(rotate_latlong_y(jnp.asarray(img), 2 * np.pi * 0.25 / w))
    np.testing.assert_allclose(half[0, :3, 0], [0.0, 0.75, 0.25], atol=1e-6)
    g = jax.grad(lambda a: rotate_latlong_y(jnp.asarray(img), a)[0, 2, 0])(jnp.float32(0.1))
    np.testing.assert_allclose(g, w / (2 * np.pi), rtol=1e-5)  # column 2 brightens as column 1 moves in


# --- shipped configs -------------------------------------------------------------------------------
EXPECTED = {
    "sphere.toml": (SphereOccluder, (160, 160), 1, False, "constant"),
    "bunny_studio.toml": (MeshOccluder, None, 1, True, "hdr"),
    "spot_sunset.toml": (MeshOccluder, None, 1, False, "hdr"),
    "airplane_bend.toml": (MeshOccluder, None, 24, False, None),
    "egg_breathing.toml": (MeshOccluder, None, 24, False, None),
    "fit_bend.toml": (MeshOccluder, None, 1, False, None),
}


def test_every_expected_config_is_shipped():
    assert set(EXPECTED) <= {p.name for p in CONFIGS}


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_shipped_configs_load_and_build(path):
    cfg = load_config(path)
    scene = build_scene(cfg)
    nx, nz = cfg.receiver.resolution
    assert scene.receivers.points.shape == (nx * nz, 3) and scene.receivers.grid_shape == (nz, nx)
    assert np.all(np.isfinite(np.asarray(scene.receivers.points)))
    occ_type, res, frames, self_shadow, env = EXPECTED.get(path.name, (None, None, None, None, None))
    if occ_type is None:
        return
    assert isinstance(scene.occluders[0], occ_type)
    assert scene.n_frames == frames and scene.self_shadow is self_shadow
    if res is not None:
        assert cfg.receiver.resolution == res
    if env is not None:
        assert scene.environment.kind == env
    if env == "hdr":
        assert scene.environment.image.shape == (256, 512, 3)
    for occ in scene.occluders:  # shadows fall on the plane: the occluder hovers above it, inside it
        y0 = float(scene.receivers.points[0, 1])
        assert float(occ.center[1]) - float(occ.radius) > y0
        assert np.all(np.abs(np.asarray(occ.center)[[0, 2]]) < 1.0)
    if cfg.fit is not None:
        for p in cfg.fit.params:
            assert get_param(cfg, p).shape == cfg.fit.target_values[0].shape


def test_build_scene_under_jit_reads_files_once_and_caches_no_tracers():
    from jshadow.config import clear_file_cache

    occ = {"type": "mesh", "shape": "icosphere", "subdivisions": 0, "center": [0.0, 1.0, 0.0], "radius": 0.5}
    cfg = config_from_dict(base_dict(occluder=[occ]))
    clear_file_cache()  # the mesh is first built inside the trace below
    verts = eqx.filter_jit(lambda c: build_scene(c).occluders[0].vertices(0.0))(cfg)
    eager = build_scene(cfg).occluders[0]  # from the cache filled during tracing: concrete arrays
    assert not isinstance(eager.unit_vertices, jax.core.Tracer)
    np.testing.assert_allclose(verts, eager.vertices(0.0), rtol=1e-6)
    assert verts.shape == (12, 3)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(verts) - [0.0, 1.0, 0.0], axis=1), 0.5, rtol=1e-6)
