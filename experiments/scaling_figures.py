"""Figures and numbers of SH scaling: the paper's Fig. 4 (rescaling curves f_k) and Fig. 6 (sparsity
of M_k for n = 4), the table's interpolation error, and the M_k application benchmark.

Usage (from the repository root, with the project's environment active)::

    python experiments/scaling_figures.py            # figures + experiments/figures/scaling.json
    python experiments/scaling_figures.py --bench    # also time mk_apply for 1e5 receivers

Writes ``experiments/figures/scaling_fk.png``, ``scaling_mk_pattern.png`` and ``scaling.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import pathlib
import platform
import time

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from jshadow.scaling import f_k, mk_apply, mk_interpolate, mk_matrix, mk_pattern, mk_table  # noqa: E402
from jshadow.sh import sh_lm  # noqa: E402

OUT = pathlib.Path(__file__).resolve().parent / "figures"


def fig_fk(out: dict) -> None:
    """Fig. 4: f_k(θ) for several k (paper model solid, sphere model dashed)."""
    theta = np.linspace(0.0, math.pi, 361)
    ks = [0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 4.0]
    fig, ax = plt.subplots(figsize=(4.6, 4.0), dpi=110)
    curves = {}
    for i, k in enumerate(ks):
        col = plt.cm.viridis(i / (len(ks) - 1))
        fp = np.asarray(f_k(jnp.asarray(theta, jnp.float32), k))
        fs = np.asarray(f_k(jnp.asarray(theta, jnp.float32), k, "sphere"))
        ax.plot(np.degrees(theta), np.degrees(fp), color=col, label=f"k = {k}")
        ax.plot(np.degrees(theta), np.degrees(fs), color=col, ls="--", lw=1)
        curves[str(k)] = {
            "paper_deg_at_90": float(np.degrees(fp[180])),
            "sphere_deg_at_90": float(np.degrees(fs[180])),
        }
    ax.axvline(90, color="0.7", lw=0.8)
    ax.set(xlabel="θ on the shell (deg)", ylabel="f_k(θ) (deg)", xlim=(0, 180), ylim=(0, 180))
    ax.set_title("Angular rescaling f_k (solid: paper, dashed: sphere)", fontsize=9)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(OUT / "scaling_fk.png")
    plt.close(fig)
    out["f_k"] = {
        "silhouette_deg_of_a_90deg_shell_silhouette": curves,
        "unit_sphere_seen_from_d2": {
            "paper_deg": float(np.degrees(float(f_k(math.pi / 2, 0.5)))),
            "sphere_model_deg": float(np.degrees(float(f_k(math.pi / 2, 0.5, "sphere")))),
            "true_deg": 30.0,
        },
    }


def fig_pattern(out: dict) -> None:
    """Fig. 6: |M_k| for n = 4 at k = 0.5 with the equal-m positions marked."""
    n, k = 4, 0.5
    m_occ = mk_matrix(k, n, "occlusion")
    m_jac = mk_matrix(k, n, "radiance_jacobian")
    rows, cols = mk_pattern(n)
    fig, axes = plt.subplots(1, 2, figsize=(7.6, 3.9), dpi=110)
    for ax, m, title in [(axes[0], m_occ, "occlusion / radiance"), (axes[1], m_jac, "radiance_jacobian")]:
        ax.imshow(np.abs(m), cmap="Greys", vmin=0, vmax=1.2)
        ax.scatter(cols, rows, marker="x", s=14, color="tab:red", lw=0.8)
        ticks = range(n * n)
        ax.set_xticks(ticks, [f"{sh_lm(i)[0]},{sh_lm(i)[1]}" for i in ticks], rotation=90, fontsize=5)
        ax.set_yticks(ticks, [f"{sh_lm(i)[0]},{sh_lm(i)[1]}" for i in ticks], fontsize=5)
        ax.set_title(f"|M_k|, k = {k}, {title}", fontsize=8)
    fig.suptitle("x: the 44 equal-m positions (41 non-zero: column 0 = e0, or row 0 = e0ᵀ)", fontsize=8)
    fig.tight_layout()
    fig.savefig(OUT / "scaling_mk_pattern.png")
    plt.close(fig)
    out["pattern"] = {
        "n": n,
        "positions": len(rows),
        "nonzero_occlusion": len(mk_pattern(n, "occlusion")[0]),
        "nonzero_radiance_jacobian": len(mk_pattern(n, "radiance_jacobian")[0]),
        "M_k0.5_occlusion": np.round(m_occ, 6).tolist(),
    }


def interpolation_error(out: dict) -> None:
    """Max |M_interp − M_k| at the midpoints (in k) of the default table (16 distances 0.2..8)."""
    t = mk_table(dtype=jnp.float32)
    ks = np.asarray(t.ks, np.float64)
    mids = 0.5 * (ks[:-1] + ks[1:])
    errs = [
        float(np.abs(np.asarray(mk_interpolate(t, jnp.float32(k)), np.float64) - mk_matrix(k)).max())
        for k in mids
    ]
    out["interpolation"] = {
        "table": "n=4, 16 distances geometric in d from 0.2 to 8 shell radii",
        "midpoint_d": [float(1 / k) for k in mids],
        "max_abs_error": errs,
    }


def _dense_apply(table, k, c):
    return jnp.einsum("...ij,...j->...i", mk_interpolate(table, k), c)


def _gather_apply(table, k, c):
    """Interpolation by gathering the two neighbouring table rows per receiver, then sparse products."""
    ks = table.ks.astype(c.dtype)
    vals = table.values.astype(c.dtype)
    kc = jnp.clip(k, ks[0], ks[-1])
    i0 = jnp.clip(jnp.searchsorted(ks, kc, side="right") - 1, 0, ks.shape[0] - 2)
    w = ((kc - ks[i0]) / (ks[i0 + 1] - ks[i0]))[..., None]
    v = vals[i0] * (1.0 - w) + vals[i0 + 1] * w
    acc = [None] * c.shape[-1]
    for e, (i, j) in enumerate(zip(table.rows, table.cols)):
        term = v[..., e] * c[..., j]
        acc[i] = term if acc[i] is None else acc[i] + term
    return jnp.stack(acc, axis=-1)


def _time(fn, *args, reps=7):
    t0 = time.perf_counter()
    fn(*args).block_until_ready()
    compile_s = time.perf_counter() - t0
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn(*args).block_until_ready()
        ts.append(time.perf_counter() - t0)
    return compile_s, float(np.median(ts))


def bench(out: dict, num: int = 100_000) -> None:
    t = mk_table(dtype=jnp.float32)
    rng = np.random.default_rng(0)
    k = jnp.asarray(rng.uniform(0.1, 5.0, num), jnp.float32)
    c = jnp.asarray(rng.normal(size=(num, 16)), jnp.float32)
    variants = {
        "mk_apply (hat-weight matmul + sparse)": jax.jit(lambda k, c: mk_apply(t, k, c)),
        "gathered table rows + sparse": jax.jit(lambda k, c: _gather_apply(t, k, c)),
        "dense mk_interpolate + einsum": jax.jit(lambda k, c: _dense_apply(t, k, c)),
    }
    ref = np.asarray(variants["dense mk_interpolate + einsum"](k, c))
    res = {}
    for name, fn in variants.items():
        np.testing.assert_allclose(np.asarray(fn(k, c)), ref, rtol=1e-4, atol=1e-4)
        comp, med = _time(fn, k, c)
        res[name] = {"compile_s": comp, "median_ms": med * 1e3}
        print(f"{name:40s} compile {comp:6.2f} s   median {med * 1e3:8.2f} ms")
    out["bench"] = {
        "receivers": num,
        "n": 4,
        "dtype": "float32",
        "backend": jax.default_backend(),
        "machine": platform.platform(),
        "results": res,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bench", action="store_true", help="also time M_k application for 1e5 receivers")
    args = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    out: dict = {}
    fig_fk(out)
    fig_pattern(out)
    interpolation_error(out)
    if args.bench:
        bench(out)
    (OUT / "scaling.json").write_text(json.dumps(out, indent=1))
    print(json.dumps({k: v for k, v in out.items() if k != "pattern"}, indent=1)[:3000])


if __name__ == "__main__":
    main()
