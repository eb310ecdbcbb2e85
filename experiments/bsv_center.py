"""A deforming occluder's bounding-sphere centre: its placed centre against its box centre per pose.

The BSV of a mesh occluder is sampled on a shell about the centre of a bounding sphere. With
``[method] bsv_center = "box"`` (the paper's choice) that is the deformed mesh's axis-aligned box
centre, recomputed at every pose; a deformation that is not symmetric about the centre moves it
(the shipped airplane's bend by 0.15, a twisted bunny's by 0.11). With ``"placed"`` (the default)
it is the occluder's configured ``center``, where its rest pose's sphere sits, and the radius is
the farthest deformed vertex from it. Only the second lets :class:`jshadow.Renderer` read frames
out of the field's table (:mod:`jshadow.readout`), which needs a centre that stays where it is.

This script measures what the choice costs in accuracy: the scenes of ``experiments/models.py``
whose occluder deforms (the airplane's last bent frame, the twisted airplane under a sky, the
twisted bunny with its own vertices as receivers, the breathing egg, whose centre never moves: a
control), rendered with the default method under each centre against the cached Monte Carlo
references (``experiments/results/refs/<case>.npz``; ``models.py --cases <case>`` computes a
missing one). It also records how far the box centre moves and the two radii.

Usage (repository root, project environment active)::

    python experiments/bsv_center.py

Writes ``experiments/results/bsv_center.json``.
"""

from __future__ import annotations

import json
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import models  # noqa: E402

from jshadow.entities import frame_time  # noqa: E402
from jshadow.geometry import bounding_sphere  # noqa: E402

CASES = ["airplane_bend_last", "twisted_airplane_sky", "bunny_self_sky_twist", "egg_breathing"]
CENTERS = ["box", "placed"]


def main() -> None:
    cases = models._cases()
    out = {"cases": {}, "default_variant": models.DEFAULT_VARIANT}
    t_start = time.perf_counter()
    for name in CASES:
        build, frame, sphere_path, tuned = cases[name]
        base = build(models.VARIANTS["paper"], 32)
        ref = models.reference(name, base, frame, 0.001, 32768)
        n_plane = int(np.prod(base.receivers.grid_shape))
        row = out["cases"][name] = {"frame": frame, "tuned": tuned, "centers": {}}
        for center in CENTERS:
            scene = build({**models.VARIANTS[models.DEFAULT_VARIANT], "bsv_center": center}, 32)
            approx, _, warm = models.timed(scene, frame, sphere_path, runs=2)
            e = models.errors(approx, ref, n_plane)
            e["warm_ms"] = warm
            row["centers"][center] = e
            print(
                f"{name:22s} {center:6s} rmse {e['rel_rmse_pct']:6.3f} %  max {e['max_rel_err_pct']:6.2f} %  "
                f"excess {e['max_excess_over_unoccluded_pct']:5.2f} %",
                flush=True,
            )
        occ = scene.occluders[0]
        v = occ.vertices(jnp.asarray(frame_time(frame, scene.n_frames), occ.unit_vertices.dtype))
        c_box, r_box = bounding_sphere(v)
        row["box_centre_shift"] = float(jnp.linalg.norm(c_box - occ.center))
        row["radius_box"] = float(r_box)
        row["radius_placed"] = float(jnp.max(jnp.linalg.norm(v - occ.center, axis=-1)))
    out["machine"] = dict(jax=jax.__version__, devices=str(jax.devices()))
    out["seconds"] = time.perf_counter() - t_start
    path = models.RESULTS / "bsv_center.json"
    path.write_text(json.dumps(out, indent=1))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
