"""Receivers and frames over several JAX devices (jshadow._parallel, Renderer(devices=...),
render_frames, ``jshadow render --devices``).

Two CPU devices need ``XLA_FLAGS=--xla_force_host_platform_device_count=2`` before JAX is imported,
so the multi-device comparison runs in a subprocess. Claims tested: frames rendered on another
device are bitwise identical to one device; receivers sharded over two devices agree with one device
to 8 float32 ulp of the frame's largest value (the pieces have other shapes, and XLA may round the
small matrix products differently for another shape; measured: at most 4 ulp).
"""

import json
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import subprocess_env

from jshadow import _parallel

SCRIPT = textwrap.dedent(
    """
    import json, os, sys
    import jax, numpy as np
    import jshadow
    from jshadow import _parallel
    from jshadow.cli import main
    from jshadow.config import config_from_dict
    from jshadow.runner import Renderer, _fields, render_frames

    cfg = {  # brute-force BSV: sharding does not depend on the sampler, and it compiles fastest; the
             # egg's own-vertex visibility by rays, so that its rows are sharded with the receivers
        "method": {"bsv_grid": [4, 6], "directions": [8, 8], "bsv_method": "brute",
                   "self_visibility": "rays", "self_visibility_grid": [4, 8]},
        "environment": {"type": "sky", "radiance": [1.0, 0.9, 0.8]},
        "occluder": [
            {"type": "mesh", "shape": "egg", "subdivisions": 1, "center": [0.0, 0.8, 0.0], "radius": 0.5,
             "deform": {"type": "twist", "amount": [0.0, 0.8], "axis": "y"}},
            {"type": "sphere", "center": [0.9, 0.6, 0.3], "radius": 0.3},
        ],
        "light": [{"type": "sphere", "center": [1.0, 3.0, 0.5], "radius": 0.3, "radiance": [9.0, 9.0, 9.0]}],
        "receiver": {"type": "plane", "center": [0.0, 0.0, 0.0], "size": [3.0, 3.0], "resolution": [7, 5],
                     "self_shadow": True},
        "animation": {"frames": 3},
    }
    scene = jshadow.build_scene(config_from_dict(cfg))
    out = {"devices": len(jax.devices())}
    one = Renderer(scene)
    ref = [one.frame(f)[0] for f in range(3)]
    n = int(ref[0].irradiance.shape[0])
    out["receivers"] = n
    diffs = {}
    def compare(a, b):
        a, b = np.asarray(a), np.asarray(b)
        same = bool(a.shape == b.shape and np.array_equal(a, b))
        return [same, float(np.abs(a - b).max() / max(np.abs(a).max(), 1e-30)) if a.shape == b.shape else 1.0]

    # (chunked pieces over two devices: the CLI run below, --devices 2 --chunk 20)
    for name, rend, fs in [("sharded", Renderer(scene, devices=2), (0, 2))]:
        for f in fs:
            res = rend.frame(f)[0]
            for k in ("irradiance", "radiance", "points", "normals"):
                diffs[f"{name}/{f}/{k}"] = compare(getattr(ref[f], k), getattr(res, k))
    frames = render_frames(scene, devices=2)
    for f in range(3):
        diffs[f"frames/{f}/irradiance"] = compare(ref[f].irradiance, frames[f].irradiance)
    out["diffs"] = diffs
    rend = Renderer(scene, devices=2, chunk=16)
    size = rend.piece_size(n)
    p = _parallel.shard_rows(_parallel.pad_rows(ref[0].points[:size], size), rend.mesh)
    vis, _ = _fields(rend._light, rend._bsvs(0.0), p)
    out["piece_size"] = size
    out["piece_devices"] = len(p.sharding.device_set)
    out["vis_devices"] = len(vis[0].sharding.device_set)
    out["frame_devices"] = [str(d) for d in _parallel.frame_devices(3, 2)]
    d = sys.argv[1]
    with open(os.path.join(d, "scene.toml"), "w") as fh:
        fh.write(\"\"\"
    [method]
    directions = [8, 8]
    [environment]
    type = "constant"
    [[occluder]]
    type = "sphere"
    center = [0.0, 1.0, 0.0]
    radius = 0.5
    [receiver]
    type = "plane"
    center = [0.0, 0.0, 0.0]
    size = [3.0, 3.0]
    resolution = [9, 7]
    \"\"\")
    rc1 = main(["render", os.path.join(d, "scene.toml"), "--out", os.path.join(d, "one"), "--no-warm"])
    rc2 = main(["render", os.path.join(d, "scene.toml"), "--out", os.path.join(d, "two"), "--no-warm",
                "--devices", "2", "--chunk", "20"])
    a = np.load(os.path.join(d, "one", "frame_0000.npz"))["irradiance"]
    b = np.load(os.path.join(d, "two", "frame_0000.npz"))["irradiance"]
    out["cli"] = [rc1, rc2, float(np.abs(a - b).max() / np.abs(a).max())]
    with open(os.path.join(d, "two", "timings.json")) as fh:
        t = json.load(fh)
    out["cli_timings"] = [t["devices"], t["receivers_per_piece"]]
    print("RESULT " + json.dumps(out))
    """
)


def _two_devices(tmp_path):
    script = tmp_path / "run.py"
    script.write_text(SCRIPT)
    env = subprocess_env(xla_flags="--xla_force_host_platform_device_count=2")
    p = subprocess.run(
        [sys.executable, str(script), str(tmp_path)], capture_output=True, text=True, timeout=600, env=env
    )
    assert p.returncode == 0, p.stderr[-3000:]
    line = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
    assert line, p.stdout[-2000:] + p.stderr[-2000:]
    return json.loads(line[0][len("RESULT ") :])


def test_two_host_devices_sharded_receivers_frames_and_cli(tmp_path):
    # One subprocess with two CPU devices (about 70 s in the suite, mostly compilation) checks all of the
    # module docstring's multi-device claims; as separate tests sharing a module fixture, each
    # pytest-xdist worker that picked one of them up ran the subprocess again.
    r = _two_devices(tmp_path)

    # the devices are used: pieces and visibilities sharded over both, frames round-robin
    assert r["devices"] == 2
    assert r["piece_size"] == 16 and r["piece_devices"] == 2 and r["vis_devices"] == 2
    f0, f1, f2 = r["frame_devices"]
    assert f0 == f2 != f1

    diffs = r["diffs"]
    assert len(diffs) == 2 * 4 + 3
    # receiver positions and normals are computed once per frame, before sharding: identical
    assert all(v[0] for k, v in diffs.items() if k.endswith(("points", "normals"))), diffs
    # whole frames on another device run the same compiled program: identical
    assert all(v[0] for k, v in diffs.items() if k.startswith("frames/")), diffs
    # sharded pieces have other shapes, so XLA may round the small matrix products differently:
    # at most 8 float32 ulp of the frame's largest value
    tol = 8 * float(np.finfo(np.float32).eps)
    worst = max(v[1] for v in diffs.values())
    print(f"largest relative difference: {worst:.3g} ({worst / (tol / 8):.1f} ulp)")
    assert worst <= tol, diffs

    # `jshadow render --devices 2 --chunk 20` agrees with one device and reports its layout
    rc1, rc2, rel = r["cli"]
    assert rc1 == 0 and rc2 == 0 and rel <= tol
    assert r["cli_timings"] == [2, 20]


def test_device_selection_and_padding_on_one_device():
    n = len(jax.devices())
    assert _parallel.select_devices(None) == list(jax.devices())
    assert _parallel.select_devices(1) == [jax.devices()[0]]
    with pytest.raises(ValueError, match=rf"devices must be in 1..{n}"):
        _parallel.select_devices(n + 1)
    with pytest.raises(ValueError, match="devices must be in"):
        _parallel.select_devices(0)
    with pytest.raises(ValueError, match="list of jax devices"):
        _parallel.select_devices(["cpu"])
    x = jnp.arange(6.0, dtype=jnp.float32).reshape(3, 2)
    padded = _parallel.pad_rows(x, 5)
    np.testing.assert_array_equal(padded, np.array([[0, 1], [2, 3], [4, 5], [4, 5], [4, 5]], np.float32))
    assert _parallel.pad_rows(x, 3) is x
    with pytest.raises(ValueError, match="between 1 and 2 rows"):
        _parallel.pad_rows(x, 2)
    mesh = _parallel.receiver_mesh(1)
    assert mesh.axis_names == (_parallel.RECEIVER_AXIS,)
    np.testing.assert_array_equal(_parallel.shard_rows(x, mesh), x)
    assert [str(d) for d in _parallel.frame_devices(3, 1)] == [str(jax.devices()[0])] * 3
