"""Figs. 1 and 3 of the deformable-shadow-fields paper: true visibility against the shrinking
approximation, seen from receivers at several distances.

An occluder (default: the bunny, normalised to its unit bounding sphere at the origin) is looked at
from the direction ``u`` (θ, φ about world +z, the BSV convention of
:mod:`jshadow.visibility._frames`; default the side view u = +x). The base visibility V_R is cast
from the shell point ``R·u`` (R = ``--shell`` · r; 1 = the paper), and for each receiver distance d
(default 1.2, 2, 4 r) along the same direction, in the same local frame (+z toward the centre):

1. **true** V_d: rays cast from ``d·u`` (binary; Fig. 1, top row);
2. **shrunk** ``V_R(f_{1/k}(θ), φ)`` with k = R/d: the base visibility seen through the paper's
   square-silhouette rescaling (binary; Fig. 1, bottom row; DESIGN.md §2 for the f_k⁻¹);
3. **true, SH**: V_d projected onto n bands (what an exact method would give at n bands);
4. **M_k · S_R**: the base visibility's n-band SH extrapolated with the M_k matrix (Fig. 3; the
   method's visibility at that receiver before BSV interpolation and rotation);
5. the same with the base visibility and M_k in n + 1 bands, truncated to n afterwards (the
   library's ``bsv_bands`` default).

Pictures are azimuthal-equidistant views of the local hemisphere facing the occluder (centre of a
disk = local +z = toward the centre, rim = 90°). Numbers per distance: the solid angle where the
binary true and shrunk visibilities disagree, relative to the true occluded solid angle, and the
L² error of the extrapolated SH against the SH-truncated truth, relative to the L² norm of the
SH-truncated true occlusion, and the L² truncation error of the true visibility relative to its
occlusion's L² norm (both from a 64 × 128 Gauss–Legendre × uniform-φ sphere quadrature).

Usage (repository root, project environment active)::

    python experiments/shrink_pictures.py [--model bunny] [--distances 1.2 2 4] [--bands 4]

Writes ``experiments/figures/shrink_<model>[_shell<R>].png`` and
``experiments/results/shrink_pictures.json`` (one entry per model/shell, merged with the file).
``--rescale sphere`` uses the concentric-sphere rescaling of :mod:`jshadow.scaling` instead of the
paper's square-silhouette f_k (suffix ``_sphere``).
"""

from __future__ import annotations

import argparse
import json
import math

import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from _common import FIGURES, RESULTS, ROOT, machine, unit_mesh  # noqa: E402

from jshadow.scaling import f_k, mk_matrix  # noqa: E402
from jshadow.sh import sh_basis  # noqa: E402
from jshadow.visibility import bsv_frames, ray_fan_any_hit  # noqa: E402


def local_dirs(theta, phi):
    st = np.sin(theta)
    return np.stack([st * np.cos(phi), st * np.sin(phi), np.cos(theta)], axis=-1)


def sphere_quadrature(nt: int = 64, nphi: int = 128):
    """Gauss–Legendre in cos θ × uniform φ over the whole sphere: (θ (K,), φ (K,), w (K,)), Σw = 4π."""
    x, w = np.polynomial.legendre.leggauss(nt)
    theta = np.arccos(x)
    phi = (np.arange(nphi) + 0.5) * (2 * math.pi / nphi)
    tt, pp = np.meshgrid(theta, phi, indexing="ij")
    ww = np.repeat(w[:, None] * (2 * math.pi / nphi), nphi, axis=1)
    return tt.ravel(), pp.ravel(), ww.ravel()


def disk_pixels(size: int):
    """Azimuthal-equidistant image of the hemisphere θ ≤ π/2: (θ, φ, inside) of size × size pixels."""
    c = (np.arange(size) + 0.5) / size * 2.0 - 1.0
    xx, yy = np.meshgrid(c, -c)
    rho = np.hypot(xx, yy)
    return rho * (math.pi / 2), np.arctan2(yy, xx), rho <= 1.0


def cast(vertices, faces, origin, frame, theta, phi):
    """Visibility (1 = free) from ``origin`` along local directions (θ, φ) of ``frame``."""
    world = local_dirs(theta, phi) @ frame.T
    hit = ray_fan_any_hit(
        jnp.asarray(origin[None], jnp.float32), jnp.asarray(world[None], jnp.float32), vertices, faces
    )
    return 1.0 - np.asarray(hit[0], np.float64)


def study(
    model: str, direction, distances, shell: float, n: int, size: int, rescale: str = "paper"
) -> tuple[dict, dict]:
    vertices, faces = unit_mesh(model)
    u, frame = (np.asarray(a, np.float64) for a in bsv_frames(*direction))
    qt, qp, qw = sphere_quadrature()
    y_q = np.asarray(sh_basis(jnp.asarray(local_dirs(qt, qp)), n), np.float64)  # (K, n²)
    pt, pp, inside = disk_pixels(size)
    y_img = np.asarray(sh_basis(jnp.asarray(local_dirs(pt, pp).reshape(-1, 3)), n), np.float64)
    s_unit = np.zeros(n * n)
    s_unit[0] = math.sqrt(4 * math.pi)
    base_q = cast(vertices, faces, shell * u, frame, qt, qp)
    s_base = y_q.T @ (qw * base_q)
    y_q1 = np.asarray(sh_basis(jnp.asarray(local_dirs(qt, qp)), n + 1), np.float64)
    s_base1 = y_q1.T @ (qw * base_q)  # n + 1 bands: extrapolated first, truncated after
    rows, images = [], {}
    for d in distances:
        k = shell / d
        true_q = cast(vertices, faces, d * u, frame, qt, qp)
        warp_q = np.asarray(f_k(jnp.asarray(qt), jnp.asarray(1.0 / k), rescale), np.float64)
        shrunk_q = cast(vertices, faces, shell * u, frame, warp_q, qp)
        s_true = y_q.T @ (qw * true_q)
        s_mk = mk_matrix(k, n, model=rescale) @ s_base
        s_mk1 = (mk_matrix(k, n + 1, model=rescale) @ s_base1)[: n * n]
        occ_true = np.sum(qw * (1.0 - true_q))
        occ_norm = math.sqrt(np.sum(qw * (1.0 - true_q) ** 2))
        rows.append(
            {
                "d_over_r": d,
                "k": k,
                "true_occluded_sr": float(occ_true),
                "shrunk_occluded_sr": float(np.sum(qw * (1.0 - shrunk_q))),
                "binary_mismatch_rel": float(np.sum(qw * np.abs(true_q - shrunk_q)) / occ_true),
                "sh_l2_err_rel": float(np.linalg.norm(s_mk - s_true) / np.linalg.norm(s_unit - s_true)),
                "sh_l2_err_rel_extra_band": float(
                    np.linalg.norm(s_mk1 - s_true) / np.linalg.norm(s_unit - s_true)
                ),
                "sh_truncation_l2_rel": float(
                    math.sqrt(max(np.sum(qw * (true_q - y_q @ s_true) ** 2), 0.0)) / occ_norm
                ),
            }
        )
        warp_img = np.asarray(f_k(jnp.asarray(pt.ravel()), jnp.asarray(1.0 / k), rescale), np.float64)
        images[d] = [
            cast(vertices, faces, d * u, frame, pt.ravel(), pp.ravel()),
            cast(vertices, faces, shell * u, frame, warp_img, pp.ravel()),
            y_img @ s_true,
            y_img @ s_mk,
            y_img @ s_mk1,
        ]
        images[d] = [np.where(inside, im.reshape(size, size), np.nan) for im in images[d]]
    base_img = np.where(
        inside, cast(vertices, faces, shell * u, frame, pt.ravel(), pp.ravel()).reshape(size, size), np.nan
    )
    return {"rows": rows, "base_img": base_img}, images


def figure(model, shell, n, out, images, path, rescale="paper"):
    cols = [
        "true $V_d$",
        r"shrunk $V_R(f_{1/k}(\theta), \phi)$",
        f"true, {n} bands",
        r"$M_k S_R$",
        f"$M_k S_R$ in {n + 1} bands, cut to {n}",
    ]
    ds = list(images)
    fig, axes = plt.subplots(len(ds), 5, figsize=(9.0, 1.9 * len(ds) + 0.4), dpi=100)
    cmap = plt.get_cmap("gray").copy()
    cmap.set_bad("white")
    for i, d in enumerate(ds):
        row = out["rows"][i]
        for j, im in enumerate(images[d]):
            ax = axes[i, j]
            ax.imshow(im, cmap=cmap, vmin=-0.15, vmax=1.15, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(cols[j], fontsize=8)
        axes[i, 0].set_ylabel(f"d = {d:g} r\n(k = {row['k']:.2f})", fontsize=8)
        axes[i, 1].set_xlabel(f"mismatch {100 * row['binary_mismatch_rel']:.0f} %", fontsize=7)
        axes[i, 3].set_xlabel(f"L² err {100 * row['sh_l2_err_rel']:.0f} %", fontsize=7)
        axes[i, 4].set_xlabel(f"L² err {100 * row['sh_l2_err_rel_extra_band']:.0f} %", fontsize=7)
        axes[i, 2].set_xlabel(f"trunc. {100 * row['sh_truncation_l2_rel']:.0f} %", fontsize=7)
    fig.suptitle(
        f"{model}: visibility seen from d, base shell R = {shell:g} r, {rescale} rescaling "
        "(black = occluded)",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="bunny", help="bunny_small | bunny | spot | airplane | egg")
    ap.add_argument("--distances", type=float, nargs="+", default=[1.2, 2.0, 4.0], help="d / r")
    ap.add_argument("--shell", type=float, default=1.0, help="base shell R / r (1 = the paper)")
    ap.add_argument("--direction", type=float, nargs=2, default=[math.pi / 2, 0.0], help="θ φ (radians)")
    ap.add_argument("--bands", type=int, default=4)
    ap.add_argument(
        "--rescale", default="paper", choices=("paper", "sphere"), help="f_k model (jshadow.scaling.MODELS)"
    )
    ap.add_argument("--size", type=int, default=96, help="pixels per picture side")
    args = ap.parse_args()
    if any(d < args.shell for d in args.distances):
        ap.error("--distances must be >= --shell (the shrinking approximation extrapolates outward)")
    out, images = study(
        args.model, tuple(args.direction), args.distances, args.shell, args.bands, args.size, args.rescale
    )
    suffix = ("" if args.shell == 1.0 else f"_shell{args.shell:g}") + (
        "" if args.rescale == "paper" else f"_{args.rescale}"
    )
    png = FIGURES / f"shrink_{args.model}{suffix}.png"
    figure(args.model, args.shell, args.bands, out, images, png, args.rescale)
    for r in out["rows"]:
        print(
            f"{args.model} R={args.shell:g} d={r['d_over_r']:g}: binary mismatch "
            f"{100 * r['binary_mismatch_rel']:.1f} %, SH L2 err {100 * r['sh_l2_err_rel']:.1f} % "
            f"(n + 1 bands: {100 * r['sh_l2_err_rel_extra_band']:.1f} %; "
            f"truncation alone {100 * r['sh_truncation_l2_rel']:.1f} %)"
        )
    path = RESULTS / "shrink_pictures.json"
    data = json.loads(path.read_text()) if path.exists() else {}
    data[f"{args.model}{suffix}"] = {
        "settings": vars(args),
        "rows": out["rows"],
        "figure": str(png.relative_to(ROOT)),
        "machine": machine(),
    }
    path.write_text(json.dumps(data, indent=2))


if __name__ == "__main__":
    main()
