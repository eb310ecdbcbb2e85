"""Where one frame's shading call spends its time: XLA's kernels per call, from a profiler trace.

    python benchmarks/profile_shading.py configs/airplane_bend.toml --resolution 4 128 [--frames 20]

For each plane resolution: a fresh :class:`jshadow.Renderer`, a warm-up, then ``--frames`` frames
under ``jax.profiler.trace``. The trace's events inside the one-call shading (from the start of
``Renderer._shade_once`` to the end of its frame) are summed per name and divided by the frame
count: the compiled kernels (fusions, GEMMs as ``ynn_fusion``/``dot``), the number of kernels per
call, and the host-side dispatch. A small resolution shows the fixed per-frame cost (kernels that
do not scale with the receivers, and the per-kernel overhead); a large one the per-receiver work.
Profiling adds overhead, so compare the rows with each other, not with ``bench_render.py``.
Kernels are named by XLA; ``--dump DIR`` also writes the optimised HLO (``XLA_FLAGS
--xla_dump_to``) to look a name up.
"""

from __future__ import annotations

import argparse
import collections
import glob
import gzip
import json
import os
import pathlib
import sys
import tempfile
import tomllib


def _parse(argv):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("config", type=pathlib.Path)
    p.add_argument("--resolution", type=int, nargs="+", default=[4, 128], help="plane resolutions")
    p.add_argument("--frames", type=int, default=20)
    p.add_argument("--top", type=int, default=12, help="kernels listed per resolution")
    p.add_argument("--dump", type=pathlib.Path, default=None, help="write the optimised HLO here")
    return p.parse_args(argv)


_HOST = ("Thunk", "PjRt", "Pjit", "Slinky", "ParseArguments", "Handle ", "Allocate", "PythonRef")


def _is_host(name: str) -> bool:
    """Python frames (``$file:line``), the runtime's own events and the ends of async kernels."""
    return name.startswith(("$", "end:")) or any(h in name for h in _HOST)


def _events(trace_dir):
    (path,) = glob.glob(str(pathlib.Path(trace_dir) / "**" / "*.trace.json.gz"), recursive=True)
    with gzip.open(path) as fh:
        return [e for e in json.load(fh)["traceEvents"] if e.get("ph") == "X"]


def summarise(events, frames: int) -> dict:
    """Per-call sums of the events inside each shading window (start of ``_shade_once`` to the end
    of its ``frame``)."""
    starts = sorted(e["ts"] for e in events if e["name"].endswith("_shade_once"))
    spans = sorted((e["ts"], e["ts"] + e["dur"]) for e in events if e["name"].endswith(" frame"))
    windows = [(s, min(b for a, b in spans if a <= s <= b)) for s in starts]
    if len(windows) != frames:
        raise RuntimeError(f"expected {frames} shading calls in the trace, found {len(windows)}")
    total, count = collections.Counter(), collections.Counter()
    for e in events:
        for a, b in windows:
            if e["ts"] >= a and e["ts"] + e["dur"] <= b:
                total[e["name"]] += e["dur"]
                count[e["name"]] += 1
                break
    kernels = {k: v / frames for k, v in total.items() if not _is_host(k)}
    dispatch = [v / frames for k, v in total.items() if k.endswith("_shade_once")]
    return {
        "window_us": sum(b - a for a, b in windows) / frames,
        "dispatch_us": dispatch[0] if dispatch else float("nan"),
        "kernels_per_call": sum(count[k] for k in kernels) / frames,
        "kernel_us": sum(kernels.values()),
        "kernels": dict(sorted(kernels.items(), key=lambda kv: -kv[1])),
    }


def main(argv=None) -> int:
    args = _parse(argv)
    if args.dump is not None:
        os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} --xla_dump_to={args.dump}".strip()
    import jax

    sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))
    from jshadow import Renderer
    from jshadow.config import build_scene, config_from_dict

    for res in args.resolution:
        d = tomllib.loads(args.config.read_text())
        d["receiver"]["resolution"] = [res, res]
        d.setdefault("method", {}).update(light_visibility="sh", environment_lights=0)  # the n-band path
        scene = build_scene(config_from_dict(d, source=str(args.config), root=args.config.parent))
        rend = Renderer(scene)
        out, _ = rend.frame(0)
        frame = 1 % max(scene.n_frames, 1)
        for _ in range(5):
            rend.frame(frame)
        with tempfile.TemporaryDirectory() as tmp:
            with jax.profiler.trace(tmp, create_perfetto_trace=True):
                for _ in range(args.frames):
                    rend.frame(frame)
            s = summarise(_events(tmp), args.frames)
        print(
            f"{args.config.stem} at {res}² ({out.points.shape[0]} receivers): shading window "
            f"{s['window_us']:.0f} µs, dispatch {s['dispatch_us']:.0f} µs, "
            f"{s['kernels_per_call']:.0f} kernels per call taking {s['kernel_us']:.0f} µs"
        )
        for name, us in list(s["kernels"].items())[: args.top]:
            print(f"  {us:8.1f} µs  {name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
