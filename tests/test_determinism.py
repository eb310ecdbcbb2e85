"""Determinism: the same config and seed give bitwise-identical outputs on the same machine,
within one process and across processes (render and Monte Carlo reference)."""

import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import subprocess_env

import jshadow
from jshadow import runner
from jshadow.cli import main
from jshadow.entities import frame_time
from jshadow.runner import Renderer

SCENE = """
[method]
bsv_grid = [4, 6]
directions = [8, 8]
shell = 1.5

[environment]
type = "sky"
radiance = [1.0, 0.9, 0.8]

[[occluder]]
type = "mesh"
shape = "egg"
subdivisions = 1
center = [0.0, 0.8, 0.0]
radius = 0.5
deform = { type = "bend", amount = [0.0, 0.6] }

[[occluder]]
type = "sphere"
center = [0.9, 0.6, 0.3]
radius = 0.3

[[light]]
type = "sphere"
center = [1.0, 3.0, 0.5]
radius = 0.3
radiance = [9.0, 9.0, 9.0]

[receiver]
type = "plane"
center = [0.0, 0.0, 0.0]
size = [3.0, 3.0]
resolution = [6, 5]
self_shadow = true

[animation]
frames = 2
"""

KEYS = ("points", "normals", "irradiance", "radiance")


@pytest.fixture(scope="module")
def config_file(tmp_path_factory):
    p = tmp_path_factory.mktemp("det") / "scene.toml"
    p.write_text(SCENE)
    return p


def _assert_identical(a, b, keys):
    for k in keys:
        x, y = np.asarray(a[k]), np.asarray(b[k])
        assert x.dtype == y.dtype and x.shape == y.shape, k
        assert np.array_equal(x, y), f"{k}: largest difference {np.abs(x - y).max()}"


def _arrays(res, keys):
    return {k: np.asarray(getattr(res, k)) for k in keys}


def test_render_twice_in_one_process_is_bitwise_identical(config_file):
    outs = []
    for _ in range(2):  # fresh config, scene and renderer each time
        scene = jshadow.build_scene(jshadow.load_config(config_file))
        rend = Renderer(scene)
        outs.append([_arrays(rend.frame(f)[0], KEYS) for f in range(2)])
    for f in range(2):
        _assert_identical(outs[0][f], outs[1][f], KEYS)
    assert not np.array_equal(outs[0][0]["irradiance"], outs[0][1]["irradiance"])  # the bend moves


def test_chunked_render_is_deterministic_and_agrees_with_one_piece(config_file):
    scene = jshadow.build_scene(jshadow.load_config(config_file))
    whole = _arrays(Renderer(scene).frame(1)[0], KEYS)
    a = _arrays(Renderer(scene, chunk=7).frame(1)[0], KEYS)
    b = _arrays(Renderer(scene, chunk=7).frame(1)[0], KEYS)
    _assert_identical(a, b, KEYS)
    _assert_identical(a, whole, ("points", "normals"))
    tol = 8 * float(np.finfo(np.float32).eps)  # pieces of another shape may round differently
    for k in ("irradiance", "radiance"):
        np.testing.assert_allclose(a[k], whole[k], rtol=0, atol=tol * np.abs(whole[k]).max())


def _check_flat_call(rend, config_file, res):
    """The renderer's one call (the scene's arrays flattened once, plain ``jax.jit``) computes
    exactly what ``_place_and_shade`` (``eqx.filter_jit`` of the scene) does; a second renderer of an
    equal scene reuses the compiled function; an unhashable static leaf falls back to the latter."""
    scene = rend.scene
    t = jnp.asarray(frame_time(1, scene.n_frames), scene.receivers.points.dtype)
    bsvs = rend._bsvs(t)
    own = rend._own(t)  # the bending egg's own vertices: "rays" every frame (self_visibility "auto")
    images = rend._images(t)  # the sphere light is shadowed through the images (light_visibility "auto")
    assert images is not None and own is not None
    ref = runner._with_receivers(
        scene,
        runner._place_and_shade(scene, bsvs, t, rend._lighting, True, rend._shared_normal, own, images),
    )
    _assert_identical(_arrays(res, KEYS), dict(zip(KEYS, (np.asarray(x) for x in ref), strict=True)), KEYS)
    again = Renderer(jshadow.build_scene(jshadow.load_config(config_file)))
    again.frame(0)
    assert again._flat[False][0] is rend._flat[False][0]  # the general (not read-out) call
    assert runner._flat_shader((bytearray(b"x"),), None, True, 0) is None


def test_one_call_shading_equals_the_split_stages(config_file):
    """The default renderer shades a frame in one call (receivers, field, combination); with
    ``split_stages`` the same arithmetic runs as three calls: the same numbers (XLA may fuse the two
    differently, so up to rounding), in one piece and in pieces, and the timings say which ran;
    the one call computes exactly what the ``eqx.filter_jit`` call does (:func:`_check_flat_call`)."""
    scene = jshadow.build_scene(jshadow.load_config(config_file))
    tol = 8 * float(np.finfo(np.float32).eps)
    for chunk in (None, 7):
        rend = Renderer(scene, chunk=chunk)
        one, t_one = rend.frame(1)
        if chunk is None:
            _check_flat_call(rend, config_file, one)
        split, t_split = Renderer(scene, chunk=chunk, split_stages=True).frame(1)
        a, b = _arrays(one, KEYS), _arrays(split, KEYS)
        _assert_identical(a, b, ("points", "normals"))
        for k in ("irradiance", "radiance"):
            np.testing.assert_allclose(a[k], b[k], rtol=0, atol=tol * np.abs(b[k]).max())
        # the own vertices' maps made for the frame ("self_visibility_ms"), the images, the shading
        # (and the receivers next to the mesh, where contact_visibility casts them)
        stages = {"bsv_ms", "self_visibility_ms", "light_images_ms", "shading_ms", "total_ms"}
        if scene.method.contact_visibility == "rays":
            stages |= {"contact_ms"}
        assert set(t_one) == stages
        assert set(t_split) == stages | {"field_ms", "combine_ms"}
        assert t_split["shading_ms"] == pytest.approx(t_split["field_ms"] + t_split["combine_ms"])
        for t in (t_one, t_split):
            parts = ("bsv_ms", "self_visibility_ms", "light_images_ms", "contact_ms", "shading_ms")
            assert t["total_ms"] == pytest.approx(sum(t.get(k, 0.0) for k in parts)) and t["shading_ms"] > 0
    with pytest.raises(TypeError, match="split_stages"):
        Renderer(scene, split_stages="yes")


def test_render_frames_on_two_host_threads_equals_one_renderer(config_file):
    scene = jshadow.build_scene(jshadow.load_config(config_file))
    rend = Renderer(scene)
    seq = [_arrays(rend.frame(f)[0], KEYS) for f in range(2)]
    par = jshadow.render_frames(scene, threads=2)
    for f in range(2):
        _assert_identical(seq[f], _arrays(par[f], KEYS), KEYS)
    with pytest.raises(ValueError, match="threads"):
        jshadow.render_frames(scene, threads=0)


def test_reference_same_seed_identical_other_seed_different(config_file):
    scene = jshadow.build_scene(jshadow.load_config(config_file))
    keys = (*KEYS, "irradiance_stderr")
    a = _arrays(jshadow.reference(scene, 8, jax.random.PRNGKey(3), frame=1), keys)
    b = _arrays(jshadow.reference(scene, 8, jax.random.PRNGKey(3), frame=1), keys)
    c = _arrays(jshadow.reference(scene, 8, jax.random.PRNGKey(4), frame=1), keys)
    _assert_identical(a, b, keys)
    assert not np.array_equal(a["irradiance"], c["irradiance"])


def test_cli_outputs_identical_across_processes(config_file, tmp_path):
    code = (
        "import sys; from jshadow.cli import main; d, cfg = sys.argv[1], sys.argv[2]; "
        "assert main(['render', cfg, '--out', d + '/render', '--no-warm']) == 0; "
        "assert main(['reference', cfg, '--spp', '8', '--seed', '5', '--out', d + '/reference']) == 0"
    )
    runs = [tmp_path / "run0", tmp_path / "run1"]
    # One after the other, sharing this run's compilation cache: the second process loads what the
    # first compiled and the cache holds (a hit is keyed by the program, so a program that differed
    # between the processes would still be compiled anew, and its outputs compared below; programs
    # with a host callback, as every equinox runtime check is, are not cached and compiled by both).
    for d in runs:
        p = subprocess.run(
            [sys.executable, "-c", code, str(d), str(config_file)],
            capture_output=True,
            text=True,
            timeout=600,
            env=subprocess_env(),
        )
        assert p.returncode == 0, p.stderr[-3000:]
    for sub, keys in (("render", KEYS), ("reference", (*KEYS, "irradiance_stderr"))):
        for f in range(2):
            with (
                np.load(runs[0] / sub / f"frame_{f:04d}.npz") as a,
                np.load(runs[1] / sub / f"frame_{f:04d}.npz") as b,
            ):
                assert sorted(a.files) == sorted(b.files)
                _assert_identical(a, b, a.files)
                assert set(keys) <= set(a.files)
    # and this process computes the same render as the two others
    assert main(["render", str(config_file), "--out", str(tmp_path / "here"), "--no-warm"]) == 0
    for f in range(2):
        with (
            np.load(runs[0] / "render" / f"frame_{f:04d}.npz") as a,
            np.load(tmp_path / "here" / f"frame_{f:04d}.npz") as b,
        ):
            _assert_identical(a, b, KEYS)
