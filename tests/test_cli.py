"""The command-line contract (DESIGN.md §4): output files and arrays, clean errors on bad input."""

import json
import subprocess
import sys

import numpy as np
import pytest
from conftest import subprocess_env

from jshadow.cli import main

SCENE = """
[method]
directions = [8, 8]

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
"""


@pytest.fixture
def scene_file(tmp_path):
    p = tmp_path / "scene.toml"
    p.write_text(SCENE)
    return p


def test_render_and_reference_write_the_contract_files(tmp_path, scene_file):
    assert main(["render", str(scene_file), "--out", str(tmp_path / "r")]) == 0
    with np.load(tmp_path / "r" / "frame_0000.npz") as d:
        for k in ("points", "normals", "irradiance", "radiance"):
            assert d[k].shape == (63, 3) and np.all(np.isfinite(d[k]))
        pts = d["points"]
    assert (tmp_path / "r" / "frame_0000.png").stat().st_size > 1000
    t = json.loads((tmp_path / "r" / "timings.json").read_text())
    assert t["frames"] == 1 and t["median_ms"]["total_ms"] > 0

    assert (
        main(["reference", str(scene_file), "--spp", "16", "--out", str(tmp_path / "q"), "--seed", "1"]) == 0
    )
    with np.load(tmp_path / "q" / "frame_0000.npz") as d:
        assert d["irradiance_stderr"].shape == (63, 3)
        np.testing.assert_array_equal(d["points"], pts)

    assert main(["compare", str(tmp_path / "r"), str(tmp_path / "q"), "--out", str(tmp_path / "d.png")]) == 0


def test_one_frame_render_times_a_frame_not_the_readout_preparation(tmp_path, scene_file):
    # the sphere through the BSV path could be read out of the field's table from the second call
    # on; the warm re-run of a one-frame render would then time the readout's preparation (1.6 s
    # for the studio bunny, against a 1.1 ms frame), so a one-frame render does not prepare it.
    # An animation of the same static scene prepares it at its first frame and reads out every frame.
    assert main(["render", str(scene_file), "--out", str(tmp_path / "one"), "--sphere-path", "bsv"]) == 0
    t = json.loads((tmp_path / "one" / "timings.json").read_text())
    assert t["readout_frames"] == 0 and "first_call" in t["per_frame"][0]
    anim = tmp_path / "anim.toml"
    anim.write_text(scene_file.read_text() + "\n[animation]\nframes = 3\n")
    assert main(["render", str(anim), "--out", str(tmp_path / "anim"), "--sphere-path", "bsv"]) == 0
    t = json.loads((tmp_path / "anim" / "timings.json").read_text())
    assert t["frames"] == 3 and t["readout_frames"] == 3


def test_misspelt_key_exits_2_with_one_line_and_no_output(tmp_path, scene_file):
    bad = tmp_path / "bad.toml"
    bad.write_text(SCENE.replace("resolution = [9, 7]", "resolution = [9, 7]\nresolutoin = [1, 1]"))
    p = subprocess.run(
        [sys.executable, "-m", "jshadow.cli", "render", str(bad), "--out", str(tmp_path / "bad")],
        capture_output=True,
        text=True,
        timeout=300,
        env=subprocess_env(),
    )
    lines = [line for line in p.stderr.splitlines() if line.strip()]
    assert p.returncode == 2, p.stderr
    assert len(lines) == 1 and "resolutoin" in lines[0] and "Traceback" not in p.stderr
    assert not (tmp_path / "bad").exists()


@pytest.mark.parametrize(
    "args, needle",
    [
        (["render", "no/such/file.toml", "--out", "{tmp}/o"], "file.toml"),
        (["reference", "{scene}", "--spp", "0", "--out", "{tmp}/o"], "--spp"),
        (["compare", "{tmp}/nothere", "{tmp}/nothere2"], "nothere"),
    ],
)
def test_bad_invocations_exit_2(tmp_path, scene_file, capsys, args, needle):
    args = [a.format(tmp=tmp_path, scene=scene_file) for a in args]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0]


def test_fit_writes_its_outputs_and_reduces_the_loss(tmp_path):
    cfg = tmp_path / "fit.toml"
    cfg.write_text(
        SCENE.replace("resolution = [9, 7]", "resolution = [8, 8]")
        + '\n[fit]\nparams = ["light.0.center"]\ntarget_values = [[0.6, 3.0, 0.5]]\n'
        + "steps = 8\nlearning_rate = 0.05\n"
    )
    assert main(["fit", str(cfg), "--out", str(tmp_path / "f")]) == 0
    rep = json.loads((tmp_path / "f" / "fit.json").read_text())
    assert set(rep["params"]) == {"light.0.center"} and len(rep["loss"]) == 8
    assert rep["loss"][-1] < rep["loss"][0]
    assert rep["bsv_images"] == "samples" and rep["retraced"] == []  # a light: no mesh shape fitted
    for name in ("loss.png", "before.png", "after.png", "target.png"):
        assert (tmp_path / "f" / name).stat().st_size > 1000


def test_fit_of_a_mesh_deformation_takes_the_coverage_bsv_and_says_so(tmp_path, capsys):
    cfg = tmp_path / "bend.toml"
    cfg.write_text(
        "[method]\nsh_bands = 3\nbsv_grid = [4, 6]\ndirections = [8, 8]\n"
        '[environment]\ntype = "constant"\nradiance = [0.3, 0.3, 0.3]\n'
        '[[occluder]]\ntype = "mesh"\nshape = "egg"\nsubdivisions = 1\ncenter = [0.0, 1.1, 0.0]\n'
        'radius = 0.8\ndeform = { type = "bend", amount = 0.4, axis = "y", toward = "x" }\n'
        '[[light]]\ntype = "sphere"\ncenter = [0.5, 3.0, 0.3]\nradius = 0.3\nradiance = [20.0, 20.0, 20.0]\n'
        '[receiver]\ntype = "plane"\ncenter = [0.0, 0.0, 0.0]\nsize = [4.0, 4.0]\nresolution = [8, 8]\n'
        '[fit]\nparams = ["occluder.0.deform.amount"]\ntarget_values = [0.8]\nsteps = 4\n'
    )
    assert main(["fit", str(cfg), "--out", str(tmp_path / "f")]) == 0
    assert "bsv_images = 'auto' is 'coverage'" in capsys.readouterr().err
    rep = json.loads((tmp_path / "f" / "fit.json").read_text())
    assert rep["bsv_images"] == "coverage" and len(rep["loss"]) == 4
    assert rep["loss"][-1] < rep["loss"][0]


def test_bench_prints_stages_and_error_and_writes_json(tmp_path, scene_file, capsys):
    out = tmp_path / "b" / "bench.json"
    assert main(["bench", str(scene_file), "--frames", "2", "--spp", "64", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "field_ms" in text and "relative RMSE" in text
    rep = json.loads(out.read_text())
    assert rep["median_ms"]["total_ms"] > 0 and 0 < rep["reference"]["rel_rmse"] < 1
