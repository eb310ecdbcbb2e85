"""Agreement between JAX devices: the same frames and gradients rendered on two machines.

Usage::

    python benchmarks/bench_devices.py save OUT.npz [--precision default highest]
    python benchmarks/bench_devices.py compare REFERENCE.npz OTHER.npz

``save`` renders the middle frame of every shipped config (fit configs excluded) with
:class:`jshadow.Renderer` on JAX's default device, under each ``--precision`` (JAX's
``default_matmul_precision``: on GPUs ``default`` lets float32 matrix products run as TF32, whose
mantissa has 10 bits; ``highest`` keeps full float32), and the vertex gradient of
``L(δ) = Σ w · irradiance`` (``bench_frame_grad.frame_loss``) for ``--gradients`` configs. Arrays are
stored in one npz, with the device's name.

``compare`` prints, per array, the relative RMSE ‖a − b‖ / ‖b‖ and the largest absolute difference
over the largest magnitude of the reference, and the gradients' cosine similarity. The figures say
how far a device's float32 result is from another's; both sides are float32, so neither is exact.
"""

from __future__ import annotations

import argparse
import pathlib
import sys
import time
import tomllib

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
GRADIENTS = ["configs/egg_breathing.toml"]


def _scene(path: str):
    from jshadow.config import build_scene, config_from_dict

    d = tomllib.loads((ROOT / path).read_text())
    d.setdefault("method", {}).update(light_visibility="sh", environment_lights=0)  # the n-band light path
    return build_scene(config_from_dict(d, source=path, root=(ROOT / path).parent))


def _gradient(path: str):
    import jax
    import jax.numpy as jnp
    from bench_frame_grad import frame_loss  # the script's folder is on sys.path

    from jshadow.entities import frame_time

    scene = _scene(path)
    loss = frame_loss(scene, frame_time(scene.n_frames // 2, scene.n_frames))
    return np.asarray(jax.jit(jax.grad(loss))(jnp.zeros_like(scene.occluders[0].unit_vertices)))


def save(out: str, precisions: list[str], gradients: list[str]) -> None:
    import jax

    from jshadow.runner import Renderer

    arrays = {"device": np.array(str(jax.devices()[0]))}
    cfgs = sorted(str(p.relative_to(ROOT)) for p in (ROOT / "configs").glob("*.toml") if "fit" not in p.name)
    for c in cfgs:
        scene = _scene(c)
        for prec in precisions:
            t0 = time.perf_counter()
            with jax.default_matmul_precision(None if prec == "default" else prec):
                result, _ = Renderer(scene, progress=False).frame(scene.n_frames // 2)
            arrays[f"{pathlib.Path(c).stem}/{prec}/irradiance"] = np.asarray(result.irradiance)
            print(f"{c:32s} {prec:8s} rendered in {time.perf_counter() - t0:6.1f} s", flush=True)
    for c in gradients:
        t0 = time.perf_counter()
        arrays[f"{pathlib.Path(c).stem}/default/gradient"] = _gradient(c)
        print(f"{c:32s} gradient in {time.perf_counter() - t0:6.1f} s", flush=True)
    np.savez_compressed(out, **arrays)


def compare(ref_path: str, other_path: str) -> int:
    ref, other = np.load(ref_path), np.load(other_path)
    print(f"reference: {ref['device']}   other: {other['device']}")
    print(f"{'array':48s} {'rel RMSE':>10s} {'max |diff| / max |ref|':>24s} {'cosine':>10s}")
    for key in sorted(k for k in other.files if k != "device"):
        stem = key.split("/")[0]
        ref_key = f"{stem}/default/{key.split('/')[-1]}"
        if ref_key not in ref.files:
            print(f"{key:48s} (no reference)")
            continue
        a, b = other[key].astype(np.float64).ravel(), ref[ref_key].astype(np.float64).ravel()
        if a.shape != b.shape or not np.all(np.isfinite(a)):
            print(f"{key:48s} shape {a.shape} vs {b.shape}, finite {bool(np.all(np.isfinite(a)))}")
            continue
        rel = np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-30)
        mx = np.max(np.abs(a - b)) / max(np.max(np.abs(b)), 1e-30)
        cos = a @ b / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-30)
        print(f"{key:48s} {rel:10.2e} {mx:24.2e} {cos:10.6f}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("save")
    s.add_argument("out")
    s.add_argument("--precision", nargs="+", default=["default"], choices=["default", "high", "highest"])
    s.add_argument("--gradients", nargs="*", default=GRADIENTS)
    c = sub.add_parser("compare")
    c.add_argument("reference")
    c.add_argument("other")
    args = ap.parse_args(argv)
    if args.cmd == "save":
        save(args.out, args.precision, args.gradients)
        return 0
    return compare(args.reference, args.other)


if __name__ == "__main__":
    sys.exit(main())
