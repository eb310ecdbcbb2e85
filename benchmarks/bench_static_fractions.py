"""Re-shaded frames of static scenes: the visible fractions made once, and read out of the
field's table with the image terms as an offset, against the fractions made every frame.

    python benchmarks/bench_static_fractions.py [--frames 21]

For ``spot_sunset`` and ``bunny_studio`` (static meshes; their default shadows the sphere light and
the map's lamps through the occlusion images), three :class:`jshadow.Renderer` in one process:
``every``, the general path with each frame's shading making the fractions again (the behaviour
before; ``static_readout=False`` and ``_fractions`` returning None); ``once``, the general path
with the fractions made once (``static_readout=False``); ``default``, the renderer's default, which
also reads the frame out of the field's table and adds the image terms as a constant offset
(``Readout.offset``). Each renders frame 0 twice (compile, preparation), then ``--frames`` frames
each, alternating; medians of ``total_ms``, and the largest difference from ``every``'s irradiance
over its maximum.
"""

from __future__ import annotations

import argparse
import pathlib

import numpy as np

from jshadow.config import build_scene, load_config
from jshadow.runner import Renderer

ROOT = pathlib.Path(__file__).resolve().parents[1]
CONFIGS = ["configs/spot_sunset.toml", "configs/bunny_studio.toml"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=21)
    args = ap.parse_args()
    for cfg in CONFIGS:
        scene = build_scene(load_config(ROOT / cfg))
        renderers = {
            "every": Renderer(scene, static_readout=False),
            "once": Renderer(scene, static_readout=False),
            "default": Renderer(scene),
        }
        renderers["every"]._fractions = lambda own, images: None  # made with each frame's shading
        out = {k: r.frame(0)[0] for k, r in renderers.items()}
        for r in renderers.values():
            r.frame(0)
        ref = np.asarray(out["every"].irradiance)
        times = {k: [] for k in renderers}
        for _ in range(args.frames):
            for k, r in renderers.items():
                times[k].append(r.frame(0)[1]["total_ms"])
        med = {k: float(np.median(v)) for k, v in times.items()}
        diff = {
            k: float(np.abs(np.asarray(out[k].irradiance) - ref).max() / np.abs(ref).max()) for k in ("once",)
        }
        last = np.asarray(renderers["default"].frame(0)[0].irradiance)  # a read-out frame
        diff["default"] = float(np.abs(last - ref).max() / np.abs(ref).max())
        print(
            f"{cfg}: fractions every frame {med['every']:.2f} ms, once {med['once']:.2f} ms "
            f"({med['once'] / med['every']:.2f}x), read out with the image offset {med['default']:.2f} ms "
            f"({med['default'] / med['every']:.2f}x; read out {renderers['default'].readout_frames} frames); "
            f"largest difference {diff['once']:.1e} / {diff['default']:.1e} of the maximum",
            flush=True,
        )


if __name__ == "__main__":
    main()
