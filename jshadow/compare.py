"""Error of one output folder against another (usually the Monte Carlo reference).

Both folders hold ``frame_XXXX.npz`` files with ``points``, ``normals``, ``irradiance``,
``radiance`` (N, 3) and optionally ``irradiance_stderr``, ``plane_count`` and ``grid_shape``
(DESIGN.md §4). Errors are of irradiance, over all receivers and colour channels; relative figures
divide by the mean irradiance of ``b`` (DESIGN.md §5).
"""

from __future__ import annotations

import json
import pathlib
import re

import numpy as np

__all__ = ["compare_outputs", "frame_errors"]

_FRAME = re.compile(r"^frame_(\d{4})\.npz$")
_REQUIRED = ("points", "normals", "irradiance", "radiance")


def _frames(folder: pathlib.Path) -> dict[int, pathlib.Path]:
    if not folder.is_dir():
        raise ValueError(f"{folder}: no such output folder")
    found = {int(m.group(1)): p for p in folder.iterdir() if (m := _FRAME.match(p.name))}
    if not found:
        raise ValueError(f"{folder}: no frame_XXXX.npz files")
    return found


def _load(path: pathlib.Path) -> dict[str, np.ndarray]:
    with np.load(path, allow_pickle=False) as z:
        data = {k: z[k] for k in z.files}
    for k in _REQUIRED:
        if k not in data:
            raise ValueError(f"{path}: missing array {k!r} (expected {', '.join(_REQUIRED)})")
        if data[k].ndim != 2 or data[k].shape[1] != 3:
            raise ValueError(f"{path}: {k!r} must have shape (N, 3), got {data[k].shape}")
    return data


def _grid_shape(data: dict[str, np.ndarray]) -> tuple[int, int] | None:
    if "grid_shape" in data:
        g = np.asarray(data["grid_shape"]).ravel()
        return (int(g[0]), int(g[1])) if g.size == 2 else None
    if "meta" in data:
        try:
            meta = json.loads(str(np.asarray(data["meta"]).item()))
            g = meta.get("grid_shape")
            return (int(g[0]), int(g[1])) if g is not None and len(g) == 2 else None
        except (ValueError, TypeError, AttributeError):
            return None
    return None


def frame_errors(a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    """Irradiance errors of a against b, both (N, 3): ``rmse``, ``rel_rmse`` (÷ mean of b),
    ``max_err``, ``max_rel_err`` (max error ÷ mean of b), ``max_pointwise_rel_err``
    (max |a − b| / |b| over entries with |b| above 1e-3 of the mean) and ``mean_irradiance_b``."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    diff = a - b
    mean_b = float(np.mean(b))
    rmse = float(np.sqrt(np.mean(diff**2)))
    max_err = float(np.max(np.abs(diff)))
    scale = abs(mean_b) if mean_b != 0 else 1.0
    big = np.abs(b) > 1e-3 * scale
    pointwise = float(np.max(np.abs(diff[big]) / np.abs(b[big]))) if np.any(big) else 0.0
    return {
        "rmse": rmse,
        "rel_rmse": rmse / scale,
        "max_err": max_err,
        "max_rel_err": max_err / scale,
        "max_pointwise_rel_err": pointwise,
        "mean_irradiance_b": mean_b,
    }


def _difference_png(out_png, a: dict, b: dict, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    diff = np.mean(np.asarray(a["irradiance"], np.float64) - np.asarray(b["irradiance"], np.float64), axis=1)
    n_plane = int(b["plane_count"]) if "plane_count" in b else diff.shape[0]
    grid = _grid_shape(b) or _grid_shape(a)
    lim = float(np.max(np.abs(diff))) or 1.0
    fig, ax = plt.subplots(figsize=(5.2, 4.4), dpi=100)
    if grid is not None and grid[0] * grid[1] in (n_plane, diff.shape[0]):
        img = diff[: grid[0] * grid[1]].reshape(grid)
        im = ax.imshow(img, cmap="RdBu_r", vmin=-lim, vmax=lim, origin="lower", interpolation="nearest")
        ax.set_xlabel("column")
        ax.set_ylabel("row")
    else:
        pts = np.asarray(b["points"])
        im = ax.scatter(pts[:, 0], pts[:, 2], c=diff, cmap="RdBu_r", vmin=-lim, vmax=lim, s=6)
        ax.set_xlabel("x")
        ax.set_ylabel("z")
        ax.set_aspect("equal")
    fig.colorbar(im, ax=ax, label="irradiance a − b (mean of RGB)")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(out_png)
    plt.close(fig)


def compare_outputs(dir_a, dir_b, out_png=None) -> dict:
    """Per-frame irradiance errors of output folder ``dir_a`` against ``dir_b`` (the reference).

    Returns ``{"frames": [{"frame", "rmse", "rel_rmse", "max_err", "max_rel_err",
    "max_pointwise_rel_err", "mean_irradiance_b"[, "ref_stderr_rms", "ref_stderr_ratio"]}, ...],
    "summary": {...}, "png": path or None}``. ``ref_stderr_ratio`` is the RMS standard error of b
    divided by the RMSE: it should be ≤ 0.1 for the error to be meaningful (DESIGN.md §5).
    ``out_png``: a signed difference image of the first frame (diverging colour map), on the
    receiver plane's grid when ``grid_shape`` (or a JSON ``meta`` entry with it) factors the
    receiver count, else a scatter over the points' x/z.

    Raises ValueError when a folder is missing or empty, the frame sets differ, arrays are missing
    or malformed, or the receiver points differ.
    """
    pa, pb = pathlib.Path(dir_a), pathlib.Path(dir_b)
    fa, fb = _frames(pa), _frames(pb)
    if set(fa) != set(fb):
        only_a = sorted(set(fa) - set(fb))
        only_b = sorted(set(fb) - set(fa))
        raise ValueError(f"frames differ: only in {pa}: {only_a}, only in {pb}: {only_b}")
    frames, first = [], None
    for f in sorted(fa):
        a, b = _load(fa[f]), _load(fb[f])
        if a["points"].shape != b["points"].shape:
            raise ValueError(
                f"frame {f}: receiver counts differ "
                f"({a['points'].shape[0]} in {pa}, {b['points'].shape[0]} in {pb})"
            )
        pts_a, pts_b = np.asarray(a["points"], np.float64), np.asarray(b["points"], np.float64)
        tol = 1e-5 * max(float(np.max(np.abs(pts_b))), 1.0)
        if not np.allclose(pts_a, pts_b, rtol=0.0, atol=tol):
            worst = int(np.argmax(np.max(np.abs(pts_a - pts_b), axis=1)))
            raise ValueError(
                f"frame {f}: receiver points differ "
                f"(first at index {worst}: {pts_a[worst]} vs {pts_b[worst]})"
            )
        row = {"frame": f, **frame_errors(a["irradiance"], b["irradiance"])}
        if "irradiance_stderr" in b:
            se = float(np.sqrt(np.mean(np.asarray(b["irradiance_stderr"], np.float64) ** 2)))
            row["ref_stderr_rms"] = se
            row["ref_stderr_ratio"] = se / row["rmse"] if row["rmse"] > 0 else float("inf")
        frames.append(row)
        if first is None:
            first = (a, b, f)
    summary = {
        "frames": len(frames),
        "mean_rel_rmse": float(np.mean([r["rel_rmse"] for r in frames])),
        "max_rel_rmse": float(np.max([r["rel_rmse"] for r in frames])),
        "max_rel_err": float(np.max([r["max_rel_err"] for r in frames])),
    }
    png = None
    if out_png is not None:
        a, b, f = first
        row = frames[0]
        title = (
            f"{pa.name} − {pb.name}, frame {f}: rel. RMSE {row['rel_rmse']:.2%}, max {row['max_rel_err']:.2%}"
        )
        _difference_png(out_png, a, b, title)
        png = str(out_png)
    return {"frames": frames, "summary": summary, "png": png}
