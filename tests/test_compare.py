"""compare_outputs: error figures on hand-made folders, the difference picture, clear errors."""

import json

import imageio.v3 as iio
import numpy as np
import pytest

from jshadow.compare import compare_outputs, frame_errors


def write(folder, frame, points, irr, **extra):
    folder.mkdir(exist_ok=True)
    normals = np.tile([0.0, 1.0, 0.0], (len(points), 1))
    np.savez(
        folder / f"frame_{frame:04d}.npz",
        points=points,
        normals=normals,
        irradiance=irr,
        radiance=irr / np.pi,
        **extra,
    )


@pytest.fixture
def grid_points():
    g = np.linspace(-1, 1, 4)
    x, z = np.meshgrid(g, np.linspace(-1, 1, 3))
    return np.stack([x.ravel(), np.zeros(12), z.ravel()], -1)


def test_error_figures(tmp_path, grid_points, rng):
    b = 1.0 + rng.random((12, 3))
    a = b.copy()
    a[5, 1] += 0.3
    write(tmp_path / "a", 0, grid_points, a, grid_shape=np.array([3, 4]))
    write(
        tmp_path / "b",
        0,
        grid_points,
        b,
        grid_shape=np.array([3, 4]),
        irradiance_stderr=np.full((12, 3), 0.01),
    )
    write(tmp_path / "a", 1, grid_points, b)
    write(tmp_path / "b", 1, grid_points, b)
    rep = compare_outputs(tmp_path / "a", tmp_path / "b", out_png=tmp_path / "d.png")
    f0, f1 = rep["frames"]
    assert f0["frame"] == 0 and f1["frame"] == 1
    np.testing.assert_allclose(f0["rmse"], 0.3 / 6.0)  # one entry of 36 differs by 0.3
    np.testing.assert_allclose(f0["rel_rmse"], 0.05 / b.mean())
    np.testing.assert_allclose(f0["max_err"], 0.3)
    np.testing.assert_allclose(f0["max_rel_err"], 0.3 / b.mean())
    np.testing.assert_allclose(f0["max_pointwise_rel_err"], 0.3 / b[5, 1])
    np.testing.assert_allclose(f0["ref_stderr_ratio"], 0.01 / 0.05)
    assert f1["rmse"] == 0.0 and f1["max_err"] == 0.0
    assert rep["summary"]["frames"] == 2
    np.testing.assert_allclose(rep["summary"]["max_rel_err"], f0["max_rel_err"])
    img = iio.imread(tmp_path / "d.png")
    assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100
    json.dumps(rep)  # serialisable for the CLI


def test_frame_errors_zero_and_sign():
    b = np.ones((4, 3))
    e = frame_errors(b * 1.1, b)
    np.testing.assert_allclose([e["rmse"], e["rel_rmse"], e["max_err"]], [0.1, 0.1, 0.1])


def test_scatter_picture_without_grid(tmp_path, grid_points):
    b = np.ones((12, 3))
    write(tmp_path / "a", 0, grid_points, b * 0.9, meta=np.array(json.dumps({"note": "no grid"})))
    write(tmp_path / "b", 0, grid_points, b)
    rep = compare_outputs(tmp_path / "a", tmp_path / "b", out_png=tmp_path / "s.png")
    assert rep["png"] == str(tmp_path / "s.png") and (tmp_path / "s.png").stat().st_size > 0


def test_meta_grid_shape(tmp_path, grid_points):
    b = np.ones((12, 3))
    write(tmp_path / "a", 0, grid_points, b, meta=np.array(json.dumps({"grid_shape": [3, 4]})))
    write(tmp_path / "b", 0, grid_points, b, meta=np.array(json.dumps({"grid_shape": [3, 4]})))
    assert (
        compare_outputs(tmp_path / "a", tmp_path / "b", out_png=tmp_path / "m.png")["frames"][0]["rmse"] == 0
    )


def test_clear_errors(tmp_path, grid_points):
    b = np.ones((12, 3))
    write(tmp_path / "a", 0, grid_points, b)
    write(tmp_path / "b", 0, grid_points + [0.0, 0.1, 0.0], b)
    with pytest.raises(ValueError, match="points differ"):
        compare_outputs(tmp_path / "a", tmp_path / "b")
    write(tmp_path / "c", 0, grid_points[:6], b[:6])
    with pytest.raises(ValueError, match="receiver counts differ"):
        compare_outputs(tmp_path / "a", tmp_path / "c")
    write(tmp_path / "d", 0, grid_points, b)
    write(tmp_path / "d", 1, grid_points, b)
    with pytest.raises(ValueError, match=r"frames differ.*\[1\]"):
        compare_outputs(tmp_path / "a", tmp_path / "d")
    with pytest.raises(ValueError, match="no such output folder"):
        compare_outputs(tmp_path / "a", tmp_path / "missing")
    (tmp_path / "e").mkdir()
    with pytest.raises(ValueError, match="no frame_XXXX.npz"):
        compare_outputs(tmp_path / "a", tmp_path / "e")
    (tmp_path / "f").mkdir()
    np.savez(tmp_path / "f" / "frame_0000.npz", points=grid_points)
    with pytest.raises(ValueError, match="missing array 'normals'"):
        compare_outputs(tmp_path / "a", tmp_path / "f")
