"""The "about 20 times faster than full shadow field computation" claim of the deformable-shadow-fields
paper (Sec. 5), measured: a per-frame BSV (one shell) + the precomputed M_k table, against sampling
the object occlusion field of Zhou et al. 2005 on every radial shell.

Both sides use the same sampler, grid and directions: a 12×20 (θ × φ) grid of points on each shell,
32² directions per hemisphere, 4 SH bands. The full field samples the 16 shells at exactly the
distances of the method's M_k table (0.2 … 8 shell radii, geometric, with the shell as a node);
on shells outside the bounding sphere only the hemisphere facing the centre is cast (the other one
is free), on shells inside it both hemispheres. Settings:

* ``paper``: shell R = r; BSV and every shell by the brute-force ray caster
  (:func:`jshadow.visibility.ray_fan_any_hit`);
* ``shell1.5``: shell R = 1.5 r (the same square-silhouette M_k, 4 bands); BSV and the shells
  outside the bounding sphere by the edge-scan (its 32² gnomonic cone image), shells inside it by
  the brute force over the whole sphere.

Evaluation at receivers: the method interpolates the BSV bilinearly, applies M_k and rotates
(:func:`jshadow.field.bsv_visibility_sh`); the full field interpolates each shell bilinearly,
then linearly in k = R/d between the two bracketing shells, and rotates (no visibility beyond the
outermost shell, the innermost shell clamped, as the method does). Both are compared with the
exact visibility projected at each receiver (``_common.exact_visibility_sh``: rays over the whole
sphere, 32² per hemisphere) for three receiver sets around the bunny (bounding radius 0.8 at
(0, 1, 0), the calibration setting of DESIGN.md §2): the 32² plane y = 0 over [−2, 2]², 512 random
points at d ∈ [1.05, 6] r, and 384 of the bunny's own vertices (self-shadowing). Errors:
``rel L2 vis`` = RMS over receivers of ‖S − S_exact‖ / RMS of ‖S_exact − S_unoccluded‖ (SH
coefficients, n bands); for the plane also the relative RMSE of irradiance under a constant
environment L = 1 (``E = S · clamped cosine``) against the exact visibility's n-band irradiance.

Times: warm medians (``--runs``) with ``block_until_ready``; the M_k table is built once per
method configuration (numpy, not per frame), its build time is reported separately.

Usage (repository root, project environment active)::

    python experiments/full_field.py [--runs 3]

Writes ``experiments/results/full_field.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from _common import RESULTS, exact_visibility_sh, machine, timed, unit_mesh, world_dirs

from jshadow import sh
from jshadow.field import bsv_visibility_sh, interpolate_bsv, unit_visibility
from jshadow.geometry import bounding_sphere, vertex_normals
from jshadow.scaling import mk_table
from jshadow.scaling._matrices import _blocks
from jshadow.visibility import (
    bsv_frames,
    bsv_grid_angles,
    bsv_mesh,
    bsv_mesh_edgescan,
    hemisphere_directions,
    ray_fan_any_hit,
)

N_BANDS = 4
GRID = (12, 20)
DIRS = (32, 32)
CENTER = np.array([0.0, 1.0, 0.0])
RADIUS = 0.8


@partial(jax.jit, static_argnames=("back", "n", "grid", "directions"))
def shell_coeffs(vertices, faces, s, *, back: bool, n: int, grid, directions):
    """(T, P, n²) local-frame visibility SH on the shell of radius s·r (brute force); ``back`` also
    casts the hemisphere facing away from the centre (needed inside the bounding sphere)."""
    dtype = vertices.dtype
    center, radius = bounding_sphere(vertices)
    theta, phi = bsv_grid_angles(*grid, dtype)
    u, frames = bsv_frames(theta[:, None], phi[None, :])
    points = center + (s * radius) * u
    local, w = hemisphere_directions(*directions, dtype=dtype)
    if back:
        local = jnp.concatenate([local, local * jnp.asarray([1.0, 1.0, -1.0], dtype)])
        w = jnp.concatenate([w, w])
    occ = ray_fan_any_hit(points.reshape(-1, 3), world_dirs(frames.reshape(-1, 3, 3), local), vertices, faces)
    full = jnp.zeros(n * n, dtype).at[0].set(math.sqrt(4.0 * math.pi))
    return (full - occ.astype(dtype) @ (sh.sh_basis(local, n) * w[:, None])).reshape(*grid, n * n)


def full_field(vertices, faces, radii, setting: str):
    """(S, T, P, n²) coefficients on every shell (radii in bounding radii, any order)."""
    out = []
    for s in radii:
        if setting == "shell1.5" and s > 1.0:
            out.append(
                bsv_mesh_edgescan(vertices, faces, n=N_BANDS, grid=GRID, directions=DIRS, shell=s).coeffs
            )
        else:
            out.append(
                shell_coeffs(
                    vertices, faces, jnp.float32(s), back=s < 1.0, n=N_BANDS, grid=GRID, directions=DIRS
                )
            )
    return jnp.stack(out)


@jax.jit
def full_field_eval(coeffs, radii, center, radius, points):
    """World-frame visibility SH (N, n²) from shells ``coeffs`` (S, T, P, n²) at ``radii`` (S,)
    ascending (bounding radii): bilinear in (θ, φ), linear in k = 1/d between shells."""
    rel = points - center
    d = jnp.linalg.norm(rel, axis=-1) / radius
    u = rel / jnp.linalg.norm(rel, axis=-1, keepdims=True)
    theta = jnp.arccos(jnp.clip(u[:, 2], -1.0, 1.0))
    phi = jnp.arctan2(u[:, 1], u[:, 0])
    per = jax.vmap(lambda c: interpolate_bsv(c, theta, phi))(coeffs)  # (S, N, n²)
    ks = 1.0 / radii  # descending
    k = 1.0 / jnp.maximum(d, radii[0])  # clamp inside the innermost shell
    i = jnp.clip(
        jnp.sum(ks[None, :] >= k[:, None], axis=1) - 1, 0, radii.shape[0] - 2
    )  # ks[i] >= k > ks[i+1]
    w = jnp.clip((ks[i] - k) / (ks[i] - ks[i + 1]), 0.0, 1.0)[:, None]
    ar = jnp.arange(points.shape[0])
    c = (1.0 - w) * per[i, ar] + w * per[i + 1, ar]
    _, frame = bsv_frames(theta, phi)
    s_w = sh.rotate(c, frame)
    n = sh.sh_bands_of(coeffs.shape[-1])
    return jnp.where((d <= radii[-1] * 1.0001)[:, None], s_w, unit_visibility(d.shape, n, s_w.dtype))


def receiver_sets(vertices, faces, seed: int = 0):
    rng = np.random.default_rng(seed)
    g = (np.arange(32) + 0.5) / 32 * 4.0 - 2.0
    xx, zz = np.meshgrid(g, g)
    plane = np.stack([xx.ravel(), np.zeros(xx.size), zz.ravel()], axis=1)
    dirs = rng.normal(size=(512, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    d = RADIUS * np.exp(rng.uniform(np.log(1.05), np.log(6.0), 512))
    cloud = CENTER + dirs * d[:, None]
    idx = rng.choice(vertices.shape[0], 384, replace=False)
    normals = np.asarray(vertex_normals(vertices, faces))[idx]
    return {"plane": plane, "cloud": cloud, "vertices": np.asarray(vertices)[idx]}, normals


def errors(s, s_ex, n, normals=None):
    s, s_ex = np.asarray(s, np.float64), np.asarray(s_ex, np.float64)
    unit = np.zeros(n * n)
    unit[0] = math.sqrt(4 * math.pi)
    out = {
        "rel_l2_vis": float(
            np.sqrt(np.mean(np.sum((s - s_ex) ** 2, -1))) / np.sqrt(np.mean(np.sum((s_ex - unit) ** 2, -1)))
        )
    }
    if normals is not None:
        t = np.asarray(sh.clamped_cosine(jnp.asarray(normals, jnp.float32), n), np.float64)
        e, e_ex = np.sum(s * t, -1), np.sum(s_ex * t, -1)
        out["irradiance_rel_rmse"] = float(np.sqrt(np.mean((e - e_ex) ** 2)) / np.mean(e_ex))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=3, help="warm runs per timing (median)")
    args = ap.parse_args()
    info = machine()
    unit_v, faces = unit_mesh("bunny")
    vertices = jnp.asarray(CENTER, jnp.float32) + RADIUS * unit_v
    sets, v_normals = receiver_sets(vertices, faces)
    exact = {
        k: exact_visibility_sh(jnp.asarray(p, jnp.float32), vertices, faces, n=N_BANDS, directions=DIRS)
        for k, p in sets.items()
    }
    plane_normals = np.tile([0.0, 1.0, 0.0], (sets["plane"].shape[0], 1))
    out_rows = []
    for setting, shell, method in (("paper", 1.0, "brute"), ("shell1.5", 1.5, "edgescan")):
        _blocks.cache_clear()
        t0 = time.perf_counter()
        table = mk_table(n=N_BANDS, num=16, d_min=0.2, d_max=8.0, dtype=jnp.float32)
        table_ms = 1e3 * (time.perf_counter() - t0)
        radii = np.sort(np.asarray(table.distances, np.float64) * shell)  # bounding radii, ascending
        bsv_first, bsv_ms, bsv = timed(
            lambda shell=shell, method=method: bsv_mesh(
                vertices, faces, n=N_BANDS, grid=GRID, directions=DIRS, shell=shell, method=method
            ),
            runs=args.runs,
        )
        ff_first, ff_ms, ff = timed(
            lambda radii=radii, setting=setting: full_field(vertices, faces, radii, setting), runs=args.runs
        )
        radii_j = jnp.asarray(radii, jnp.float32)
        row = {
            "setting": setting,
            "shell": shell,
            "sampler": method,
            "shell_radii_over_r": radii.tolist(),
            "bsv_ms": bsv_ms,
            "bsv_first_call_ms": bsv_first,
            "mk_table_build_ms_once": table_ms,
            "full_field_ms": ff_ms,
            "full_field_first_call_ms": ff_first,
            "speedup_full_over_bsv": ff_ms / bsv_ms,
            "errors": {},
        }
        for name, pts in sets.items():
            p = jnp.asarray(pts, jnp.float32)
            _, m_ms, s_m = timed(bsv_visibility_sh, bsv, table, p, runs=args.runs)
            _, f_ms, s_f = timed(full_field_eval, ff, radii_j, bsv.center, bsv.radius, p, runs=args.runs)
            normals = plane_normals if name == "plane" else (v_normals if name == "vertices" else None)
            row["errors"][name] = {
                "receivers": int(p.shape[0]),
                "method": errors(s_m, exact[name], N_BANDS, normals),
                "full_field": errors(s_f, exact[name], N_BANDS, normals),
                "eval_ms_method": m_ms,
                "eval_ms_full_field": f_ms,
            }
        out_rows.append(row)
        print(
            f"{setting}: BSV {bsv_ms:.1f} ms, full field (16 shells) {ff_ms:.1f} ms -> "
            f"{row['speedup_full_over_bsv']:.1f}x; M_k table {table_ms:.0f} ms once",
            flush=True,
        )
        for name, e in row["errors"].items():
            print(
                f"   {name:>8}: rel L2 vis  method {100 * e['method']['rel_l2_vis']:.1f} %  "
                f"full field {100 * e['full_field']['rel_l2_vis']:.1f} %"
                + (
                    f";  irradiance rel RMSE method {100 * e['method']['irradiance_rel_rmse']:.2f} %  "
                    f"full field {100 * e['full_field']['irradiance_rel_rmse']:.2f} %"
                    if "irradiance_rel_rmse" in e["method"]
                    else ""
                )
            )
    info["load_avg_after"] = machine()["load_avg_1_5_15"]
    out = {"settings": vars(args), "machine": info, "rows": out_rows, "paper_claim": "about 20x faster"}
    (RESULTS / "full_field.json").write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
