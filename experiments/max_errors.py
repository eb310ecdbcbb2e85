"""Where the default's largest errors come from, on the four scenes whose max error is largest.

The default meets ≤ 1 % relative RMSE on every scene of ``experiments/defaults.py`` but not ≤ 5 %
max error on all (BENCHMARKS.md, the latest run). This script measures what limits those maxima:

* ``worst``: for each of the four, the default's ten largest errors against the cached Monte Carlo
  reference (``experiments/results/refs/``), each with where it is (plane or own vertex), the
  reference's value and standard error there, and the count of receivers over 5 %;
* ``transfer``: the bending spot cow under a sky (``spot_self_sky_bend_last``, its last frame), the
  own vertices' shadowed diffuse transfer under the scene's sky against a fine reference transfer
  (exact rays over a 32 × 128 hemisphere grid about each vertex normal,
  :func:`jshadow.visibility.vertex_visibility_sh`): from the default's entry-face images over its
  12 × 24 sphere grid (:func:`jshadow.visibility.vertex_transfer_maps`), from exact rays over sphere
  grids of 12 × 24, 16 × 32 and 24 × 48 (the same directions for every vertex, as images need), from
  a 288-point Fibonacci sphere, from exact rays over a 12 × 48 hemisphere grid (the static meshes'
  ``self_visibility = "rays"``), and from the 12 × 24 grid with its *boundary* cells (whose
  visibility differs from a neighbour's, with n·ω > 0.25) split into 2 × 2 exact sub-directions;
* ``rings``: both bending meshes' own vertices' transfer (as ``transfer``), with the pairs whose
  four pixel centres disagree (n·d > 0; the nearest-pixel answer is unsure there) tested exactly
  against the faces within 6 rings of their vertex instead of 2 (the default tests rings 1–2 for
  every pair), against every pair tested so;
* ``lamps``: the animated bunny's plane with the lamps' visibility by exact rays (point lamps, no
  images) at 64, 256 and 1024 lamps, and at 1024 with the map split at 0.1 × its mean (nearly all
  of the map in lamps), through :class:`jshadow.Renderer` with
  ``jshadow.scene.lamp_visibility`` replaced for the run;
* ``pixels``: the same plane's largest errors under the plain lookups (receivers 911 and 592),
  against the map itself by exact rays: every map pixel sampled S × S (S = 1, 2, 4; uniform in
  cos θ and φ within the pixel, the reference's own sampling density) against the reference, and
  the map's bright part (split at 2 × its mean) by 64 / 256 / 1024 point lamps by exact rays
  against its pixels sampled 4 × 4: what a lamp's point costs where a shadow's edge crosses the
  studio map's compact key light (``method.lamp_penumbrae``).

Usage (repository root, project environment active)::

    python experiments/max_errors.py [--parts worst transfer rings lamps pixels]

Writes ``experiments/results/max_errors.json``: the parts run replace their entries, the others'
are kept; ``part_runs`` gives each part's commit and date as it was last run (``git`` and ``date``:
the file's last write).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from numpy.polynomial.legendre import leggauss

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import defaults  # noqa: E402
import light_field  # noqa: E402
import models  # noqa: E402
from _common import git_state  # noqa: E402

import jshadow.scene as scene_mod  # noqa: E402
from jshadow.entities import frame_time, receivers_at  # noqa: E402
from jshadow.geometry import vertex_normals  # noqa: E402
from jshadow.lights import environment_sh  # noqa: E402
from jshadow.sh import clamped_cosine, sh_basis, sphere_grid  # noqa: E402
from jshadow.visibility import (  # noqa: E402
    _own_exact,  # noqa: E402
    lamp_images,
    ray_fan_any_hit,
    ring_faces,
    vertex_lamp_visibility,
    vertex_transfer_maps,
    vertex_visibility_sh,
)

OUT = pathlib.Path(__file__).resolve().parent / "results" / "max_errors.json"
SCENES = ["bunny_studio", "bunny_animated_last", "spot_self_sky_bend_last", "bunny_self_sky_bend_last"]
RES = 32  # the plane's receivers per side, as experiments/defaults.py
BANDS = 5  # the transfer's bands (the default's n + 1)


def _default_scene(name: str, over: dict | None = None):
    build, frame, sphere_path, _ = light_field._cases()[name]
    nband = dict(models.VARIANTS[models.DEFAULT_VARIANT])
    base = build(nband, RES)
    ref = models.reference(name, build(models.VARIANTS["paper"], RES), frame, 1e-3, 32768)
    scene = build({**nband, **defaults.auto_keys(base), **(over or {})}, RES)
    return scene, frame, sphere_path, ref, int(np.prod(base.receivers.grid_shape))


def worst(name: str, top: int = 10) -> dict:
    """The default's largest errors on one case, each with where and how noisy the reference is."""
    scene, frame, sphere_path, ref, n_plane = _default_scene(name)
    approx, _, _ = models.timed(scene, frame, sphere_path, 1)
    mean = float(np.mean(ref["mean"]))
    diff = (approx - ref["mean"]) / mean  # (N, 3)
    channel = np.argmax(np.abs(diff), axis=1)
    rows = np.arange(diff.shape[0])
    err = diff[rows, channel]
    pts, nrm = (np.asarray(x) for x in receivers_at(scene, frame))
    out = []
    for i in np.argsort(-np.abs(err))[:top]:
        c = channel[i]
        out.append(
            {
                "receiver": int(i),
                "where": "plane" if i < n_plane else "vertex",
                "err_pct": round(100 * float(err[i]), 2),
                "ref_over_mean": round(float(ref["mean"][i, c]) / mean, 3),
                "ref_stderr_pct": round(100 * float(ref["stderr"][i, c]) / mean, 2),
                "point": np.round(pts[i], 3).tolist(),
                "normal": np.round(nrm[i], 2).tolist(),
            }
        )
    over5 = np.abs(err) > 0.05
    return {
        "largest": out,
        "over_5pct_plane": int(over5[:n_plane].sum()),
        "over_5pct_vertices": int(over5[n_plane:].sum()),
    }


def _pose(name: str):
    scene, frame, _, _, _ = _default_scene(name)
    occ = scene.occluders[0]
    t = jnp.float32(frame_time(frame, scene.n_frames))
    v = np.asarray(scene_mod._vertices_at(occ, t))
    return scene, v, np.asarray(occ.faces), float(scene_mod._concrete_lift(scene, t))


def _cells(nt: int, nph: int, sub: int) -> np.ndarray:
    """(nt·nph, sub², 3): each cell of the Gauss–Legendre × uniform sphere grid cut into sub × sub
    parts of equal solid angle (equal steps in z between the rule's weight boundaries, and in φ)."""
    _, wl = leggauss(nt)
    edges = np.concatenate([[1.0], 1.0 - np.cumsum(wl[::-1])])  # z from the pole down, as the grid
    edges[-1] = -1.0
    dphi = 2 * np.pi / nph
    out = np.zeros((nt, nph, sub * sub, 3))
    for i in range(nt):
        for a in range(sub):
            z = edges[i] + (edges[i + 1] - edges[i]) * (a + 0.5) / sub
            r = np.sqrt(max(0.0, 1 - z * z))
            for j in range(nph):
                for b in range(sub):
                    ph = (j + (b + 0.5) / sub) * dphi
                    out[i, j, a * sub + b] = [r * np.cos(ph), r * np.sin(ph), z]
    return out.reshape(nt * nph, sub * sub, 3)


def _sky_case(name: str):
    """One case's pose and what its own vertices' transfer is measured with: the scene, vertices,
    faces, lift, the sky's n²-band SH (n², 3), the vertex normals, the lifted origins, the clamped
    cosine's exact SH and the fine reference irradiance (exact rays over a 32 × 128 hemisphere)."""
    scene, v, f, lift = _pose(name)
    light = np.asarray(environment_sh(scene.environment, BANDS))  # (n², 3)
    nrm = np.asarray(vertex_normals(jnp.asarray(v), jnp.asarray(f)))
    origins = jnp.asarray(v + lift * nrm)
    exact_cos = np.asarray(clamped_cosine(jnp.asarray(nrm), BANDS))
    fine_e = np.asarray(vertex_visibility_sh(v, f, BANDS, (32, 128), True, lift, True)) @ light
    return scene, v, f, lift, light, nrm, origins, exact_cos, fine_e


def _transfer_errors(coeffs, light, fine_e) -> dict:
    """Relative RMSE and max (% of the reference's mean) of the irradiance from transfer SH
    ``coeffs``, and the vertices over 5 %."""
    d = (coeffs @ light - fine_e) / float(fine_e.mean())
    a = np.abs(d).max(1)
    return {
        "rel_rmse_pct": 100 * float(np.sqrt(np.mean(d**2))),
        "max_rel_err_pct": 100 * float(a.max()),
        "vertices_over_5pct": int((a > 0.05).sum()),
    }


def transfer(name: str = "spot_self_sky_bend_last") -> dict:
    """The own vertices' transfer under the scene's sky, quadrature by quadrature (see the module
    docstring); relative RMSE and max of the irradiance against the fine hemisphere grid."""
    t0 = time.perf_counter()
    scene, v, f, lift, light, nrm, origins, exact_cos, fine_e = _sky_case(name)
    vj, fj = jnp.asarray(v), jnp.asarray(f)

    def visible(dirs):  # (V, D) or shared (D, 3) directions
        hit = ray_fan_any_hit(origins, jnp.asarray(dirs, jnp.float32), vj, fj, t_min=lift)
        return 1.0 - np.asarray(hit, np.float64)

    out = {"vertices": int(v.shape[0]), "fine_s": time.perf_counter() - t0, "quadratures": {}}

    def record(label, coeffs, directions):
        row = {"directions_per_vertex": directions, **_transfer_errors(coeffs, light, fine_e)}
        out["quadratures"][label] = row
        print(f"  {label:44s} rmse {row['rel_rmse_pct']:.2f} %  max {row['max_rel_err_pct']:.2f} %")

    grid = tuple(scene.method.self_maps_grid)
    res = scene.method.self_maps_resolution
    local = ring_faces(f, v.shape[0], scene_mod.MAPS_RINGS)
    maps = vertex_transfer_maps(v, f, BANDS, local, lift, grid, res, scene_mod.MAPS_TRANSFER_MARGIN)
    record(f"images {grid[0]} x {grid[1]} at {res}² (the default)", np.asarray(maps), grid[0] * grid[1])
    for g in ((12, 24), (16, 32), (24, 48)):
        exact = vertex_visibility_sh(v, f, BANDS, g, False, lift, True)
        record(f"exact rays, sphere grid {g[0]} x {g[1]}", np.asarray(exact), g[0] * g[1])
    n = 288
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    ph = np.pi * (1 + 5**0.5) * k
    fib = np.stack([np.sqrt(1 - z * z) * np.cos(ph), np.sqrt(1 - z * z) * np.sin(ph), z], 1)
    occluded = (1 - visible(fib)) * np.maximum(nrm @ fib.T, 0) * (4 * np.pi / n)
    record(
        "exact rays, 288 Fibonacci directions",
        exact_cos - occluded @ np.asarray(sh_basis(jnp.asarray(fib), BANDS)),
        n,
    )
    hemi = vertex_visibility_sh(v, f, BANDS, (12, 48), True, lift, True)
    record("exact rays, hemisphere grid 12 x 48", np.asarray(hemi), 576)
    # the 12 x 24 grid with its boundary cells split into 2 x 2 exact sub-directions
    d0, w0 = (np.asarray(x, np.float64) for x in sphere_grid(12, 24))
    vis0 = visible(d0)
    cos0 = np.maximum(nrm @ d0.T, 0)
    y0 = np.asarray(sh_basis(jnp.asarray(d0, jnp.float32), BANDS), np.float64)
    g = vis0.reshape(-1, 12, 24)
    edge = (g != np.roll(g, 1, 2)) | (g != np.roll(g, -1, 2))
    edge[:, 1:] |= g[:, 1:] != g[:, :-1]
    edge[:, :-1] |= g[:, :-1] != g[:, 1:]
    chosen = edge.reshape(g.shape[0], -1) & (cos0 > 0.25)
    sub = _cells(12, 24, 2)  # (288, 4, 3)
    iv, ic = np.nonzero(chosen)
    sub_vis = 1.0 - np.asarray(
        ray_fan_any_hit(origins[iv], jnp.asarray(sub[ic], jnp.float32), vj, fj, t_min=lift), np.float64
    )  # (P, 4)
    sub_cos = np.maximum(np.einsum("pk,psk->ps", nrm[iv], sub[ic]), 0)
    sub_y = np.asarray(sh_basis(jnp.asarray(sub[ic].reshape(-1, 3), jnp.float32), BANDS)).reshape(
        len(iv), 4, -1
    )
    occ_cells = ((1 - vis0) * cos0 * w0)[:, :, None] * y0[None]  # (V, 288, n²)
    occ_cells[iv, ic] = np.einsum("ps,ps,psk->pk", 1 - sub_vis, sub_cos, sub_y) * (w0[ic] / 4)[:, None]
    record(
        f"exact 12 x 24, boundary cells (n·ω > 0.25) 2 x 2 ({chosen.sum() / (cos0 > 0).sum():.0%} of cells)",
        exact_cos - occ_cells.sum(1),
        288,
    )
    return out


def rings(names=("bunny_self_sky_bend_last", "spot_self_sky_bend_last"), wide: int = 6) -> dict:
    """The own vertices' transfer with the ambiguous pairs' near faces widened to ``wide`` rings
    (see the module docstring); relative RMSE and max against the fine hemisphere grid. The pairs
    are :func:`jshadow.visibility.settle_ambiguous`'s with ``reach`` 0 (its four centres)."""
    out = {}
    for name in names:
        scene, v, f, lift, light, nrm, origins, exact_cos, fine_e = _sky_case(name)
        vj, fj = jnp.asarray(v), jnp.asarray(f)
        grid, res = tuple(scene.method.self_maps_grid), scene.method.self_maps_resolution
        margin, base = scene_mod.MAPS_TRANSFER_MARGIN, scene_mod.MAPS_RINGS
        dirs, w = sphere_grid(*grid, dtype=jnp.float32)
        images = lamp_images(vj, f, dirs, res, entry_only=True)
        vis = {
            r: np.asarray(vertex_lamp_visibility(images, vj, fj, ring_faces(f, v.shape[0], r), lift, margin))
            for r in (base, wide)
        }
        args = (images, vj, fj, origins, jnp.asarray(nrm), jnp.float32(margin))
        amb = np.asarray(_own_exact._ambiguous(*args, _own_exact.TILE, 0, jnp.float32(_own_exact.AHEAD))[1])
        occluded = np.maximum(nrm @ np.asarray(dirs).T, 0.0) * np.asarray(w)  # cos·w per pair
        y = np.asarray(sh_basis(dirs, BANDS))
        cases = (
            (f"images {grid[0]} x {grid[1]} at {res}², {base} rings (the default)", vis[base]),
            (f"every pair against {wide} rings", vis[wide]),
            (f"the ambiguous pairs against {wide} rings", np.where(amb, vis[wide], vis[base])),
        )
        rows = {}
        for label, vv in cases:
            rows[label] = _transfer_errors(exact_cos - ((1.0 - vv) * occluded) @ y, light, fine_e)
            print(
                f"  {name} {label:52s} rmse {rows[label]['rel_rmse_pct']:.2f} %"
                f"  max {rows[label]['max_rel_err_pct']:.2f} %"
            )
        changed = vis[wide] != vis[base]
        out[name] = {
            "vertices": int(v.shape[0]),
            "ambiguous_pairs": int(amb.sum()),
            "changed_pairs": int(changed.sum()),
            "changed_ambiguous_pairs": int((changed & amb).sum()),
            "quadratures": rows,
        }
    return out


def lamps(name: str = "bunny_animated_last") -> dict:
    """The plane's errors with the lamps' visibility by exact rays (point lamps, no images)."""
    _, v, f, _ = _pose(name)
    vj, fj = jnp.asarray(v), jnp.asarray(f)

    def exact(images, points, lamps=slice(None), spread=None):
        d = images.directions[lamps].astype(points.dtype)
        return 1.0 - ray_fan_any_hit(points, d, vj, fj, t_min=1e-4).astype(points.dtype)

    out = {}
    for label, over, patched in (
        ("images (the default)", {}, False),
        ("exact, 64 lamps", {}, True),
        ("exact, 256 lamps", {"environment_lights": 256}, True),
        ("exact, 1024 lamps", {"environment_lights": 1024}, True),
        (
            "exact, 1024 lamps, split at 0.1 x mean",
            {"environment_lights": 1024, "environment_threshold": 0.1},
            True,
        ),
    ):
        scene, frame, sphere_path, ref, n_plane = _default_scene(name, over)
        jax.clear_caches()  # the renderer's jitted stages look the lamp lookup up when traced
        original = scene_mod.lamp_visibility
        scene_mod.lamp_visibility = exact if patched else original
        try:
            approx, _, _ = models.timed(scene, frame, sphere_path, 1)
        finally:
            scene_mod.lamp_visibility = original
        e = models.errors(approx, ref, n_plane)
        mean = float(np.mean(ref["mean"]))
        err = np.abs(approx - ref["mean"]).max(1)[:n_plane] / mean
        out[label] = {
            "plane_rel_rmse_pct": e["plane_rel_rmse_pct"],
            "max_rel_err_pct": e["max_rel_err_pct"],
            "plane_largest": [[int(i), round(100 * float(err[i]), 2)] for i in np.argsort(-err)[:4]],
        }
        print(
            f"  {label:40s} plane rmse {e['plane_rel_rmse_pct']:.2f} %",
            f"largest on the plane {out[label]['plane_largest']}",
        )
    return out


def _map_rays(env, sub: int):
    """Directions (M, 3), radiance (M, 3) and solid angles (M,) of a lat-long map's pixels, each
    sampled ``sub`` × ``sub`` (uniform in cos θ and in φ within the pixel)."""
    img = np.asarray(env.image, np.float64) * np.asarray(env.radiance, np.float64)
    h, w = img.shape[:2]
    ce = np.cos(np.pi * np.arange(h + 1) / h)
    at = (np.arange(sub) + 0.5) / sub
    cz = ce[:-1, None] + (ce[1:, None] - ce[:-1, None]) * at[None, :]  # (H, S)
    phi = 2 * np.pi * (np.arange(w)[:, None] + at[None, :]) / w  # (W, S)
    st = np.sqrt(np.maximum(1 - cz**2, 0.0))[:, :, None, None]
    d = np.stack(
        np.broadcast_arrays(
            st * np.cos(phi)[None, None], cz[:, :, None, None], -st * np.sin(phi)[None, None]
        ),
        -1,
    ).reshape(-1, 3)
    omega = (2 * np.pi / w) * (ce[:-1] - ce[1:]) / sub**2
    radiance = np.broadcast_to(img[:, None, :, None, :], (h, sub, w, sub, 3)).reshape(-1, 3)
    weight = np.broadcast_to(omega[:, None, None, None], (h, sub, w, sub)).reshape(-1)
    return d, radiance, weight


def pixels(name: str = "bunny_animated_last", receivers=(911, 592)) -> dict:
    """The plane's irradiance at ``receivers`` from the map by exact rays over its sub-sampled
    pixels, and the bright part's by point lamps against its pixels (module docstring)."""
    from jshadow.envlights import split_environment

    scene, frame, _, ref, _ = _default_scene(name)
    _, v, f, lift = _pose(name)
    vj, fj = jnp.asarray(v), jnp.asarray(f)
    pts, nrm = (np.asarray(x) for x in receivers_at(scene, frame))
    mean = float(np.mean(ref["mean"]))
    out = {"mean_irradiance": mean, "receivers": {}}

    def free(o, d):
        hit = ray_fan_any_hit(jnp.asarray(o, jnp.float32), jnp.asarray(d, jnp.float32), vj, fj, t_min=1e-4)
        return ~np.asarray(hit)

    for r in receivers:
        p, n = pts[r], nrm[r]
        o = p + lift * n
        row = {"reference": float(ref["mean"][r, 1]), "reference_stderr": float(ref["stderr"][r, 1])}
        for sub in (1, 2, 4):  # the last one's rays are kept for the lamps below
            d, rad, wt = _map_rays(scene.environment, sub)
            c = d @ n
            up = c > 0
            vis = free(o, d[up])
            e = float((vis * c[up] * wt[up] * rad[up, 1]).sum())
            row[f"map_{sub}x{sub}_pct"] = 100 * (e - row["reference"]) / mean
        for count in (64, 256, 1024):
            rest, lights = split_environment(scene.environment, count, 2.0)
            rest_rad = _map_rays(rest, 4)[1]
            bright = rad[up, 1] - rest_rad[up, 1]
            e_true = float((vis * c[up] * wt[up] * bright).sum())
            e_open = float((c[up] * wt[up] * bright).sum())
            ld, le = np.asarray(lights.directions, np.float64), np.asarray(lights.energy, np.float64)[:, 1]
            lc = np.maximum(ld @ n, 0.0)
            frac = float((free(o, ld) * lc * le).sum() / max((lc * le).sum(), 1e-300))
            row[f"points_{count}_pct"] = 100 * (e_open * frac - e_true) / mean
        out["receivers"][str(r)] = row
        print(f"  receiver {r}: " + ", ".join(f"{k} {x:+.2f}" for k, x in row.items() if k.endswith("_pct")))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parts = ["worst", "transfer", "rings", "lamps", "pixels"]
    ap.add_argument("--parts", nargs="+", choices=parts, default=parts)
    args = ap.parse_args()
    result = json.loads(OUT.read_text()) if OUT.exists() else {}
    stamp = {"git": git_state(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
    result.update(stamp)
    result.setdefault("part_runs", {}).update({part: stamp for part in args.parts})
    if "worst" in args.parts:
        result["worst"] = {}
        for name in SCENES:
            result["worst"][name] = worst(name)
            w = result["worst"][name]
            top = ", ".join(f"{x['where']} {x['err_pct']:+.1f}" for x in w["largest"][:4])
            print(
                f"{name}: {top}; over 5 %: plane {w['over_5pct_plane']}, vertices {w['over_5pct_vertices']}"
            )
    if "transfer" in args.parts:
        print("transfer of spot_self_sky_bend_last's own vertices under its sky:")
        result["transfer"] = transfer()
    if "rings" in args.parts:
        print("the bending meshes' transfer with the ambiguous pairs' near faces widened:")
        result["rings"] = rings()
    if "lamps" in args.parts:
        print("the animated bunny's plane with exact lamp visibility:")
        result["lamps"] = lamps()
    if "pixels" in args.parts:
        print("the animated bunny's plane against the map's pixels by exact rays (% of the mean):")
        result["pixels"] = pixels()
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps(result, indent=1))
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
