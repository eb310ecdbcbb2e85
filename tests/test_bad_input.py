"""Bad input end to end through the command line (DESIGN.md §4, issue 8).

Every case must give exit status 2, exactly one line on stderr naming the key or file, no
traceback, and no output files. Open meshes warn (one line) and still render.
"""

import subprocess
import sys

import numpy as np
import pytest
from conftest import subprocess_env

from jshadow.cli import _atomic_write, main

SCENE = """
[method]
bsv_grid = [4, 6]
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
resolution = [5, 4]
albedo = [0.5, 0.5, 0.5]
"""

SPHERE = 'type = "sphere"\ncenter = [0.2, 1.0, 0.0]\nradius = 0.4'

FILES = {
    "tri.obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    "nan.obj": "v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n",
    "inf.obj": "v 0 0 0\nv 1 inf 0\nv 0 1 0\nf 1 2 3\n",
    "range.obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n",
    "nofaces.obj": "v 0 0 0\nv 1 0 0\nv 0 1 0\n",
    "flat.obj": "v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n",
    "binary.obj": bytes([0xFF, 0xFE, 0x00, 0x81]) * 40,
    "junk.hdr": b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 4 +X 8\n" + bytes(range(20)),
    "empty.hdr": b"",
    "a_file": "not a folder",
}


def _sub(old, new, text=SCENE):
    assert old in text
    return text.replace(old, new)


def _mesh(file):
    return _sub(SPHERE, f'type = "mesh"\nfile = "{file}"\ncenter = [0.2, 1.0, 0.0]\nradius = 0.4')


def _hdr(file):
    return _sub('type = "constant"', f'type = "hdr"\nfile = "{file}"')


# (id, config text, substrings of the one stderr line)
CASES = [
    ("toml-syntax", _sub("radius = 0.4", "radius = = 0.4"), ["TOML syntax error", "line 13"]),
    ("toml-unclosed", _sub("[receiver]", "[receiver"), ["TOML syntax error", "line 21"]),
    ("unknown-key", _sub("[receiver]", "[receiver]\nsizes = [1, 1]"), ["'sizes'", "did you mean 'size'"]),
    ("unknown-table", _sub("[receiver]", "[reciever]"), ["'reciever'", "did you mean 'receiver'"]),
    ("wrong-type", _sub("radius = 0.4", 'radius = "0.4"'), ["occluder[0].radius", "expected a number"]),
    ("wrong-length", _sub("size = [3.0, 3.0]", "size = [3.0]"), ["receiver.size", "2 numbers"]),
    ("negative-radius", _sub("radius = 0.4", "radius = -0.4"), ["occluder[0].radius", "positive"]),
    ("zero-light-radius", _sub("radius = 0.3", "radius = 0.0"), ["light[0].radius", "positive"]),
    ("zero-size", _sub("size = [3.0, 3.0]", "size = [0.0, 3.0]"), ["receiver.size", "positive"]),
    ("negative-size", _sub("size = [3.0, 3.0]", "size = [3.0, -1.0]"), ["receiver.size", "positive"]),
    ("zero-resolution", _sub("resolution = [5, 4]", "resolution = [0, 4]"), ["receiver.resolution", ">= 1"]),
    (
        "huge-resolution",
        _sub("resolution = [5, 4]", "resolution = [100000000, 100000000]"),
        ["receiver.resolution", "at most"],
    ),
    ("zero-frames", SCENE + "\n[animation]\nframes = 0\n", ["animation.frames", ">= 1"]),
    ("nan-radius", _sub("radius = 0.4", "radius = nan"), ["occluder[0].radius", "finite"]),
    (
        "inf-center",
        _sub("center = [1.0, 3.0, 0.5]", "center = [inf, 3.0, 0.5]"),
        ["light[0].center", "finite"],
    ),
    (
        "nan-radiance",
        _sub("radiance = [1.0, 0.8, 0.6]", "radiance = [1.0, -nan, 0.6]"),
        ["environment", "finite"],
    ),
    ("negative-albedo", _sub("albedo = [0.5, 0.5, 0.5]", "albedo = [0.5, -0.5, 0.5]"), ["receiver.albedo"]),
    ("missing-mesh", _mesh("nope.obj"), ["occluder[0].file", "not found", "nope.obj"]),
    ("mesh-is-folder", _mesh("."), ["occluder[0].file", "not found"]),
    ("binary-mesh", _mesh("binary.obj"), ["occluder[0].file", "binary.obj", "UTF-8"]),
    ("nan-mesh", _mesh("nan.obj"), ["occluder[0].file", "nan.obj", "non-finite"]),
    ("inf-mesh", _mesh("inf.obj"), ["occluder[0].file", "inf.obj", "non-finite"]),
    ("face-index-out-of-range", _mesh("range.obj"), ["occluder[0].file", "range.obj", "out of range"]),
    ("no-faces", _mesh("nofaces.obj"), ["occluder[0].file", "nofaces.obj", "no faces"]),
    ("all-faces-degenerate", _mesh("flat.obj"), ["occluder[0].file", "flat.obj", "degenerate"]),
    ("missing-hdr", _hdr("nope.hdr"), ["environment.file", "not found", "nope.hdr"]),
    ("junk-hdr", _hdr("junk.hdr"), ["environment.file", "junk.hdr"]),
    ("empty-hdr", _hdr("empty.hdr"), ["environment.file", "empty.hdr"]),
]


@pytest.fixture
def folder(tmp_path):
    for name, content in FILES.items():
        p = tmp_path / name
        if isinstance(content, bytes):
            p.write_bytes(content)
        else:
            p.write_text(content)
    return tmp_path


def _one_line(capsys) -> str:
    cap = capsys.readouterr()
    lines = [line for line in cap.err.splitlines() if line.strip()]
    assert "Traceback" not in cap.err, cap.err
    assert len(lines) == 1, cap.err
    return lines[0]


def _no_frames(out) -> None:
    assert not out.exists() or not any(p.name.startswith("frame_") for p in out.iterdir())


@pytest.mark.parametrize("text, expected", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_config_exits_2_with_one_line_and_writes_nothing(folder, capsys, text, expected):
    cfg = folder / "scene.toml"
    cfg.write_text(text)
    out = folder / "out"
    assert main(["render", str(cfg), "--out", str(out)]) == 2
    line = _one_line(capsys)
    assert line.startswith("jshadow render: error: ") and str(cfg) in line
    for s in expected:
        assert s in line, line
    assert not out.exists()


@pytest.mark.parametrize("command", ["reference", "bench", "fit"])
def test_every_command_reports_bad_config_the_same_way(folder, capsys, command):
    cfg = folder / "scene.toml"
    cfg.write_text(_mesh("nan.obj"))
    args = {
        "reference": ["--spp", "4", "--out", str(folder / "out")],
        "bench": [],
        "fit": ["--out", str(folder / "out")],
    }
    assert main([command, str(cfg), *args[command]]) == 2
    line = _one_line(capsys)
    assert line.startswith(f"jshadow {command}: error: ") and "nan.obj" in line and "non-finite" in line
    assert line.count("nan.obj") == 1, line  # the file is named once, not by every layer
    assert not (folder / "out").exists()


@pytest.mark.parametrize(
    "config, needle",
    [
        ("missing.toml", "config file not found"),
        (".", "got a directory"),
        ("binary.obj", "not a UTF-8 text file"),
    ],
)
def test_unreadable_config_files(folder, capsys, config, needle):
    assert main(["render", str(folder / config), "--out", str(folder / "out")]) == 2
    assert needle in _one_line(capsys)
    assert not (folder / "out").exists()


@pytest.mark.parametrize("out", ["a_file/sub", "a_file"])
def test_output_folder_that_cannot_be_created(folder, capsys, out):
    cfg = folder / "scene.toml"
    cfg.write_text(SCENE)
    assert main(["render", str(cfg), "--out", str(folder / out)]) == 2
    line = _one_line(capsys)
    assert "cannot create output folder" in line and "a_file" in line
    assert (folder / "a_file").read_text() == "not a folder"


@pytest.mark.parametrize(
    "args, needle",
    [
        (["render", "{cfg}"], "--out"),
        (["render", "{cfg}", "--out", "{tmp}/o", "--bogus"], "--bogus"),
        (["reference", "{cfg}", "--spp", "many", "--out", "{tmp}/o"], "--spp"),
        (["reference", "{cfg}", "--spp", "-3", "--out", "{tmp}/o"], "--spp"),
        (["bench", "{cfg}", "--frames", "0"], "--frames"),
        (["fit", "{cfg}", "--out", "{tmp}/o"], "no [fit] table"),
        (["reference", "{cfg}", "--spp", "4", "--frame", "1", "--out", "{tmp}/o"], "--frame must be in 0..0"),
        (["render", "{cfg}", "--out", "{tmp}/o", "--exposure", "nan"], "--exposure"),
        (["render", "{cfg}", "--out", "{tmp}/o", "--chunk", "0"], "--chunk"),
        (["render", "{cfg}", "--out", "{tmp}/o", "--devices", "64"], "--devices must be in 1.."),
        (["bench", "{cfg}", "--json", "{tmp}/a_file/b.json"], "a_file"),
        (["paint", "{cfg}"], "paint"),
    ],
)
def test_bad_arguments_exit_2_with_one_line(folder, capsys, args, needle):
    cfg = folder / "scene.toml"
    cfg.write_text(SCENE)
    args = [a.format(cfg=cfg, tmp=folder) for a in args]
    try:
        rc = main(args)
    except SystemExit as stop:  # argparse ends the process itself
        rc = stop.code
    assert rc == 2
    assert needle in _one_line(capsys)
    assert not (folder / "o").exists()


@pytest.mark.filterwarnings("default::jshadow.geometry.MeshWarning")
def test_open_mesh_warns_in_one_line_and_still_renders(folder, capsys):
    cfg = folder / "scene.toml"
    cfg.write_text(_mesh("tri.obj"))
    out = folder / "out"
    assert main(["render", str(cfg), "--out", str(out), "--no-warm"]) == 0
    err = capsys.readouterr().err
    warn = [line for line in err.splitlines() if "tri.obj" in line]
    assert len(warn) == 1 and "open or non-manifold" in warn[0] and warn[0].startswith("jshadow: warning:")
    with np.load(out / "frame_0000.npz") as d:
        assert d["irradiance"].shape == (20, 3) and np.all(np.isfinite(d["irradiance"]))


def test_bad_mesh_in_a_fresh_process_has_no_traceback(folder):
    cfg = folder / "scene.toml"
    cfg.write_text(_mesh("range.obj"))
    p = subprocess.run(
        [sys.executable, "-m", "jshadow.cli", "render", str(cfg), "--out", str(folder / "out")],
        capture_output=True,
        text=True,
        timeout=300,
        env=subprocess_env(),
    )
    lines = [line for line in p.stderr.splitlines() if line.strip()]
    assert p.returncode == 2 and len(lines) == 1 and "range.obj" in lines[0], p.stderr
    assert "Traceback" not in p.stderr and p.stdout == ""
    _no_frames(folder / "out")


def test_interrupted_write_leaves_no_file(tmp_path):
    def write_half(fh):
        fh.write(b"partial")
        raise KeyboardInterrupt

    target = tmp_path / "frame_0000.npz"
    with pytest.raises(KeyboardInterrupt):
        _atomic_write(target, write_half)
    assert list(tmp_path.iterdir()) == []
    _atomic_write(target, lambda fh: fh.write(b"whole"))
    assert target.read_bytes() == b"whole" and [p.name for p in tmp_path.iterdir()] == ["frame_0000.npz"]
