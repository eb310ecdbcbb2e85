"""Re-shaded frames of static scenes with the visible fractions made once, against made every frame.

    python benchmarks/bench_static_fractions.py [--frames 21]

For ``spot_sunset`` and ``bunny_studio`` (static meshes; their default shadows the sphere light and
the map's lamps through the occlusion images), two :class:`jshadow.Renderer` in one process: the
default, which makes the receivers' visible fractions once (``Renderer._fractions``), and one whose
``_fractions`` returns None, so that each frame's shading makes them again (the behaviour before).
Both render frame 0 twice (compile), then ``--frames`` frames each, alternating; medians of
``total_ms``, and the largest difference of the two renderers' irradiance over its maximum.
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
        once, every = Renderer(scene), Renderer(scene)
        every._fractions = lambda own, images: None  # made with each frame's shading
        a, _ = once.frame(0)
        b, _ = every.frame(0)
        once.frame(0)
        every.frame(0)
        ea, eb = np.asarray(a.irradiance), np.asarray(b.irradiance)
        diff = float(np.abs(ea - eb).max() / np.abs(eb).max())
        ta, tb = [], []
        for _ in range(args.frames):
            ta.append(once.frame(0)[1]["total_ms"])
            tb.append(every.frame(0)[1]["total_ms"])
        ma, mb = float(np.median(ta)), float(np.median(tb))
        print(
            f"{cfg}: made once {ma:.2f} ms, every frame {mb:.2f} ms ({ma / mb:.2f}x); "
            f"largest difference {diff:.1e} of the maximum",
            flush=True,
        )


if __name__ == "__main__":
    main()
