"""Helpers shared by the paper-reproduction experiments (table1, shrink_pictures, full_field, pareto,
mitsuba_compare): paths, scene building from a config dict, warm timings, exact visibility SH at
receivers, and a description of the machine. Not a public module of jshadow.
"""

from __future__ import annotations

import copy
import os
import pathlib
import platform
import statistics
import time
from collections.abc import Callable
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from jshadow.config import build_scene, config_from_dict
from jshadow.sh import sh_basis
from jshadow.visibility import hemisphere_directions, ray_fan_any_hit

ROOT = pathlib.Path(__file__).resolve().parents[1]
ASSETS = ROOT / "assets"
RESULTS = ROOT / "experiments" / "results"
FIGURES = ROOT / "experiments" / "figures"
STUDIO = str(ASSETS / "envmaps" / "studio_small_03_512x256.hdr")

# Table 1 models: name -> [[occluder]] keys (mesh file or procedural egg)
MODELS = {
    "bunny_small": {"file": str(ASSETS / "bunny_small.obj")},
    "bunny": {"file": str(ASSETS / "bunny.obj")},
    "spot": {"file": str(ASSETS / "spot.obj")},
    "airplane": {"file": str(ASSETS / "airplane.obj")},
    "egg": {"shape": "egg", "subdivisions": 3, "stretch": 0.2},
}


def scene_dict(
    model: str | None,
    *,
    res: int = 160,
    method: dict | None = None,
    environment: dict | None = None,
    center=(0.0, 1.1, 0.0),
    radius: float = 0.9,
    lights: list | None = None,
) -> dict:
    """A config dict (the TOML schema of DESIGN.md §4): one occluder ``model`` (a key of
    :data:`MODELS`, "sphere" for a sphere occluder of ``radius``, or None for none) above a
    ``res``² receiver plane of size 4 × 4 at y = 0, lit by ``environment`` (default: the studio map)."""
    d: dict = {
        "method": dict(method or {}),
        "environment": environment or {"type": "hdr", "file": STUDIO, "radiance": [1.0, 1.0, 1.0]},
        "receiver": {
            "type": "plane",
            "center": [0.0, 0.0, 0.0],
            "size": [4.0, 4.0],
            "resolution": [res, res],
            "albedo": [0.8, 0.8, 0.8],
        },
    }
    if model == "sphere":
        d["occluder"] = [{"type": "sphere", "center": list(center), "radius": radius}]
    elif model is not None:
        d["occluder"] = [{"type": "mesh", **MODELS[model], "center": list(center), "radius": radius}]
    if lights:
        d["light"] = copy.deepcopy(lights)
    return d


def unit_mesh(model: str, dtype=jnp.float32):
    """(vertices (V, 3), faces (F, 3)) of a :data:`MODELS` mesh normalised to its unit bounding
    sphere at the origin (AABB centre, radius to the farthest vertex)."""
    from jshadow.geometry import egg, load_mesh, normalize_to_unit_sphere

    spec = MODELS[model]
    mesh = load_mesh(spec["file"], dtype=dtype) if "file" in spec else egg(3, spec["stretch"], dtype=dtype)
    return normalize_to_unit_sphere(mesh.vertices), jnp.asarray(mesh.faces, jnp.int32)


def make_scene(d: dict):
    """:func:`jshadow.build_scene` of a config dict (paths are absolute)."""
    return build_scene(config_from_dict(d, source="<experiment>", root=ROOT))


def block(x):
    return jax.block_until_ready(x)


def timed(fn: Callable, *args, runs: int = 5) -> tuple[float, float, object]:
    """(first call ms, median of ``runs`` warm calls ms, result) of ``fn(*args)`` with
    ``block_until_ready`` (DESIGN.md §5)."""
    t0 = time.perf_counter()
    out = block(fn(*args))
    first = time.perf_counter() - t0
    ts = []
    for _ in range(runs):
        t0 = time.perf_counter()
        out = block(fn(*args))
        ts.append(time.perf_counter() - t0)
    return 1e3 * first, 1e3 * statistics.median(ts), out


def world_dirs(frames, local):
    """Local directions (K, 3) in the frames (G, 3, 3) (columns = local axes) -> (G, K, 3)."""
    return jnp.einsum("gij,kj->gki", frames, local)


@partial(jax.jit, static_argnames=("n", "directions"))
def exact_visibility_sh(points, vertices, faces, *, n: int, directions: tuple[int, int]):
    """SH (N, n²) of the exact visibility of a mesh over the whole sphere, seen from ``points``.

    Gauss–Legendre × uniform-φ directions on each of the two world hemispheres (±y), traced with
    :func:`jshadow.visibility.ray_fan_any_hit`. With the default 32² per hemisphere the projection
    is converged to about 1e-3 for 4–6 bands (binary visibility: the error is that of sampling the
    silhouette on the grid).
    """
    local, w = hemisphere_directions(*directions, dtype=points.dtype)  # z > 0 hemisphere
    up = jnp.stack([local[:, 0], local[:, 2], local[:, 1]], axis=-1)  # z -> +y
    dirs = jnp.concatenate([up, up * jnp.asarray([1.0, -1.0, 1.0], points.dtype)])
    weights = jnp.concatenate([w, w])
    occ = ray_fan_any_hit(points, jnp.broadcast_to(dirs, (points.shape[0], *dirs.shape)), vertices, faces)
    vis = 1.0 - occ.astype(points.dtype)
    return vis @ (sh_basis(dirs, n) * weights[:, None])


def git_state() -> str:
    """The commit measured and whether jshadow/ had uncommitted changes (others edit the tree)."""
    import subprocess

    def run(*a):
        return subprocess.run(
            ["git", *a], cwd=ROOT, capture_output=True, text=True, check=False
        ).stdout.strip()

    dirty = run("status", "--porcelain", "--", "jshadow")
    return run("rev-parse", "--short", "HEAD") + (" + uncommitted changes in jshadow/" if dirty else "")


def machine() -> dict:
    """Machine, software, load and the code state at measurement time."""
    return {
        "git": git_state(),
        "cpu": platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
        "backend": jax.devices()[0].platform,
        "jax": jax.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "load_avg_1_5_15": [round(x, 2) for x in os.getloadavg()],
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
    }


def md_table(header: list[str], rows: list[list]) -> str:
    """A GitHub markdown table."""
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)
