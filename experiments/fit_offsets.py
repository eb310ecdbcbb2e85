"""Recover free per-vertex offsets of a mesh from several shadows (the fit issue, "Fitting").

Setting (in-file constants below): the egg (subdivision 2, 162 vertices) normalised to its unit
bounding sphere, placed at (0, 1.1, 0) with bounding radius 0.8 and deformed by
:class:`jshadow.geometry.Offsets`. The ground truth is a smooth bump field along the rest normals,
``o_i = Σ_b a_b · exp(−‖x_i − c_b‖² / (2 σ_b²)) · n_i`` (one outward bump on the side, one inward
dent on the other side; units of the bounding radius). Four targets: the 40×40 receiver plane
rendered under a dim constant environment with one sphere light at each of four positions
(:func:`jshadow.optim.plane_radiances` shares the BSV between them). The fit starts from zero
offsets and minimises ``Σ_k relative_mse_k + w · laplacian_penalty(o)`` (uniform Laplacian) with
Adam; the shadow gradient is the silhouette-edge (visibility) gradient of the deformable
shadow-field BSV.

What can and cannot be recovered: a shadow constrains only the part of the surface on a light's
silhouette, and only the displacement across it; offsets tangent to the surface, or on vertices
that lie on no silhouette, are seen by no target and are set by the regulariser alone. The error of
the vertex positions is reported as RMS over all vertices, and separately over the vertices whose
true offset is significant, both relative to the RMS of the true offsets.

Usage (repository root, project environment active)::

    python experiments/fit_offsets.py [--steps N] [--weight W] [--lr LR] [--mode free|normal]
        [--method paper|default|coverage]

``--mode free`` (default) fits the (V, 3) offsets; ``--mode normal`` fits one scalar per vertex
along the rest normal (offsets = h_i · n_i), a prior that removes the unseen tangential freedom.
``--method`` picks the shadow-field method (the recorded fits used the paper's). Writes
``experiments/results/fit_offsets[_normal][_METHOD].json`` and
``experiments/figures/fit_offsets[_normal][_METHOD].png``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import platform
import time

import jax.numpy as jnp
import matplotlib
import numpy as np
import optax

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from jshadow.config import plane_receivers  # noqa: E402
from jshadow.entities import Environment, MeshOccluder, Method, Scene, SphereLight  # noqa: E402
from jshadow.geometry import Offsets, egg, normalize_to_unit_sphere, vertex_normals  # noqa: E402
from jshadow.optim import fit, laplacian_penalty, plane_radiances, relative_mse  # noqa: E402
from jshadow.scene import grow_slots  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]

SUBDIVISIONS = 2  # egg: 162 vertices
CENTER, RADIUS = (0.0, 1.1, 0.0), 0.8
LIGHTS = [(0.5, 3.0, 0.3), (-1.6, 2.8, 0.6), (1.4, 2.7, -1.2), (-0.4, 2.9, -1.6)]  # sphere-light centres
LIGHT_RADIUS, LIGHT_RADIANCE = 0.3, 60.0
ENV_RADIANCE = 0.2
PLANE = dict(size=(4.0, 4.0), resolution=(40, 40))
# (amplitude a, centre direction c, width σ): unit-sphere frame, units of the bounding radius
BUMPS = [(0.15, (1.0, 0.15, 0.2), 0.45), (-0.10, (-0.3, 0.0, -1.0), 0.4)]
STEPS, LEARNING_RATE, WEIGHT = 300, 0.004, 1.0
_SIZES = dict(sh_bands=4, bsv_grid=(8, 12), directions=(16, 16))
METHODS = {
    "paper": lambda: Method.paper(**_SIZES),
    "default": lambda: Method(**_SIZES),
    "coverage": lambda: Method(bsv_images="coverage", **_SIZES),
}


def true_offsets(unit, normals):
    o = np.zeros_like(unit)
    for a, c, s in BUMPS:
        c = np.asarray(c) / np.linalg.norm(c)
        w = np.exp(-np.sum((unit - c) ** 2, -1) / (2 * s * s))
        o += a * w[:, None] * normals
    return o


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=STEPS)
    ap.add_argument("--weight", type=float, default=WEIGHT, help="Laplacian penalty weight w")
    ap.add_argument("--lr", type=float, default=LEARNING_RATE)
    ap.add_argument(
        "--mode",
        choices=("free", "normal"),
        default="free",
        help="free: (V, 3) offsets; normal: one scalar per vertex along the rest normal",
    )
    ap.add_argument(
        "--method",
        choices=tuple(METHODS),
        default="paper",
        help="paper: the paper's method (the recorded fits); default: the default method; coverage: "
        "the default with the BSV projected from coverage images (bsv_images = 'coverage')",
    )
    args = ap.parse_args()

    f32 = jnp.float32
    mesh = egg(SUBDIVISIONS, dtype=f32)
    unit = np.asarray(normalize_to_unit_sphere(mesh.vertices), np.float64)
    faces = np.asarray(mesh.faces)
    normals = np.asarray(vertex_normals(jnp.asarray(unit, f32), jnp.asarray(faces)), np.float64)
    truth = true_offsets(unit, normals)

    method = METHODS[args.method]()
    receivers = plane_receivers(
        jnp.zeros(3, f32), jnp.asarray(PLANE["size"], f32), PLANE["resolution"], jnp.full(3, 0.8, f32)
    )
    light_sets = [
        (
            SphereLight(
                center=jnp.asarray(c, f32),
                radius=jnp.asarray(LIGHT_RADIUS, f32),
                radiance=jnp.full(3, LIGHT_RADIANCE, f32),
            ),
        )
        for c in LIGHTS
    ]
    unit_j, faces_j = jnp.asarray(unit, f32), jnp.asarray(faces, jnp.int32)

    def make_scene(o):
        occ = MeshOccluder(
            unit_vertices=unit_j,
            faces=faces_j,
            center=jnp.asarray(CENTER, f32),
            radius=jnp.asarray(RADIUS, f32),
            deform=Offsets(o),
            name="egg",
        )
        return Scene(
            method=method,
            receivers=receivers,
            occluders=(occ,),
            lights=(),
            environment=Environment(radiance=jnp.full(3, ENV_RADIANCE, f32)),
        )

    target = plane_radiances(make_scene(jnp.asarray(truth, f32)), light_sets)
    k = len(light_sets)

    def shadow_loss(o):
        pred = plane_radiances(make_scene(o), light_sets)
        return sum(relative_mse(pred[i], target[i]) for i in range(k))

    normals_j = jnp.asarray(normals, f32)
    if args.mode == "free":
        init = jnp.zeros_like(unit_j)

        def offsets_of(p):
            return p

    else:  # one scalar per vertex along the rest normal
        init = jnp.zeros(unit_j.shape[0], f32)

        def offsets_of(p):
            return p[:, None] * normals_j

    def loss_fn(p):
        o = offsets_of(p[0])
        return shadow_loss(o) + args.weight * laplacian_penalty(o, faces)

    zero = jnp.zeros_like(unit_j)
    t0 = time.perf_counter()
    res = fit(
        loss_fn,
        [init],
        steps=args.steps,
        optimizer=optax.adam(args.lr),
        keep_history=False,
        on_overflow=lambda p: grow_slots(make_scene(offsets_of(jnp.asarray(p[0])))),
    )
    wall = time.perf_counter() - t0
    final = np.asarray(offsets_of(res.params[0]), np.float64)

    rms_true = float(np.sqrt(np.mean(np.sum(truth**2, -1))))
    big = np.linalg.norm(truth, axis=-1) > 0.2 * np.abs(truth).max()  # where the bumps are

    def rel_rms(o, mask=None):
        d = np.sum((o - truth) ** 2, -1)
        if mask is not None:
            return float(np.sqrt(np.mean(d[mask])) / np.sqrt(np.mean(np.sum(truth[mask] ** 2, -1))))
        return float(np.sqrt(np.mean(d)) / rms_true)

    def normal_rel_rms(o):  # error of the component along the rest normal only
        d = np.sum((o - truth) * normals, -1)
        return float(np.sqrt(np.mean(d**2)) / rms_true)

    loss_before = float(shadow_loss(zero))
    loss_after = float(shadow_loss(jnp.asarray(final, f32)))
    summary = {
        "experiment": "fit_offsets",
        "command": "python experiments/fit_offsets.py"
        + (f" --steps {args.steps}" if args.steps != STEPS else "")
        + (f" --weight {args.weight}" if args.weight != WEIGHT else "")
        + (f" --lr {args.lr}" if args.lr != LEARNING_RATE else "")
        + (f" --mode {args.mode}" if args.mode != "free" else "")
        + (f" --method {args.method}" if args.method != "paper" else ""),
        "mode": args.mode,
        "method": args.method,
        "mesh": f"egg subdivision {SUBDIVISIONS}: {unit.shape[0]} vertices, {faces.shape[0]} faces",
        "lights": LIGHTS,
        "bumps": BUMPS,
        "rms_true_offsets": rms_true,
        "max_true_offset": float(np.linalg.norm(truth, axis=-1).max()),
        "vertices_in_bumps": int(big.sum()),
        "position_rel_rms_before": rel_rms(np.zeros_like(truth)),
        "position_rel_rms_after": rel_rms(final),
        "position_rel_rms_bumps_before": rel_rms(np.zeros_like(truth), big),
        "position_rel_rms_bumps_after": rel_rms(final, big),
        "normal_component_rel_rms_before": normal_rel_rms(np.zeros_like(truth)),
        "normal_component_rel_rms_after": normal_rel_rms(final),
        "shadow_loss_before": loss_before,
        "shadow_loss_after": loss_after,
        "laplacian_weight": args.weight,
        "laplacian": "uniform (umbrella) Laplacian, mean squared norm over vertices",
        "laplacian_penalty_truth": float(laplacian_penalty(jnp.asarray(truth, f32), faces)),
        "laplacian_penalty_after": float(laplacian_penalty(jnp.asarray(final, f32), faces)),
        "steps": args.steps,
        "optimizer": f"adam, learning rate {args.lr}",
        "wall_s": wall,
        "first_step_s": res.first_step_s,
        "ms_per_step": res.ms_per_step,
        "retraced": res.retraced,
        "loss": res.loss,
        "machine": f"{platform.machine()} {platform.processor() or platform.platform()}",
        "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
    }
    suffix = "" if args.mode == "free" else f"_{args.mode}"
    suffix += "" if args.method == "paper" else f"_{args.method}"
    out_json = ROOT / "experiments" / "results" / f"fit_offsets{suffix}.json"
    out_json.write_text(json.dumps(summary, indent=1) + "\n")

    # figure: loss; true vs recovered normal offset per vertex; shading under light 2 before/target/after
    before_img = plane_radiances(make_scene(zero), light_sets)
    after_img = plane_radiances(make_scene(jnp.asarray(final, f32)), light_sets)
    grid = receivers.grid_shape
    fig, ax = plt.subplots(2, 4, figsize=(13, 6.2))
    ax[0, 0].semilogy(res.loss)
    ax[0, 0].set(title="loss (Σ rel. MSE + w·Laplacian)", xlabel="step")
    tn, fn = np.sum(truth * normals, -1), np.sum(final * normals, -1)
    ax[0, 1].scatter(tn, fn, s=6)
    lim = [min(tn.min(), fn.min()), max(tn.max(), fn.max())]
    ax[0, 1].plot(lim, lim, "k--", lw=0.8)
    ax[0, 1].set(title="normal offset per vertex", xlabel="true", ylabel="recovered")
    az = np.arctan2(unit[:, 2], unit[:, 0])
    for a, val, name in ((ax[0, 2], tn, "true"), (ax[0, 3], fn, "recovered")):
        sc = a.scatter(az, unit[:, 1], c=val, s=14, cmap="coolwarm", vmin=-0.15, vmax=0.15)
        a.set(title=f"{name} normal offset", xlabel="azimuth atan2(z, x)", ylabel="y (unit frame)")
    fig.colorbar(sc, ax=ax[0, 3], fraction=0.05)
    li = 1
    imgs = [np.asarray(x[li]).mean(-1).reshape(grid) for x in (before_img, target, after_img)]
    vmax = max(float(i.max()) for i in imgs)
    for a, im, name in zip(ax[1, :3], imgs, ("before", "target", "after"), strict=True):
        a.imshow(im, origin="lower", extent=(-2, 2, -2, 2), cmap="gray", vmin=0, vmax=vmax)
        a.set(title=f"{name} (light {li})", xlabel="x", ylabel="z")
    diff = imgs[2] - imgs[1], imgs[0] - imgs[1]
    m = float(np.abs(diff[1]).max())
    ax[1, 3].imshow(diff[0], origin="lower", extent=(-2, 2, -2, 2), cmap="coolwarm", vmin=-m, vmax=m)
    ax[1, 3].set(title="after − target (scale of before − target)", xlabel="x", ylabel="z")
    fig.tight_layout()
    out_png = ROOT / "experiments" / "figures" / f"fit_offsets{suffix}.png"
    fig.savefig(out_png, dpi=70)
    print(
        f"fit_offsets ({args.mode}): {unit.shape[0]} vertices, {k} lights, w = {args.weight}: "
        f"vertex RMS error / RMS true "
        f"{summary['position_rel_rms_before']:.3f} -> {summary['position_rel_rms_after']:.3f} "
        f"(bump vertices {summary['position_rel_rms_bumps_before']:.3f} -> "
        f"{summary['position_rel_rms_bumps_after']:.3f}; normal component "
        f"{summary['normal_component_rel_rms_before']:.3f} -> "
        f"{summary['normal_component_rel_rms_after']:.3f}); "
        f"shadow loss {loss_before:.3e} -> {loss_after:.3e}; {args.steps} steps, wall {wall:.1f} s "
        f"(first step {res.first_step_s:.1f} s, {res.ms_per_step:.1f} ms/step)"
    )
    print(f"wrote {out_json.relative_to(ROOT)} and {out_png.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
