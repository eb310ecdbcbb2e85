"""Projected spherical caps (Peters & Dachsbacher 2019): the density bound and the variance gain.

1. The supplement's Fig. 2: the worst max/min density ratio of the CLIP_BELOW warp as a function of
   the distance to the light centre in light radii (1/r_y), analytically (Eq. 4, maximised over the
   elevations of the clipped-below case) and measured from samples at a few distances; plus the
   supplement's monotone variant (max over all r_y below a threshold).
2. Variance at equal sample count of the estimator of the unoccluded ∫_cap max(0, n·ω) dω:
   projected caps vs uniform cone sampling, relative standard deviation per sample, against the
   elevation of the light centre (caps above, straddling and mostly below the horizon).

Run: ``python experiments/projected_caps.py`` (float64, about a minute on 2 cores). Writes
``experiments/figures/projected_caps_bound.png``, ``projected_caps_variance.png`` and
``projected_caps.json``.
"""

from __future__ import annotations

import json
import pathlib

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import matplotlib  # noqa: E402
import numpy as np  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from jshadow.sampling import (  # noqa: E402
    projected_cap_density_bound,
    projected_solid_angle,
    sample_projected_cap,
    sample_sphere_cone,
)

OUT = pathlib.Path(__file__).resolve().parent / "figures"
N_SAMPLES = 1 << 15


def config(dist_over_r, elev):
    """Normal +z, light of radius 1 at distance dist_over_r and elevation elev (radians)."""
    n = jnp.asarray([0.0, 0.0, 1.0])
    c = dist_over_r * jnp.stack([jnp.cos(elev), jnp.zeros_like(elev), jnp.sin(elev)], -1)
    return n, c


def bound_curve(dists, n_elev=400):
    """max over clipped-below elevations of the Eq. 4 bound, per distance."""
    out = []
    for d in dists:
        alpha = np.arcsin(1.0 / d)
        elev = -alpha * np.linspace(1e-4, 1 - 1e-4, n_elev)
        n, c = config(d, jnp.asarray(elev))
        out.append(float(jnp.max(projected_cap_density_bound(n, c, 1.0))))
    return np.array(out)


def measured_ratio(d, u, n_elev=24):
    alpha = np.arcsin(1.0 / d)
    worst = 0.0
    for e in -alpha * np.linspace(0.02, 0.98, n_elev):
        n, c = config(d, jnp.asarray(e))
        p = np.asarray(sample_projected_cap(u, n, c, 1.0).pdf_proj)
        worst = max(worst, float(p.max() / p.min()))
    return worst


def rel_std(samples_inv_pdf):
    x = np.asarray(samples_inv_pdf)
    return float(x.std() / x.mean()) if x.mean() > 0 else float("nan")


def variance_curves(u, dists=(3.0, 1.2), n_elev=41):
    rows = []
    for d in dists:
        alpha = np.arcsin(1.0 / d)
        for e in np.linspace(-alpha * 0.97, np.pi / 2 * 0.98, n_elev):
            n, c = config(d, jnp.asarray(e))
            ps = sample_projected_cap(u, n, c, 1.0)
            est_ps = np.where(np.asarray(ps.valid), 1.0 / np.asarray(ps.pdf_proj), 0.0)
            cs = sample_sphere_cone(u, c, 1.0)
            cos = np.maximum(np.asarray(cs.direction) @ np.asarray(n), 0.0)
            est_cone = cos / np.asarray(cs.pdf)
            omega = float(projected_solid_angle(n, c, 1.0))
            case = "above" if np.sin(e) > 1.0 / d else ("straddling" if e > 0 else "mostly below")
            rows.append(
                {
                    "dist_over_r": d,
                    "elevation_deg": float(np.degrees(e)),
                    "case": case,
                    "omega_proj": omega,
                    "rel_std_projected_caps": rel_std(est_ps),
                    "rel_std_cone": rel_std(est_cone),
                    "mean_projected_caps": float(est_ps.mean()),
                    "mean_cone": float(est_cone.mean()),
                }
            )
    return rows


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    u = jnp.asarray(np.random.default_rng(0).random((N_SAMPLES, 2)))
    u = u.at[0].set(jnp.asarray([1.0 - 1e-12, 0.5]))  # include the top point, where the max sits

    dists = np.geomspace(1.02, 10.0, 60)
    curve = bound_curve(dists)
    monotone = np.maximum.accumulate(curve[::-1])[::-1]  # max over all r_y ≤ 1/d (supplement)
    probe = [1.1, 1.5, 2.0, 3.0, 6.0]
    measured = [measured_ratio(d, u) for d in probe]

    fig, ax = plt.subplots(figsize=(5.5, 3.6), dpi=110)
    ax.plot(dists, curve, label="Eq. 4 bound, max over elevations")
    ax.plot(dists, monotone, "--", label="max over all farther lights (Fig. 2 variant)")
    ax.plot(probe, measured, "o", label=f"measured max/min p⊥ ({N_SAMPLES} samples)")
    ax.axhline(np.sqrt(2), color="grey", lw=0.8, ls=":", label="√2")
    ax.set_xscale("log")
    ax.set_xlabel("distance to light centre / light radius  (1/r_y)")
    ax.set_ylabel("max / min density (clipped below)")
    ax.set_ylim(1.0, 3.0)
    ax.legend(fontsize=7)
    ax.set_title("Projected spherical caps: bounded density deviation", fontsize=9)
    fig.tight_layout()
    fig.savefig(OUT / "projected_caps_bound.png")
    plt.close(fig)

    rows = variance_curves(u)
    fig, ax = plt.subplots(figsize=(5.5, 3.6), dpi=110)
    for d, style in ((3.0, "-"), (1.2, "--")):
        sel = [r for r in rows if r["dist_over_r"] == d]
        el = [r["elevation_deg"] for r in sel]
        ax.plot(
            el,
            [max(r["rel_std_projected_caps"], 1e-16) for r in sel],
            style,
            c="C0",
            label=f"projected caps, |c|/r={d}",
        )
        ax.plot(el, [r["rel_std_cone"] for r in sel], style, c="C3", label=f"cone, |c|/r={d}")
    ax.set_yscale("log")
    ax.set_ylim(1e-17, 30)
    ax.axvline(0, color="grey", lw=0.8)
    ax.set_xlabel("elevation of the light centre above the tangent plane (deg)")
    ax.set_ylabel("relative std per sample")
    ax.legend(fontsize=7)
    ax.set_title("Unoccluded sphere light, equal sample count", fontsize=9)
    fig.tight_layout()
    fig.savefig(OUT / "projected_caps_variance.png")
    plt.close(fig)

    summary = {}
    for case in ("above", "straddling", "mostly below"):
        sel = [r for r in rows if r["case"] == case]
        summary[case] = {
            "configs": len(sel),
            "median_rel_std_projected_caps": float(np.median([r["rel_std_projected_caps"] for r in sel])),
            "median_rel_std_cone": float(np.median([r["rel_std_cone"] for r in sel])),
            "fraction_zero_variance_projected_caps": float(
                np.mean([r["rel_std_projected_caps"] <= 1e-12 for r in sel])
            ),
            "median_variance_ratio_cone_over_caps": (
                float(np.median([(r["rel_std_cone"] / r["rel_std_projected_caps"]) ** 2 for r in sel]))
                if all(r["rel_std_projected_caps"] > 1e-12 for r in sel)
                else "caps: zero variance"
            ),
        }
    result = {
        "samples": N_SAMPLES,
        "bound_curve": {
            "dist_over_r": dists.tolist(),
            "max_ratio": curve.tolist(),
            "monotone": monotone.tolist(),
        },
        "measured_max_ratio": dict(zip(map(str, probe), measured, strict=True)),
        "ratio_at_2_radii": float(np.interp(2.0, dists, curve)),
        "variance": rows,
        "variance_summary": summary,
    }
    (OUT / "projected_caps.json").write_text(json.dumps(result, indent=1))
    print(
        json.dumps(
            {k: result[k] for k in ("measured_max_ratio", "ratio_at_2_radii", "variance_summary")}, indent=1
        )
    )


if __name__ == "__main__":
    main()
