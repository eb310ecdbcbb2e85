"""Command line: ``jshadow render | reference | compare | bench | fit``.

Bad input (config errors, missing files, invalid numbers) ends with exit status 2 and one line on
stderr naming the key or file; nothing is written in that case. Output files are written under a
temporary name and renamed, so an interrupted run leaves no half-written file.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import sys
import tempfile
import time
import warnings

import numpy as np

__all__ = ["main"]


class UsageError(Exception):
    """Bad input from the user: reported as one line, exit status 2."""


def _atomic_write(path: pathlib.Path, write) -> None:
    """Call ``write(fileobj)`` on a temporary file next to ``path``, then rename it into place."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; give the usual permissions
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _save_npz(path: pathlib.Path, **arrays) -> None:
    _atomic_write(path, lambda fh: np.savez(fh, **{k: np.asarray(v) for k, v in arrays.items()}))


def _save_json(path: pathlib.Path, obj) -> None:
    _atomic_write(path, lambda fh: fh.write(json.dumps(obj, indent=2).encode()))


def _load(config_path: str):
    """Load and build a scene; every problem becomes a UsageError naming the key or file."""
    from .config import ConfigError, build_scene, load_config

    _enable_x64_if_requested(config_path)
    try:
        cfg = load_config(config_path)
        scene = build_scene(cfg)
    except ConfigError as err:
        raise UsageError(str(err)) from None
    except (ValueError, OSError) as err:
        raise UsageError(f"{config_path}: {err}") from None
    return cfg, scene


def _enable_x64_if_requested(config_path: str) -> None:
    """Turn on JAX's float64 mode before loading a config whose [method] asks for float64."""
    import tomllib

    try:
        with open(config_path, "rb") as fh:
            dtype = tomllib.load(fh).get("method", {}).get("dtype")
    except (OSError, ValueError, AttributeError):  # ValueError: TOML syntax, bytes that are not UTF-8
        return  # load_config reports the problem properly
    if dtype == "float64":
        import jax

        jax.config.update("jax_enable_x64", True)


def _check_exposure(exposure) -> None:
    if exposure is not None and not (np.isfinite(exposure) and exposure > 0):
        raise UsageError(f"--exposure must be a positive finite number, got {exposure}")


def _make_out(out: str) -> pathlib.Path:
    p = pathlib.Path(out)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise UsageError(f"cannot create output folder {out}: {err.strerror or err}") from None
    if not os.access(p, os.W_OK):
        raise UsageError(f"output folder {out} is not writable")
    return p


def _picture(path, scene, res, t, exposure, title):
    from .picture import draw_scene

    _atomic_write(path, lambda fh: draw_scene(fh, scene, res, t, exposure=exposure, title=title))


def _frame_arrays(scene, res, extra=None):
    d = {
        "points": res.points,
        "normals": res.normals,
        "irradiance": res.irradiance,
        "radiance": res.radiance,
        "plane_count": np.int64(scene.receivers.points.shape[0]),
    }
    if scene.receivers.grid_shape is not None:
        d["grid_shape"] = np.asarray(scene.receivers.grid_shape, np.int64)
    d.update(extra or {})
    return d


def cmd_render(args) -> int:
    import jax
    from tqdm.auto import tqdm

    from .entities import frame_time
    from .picture import exposure_for
    from .runner import Renderer

    _check_exposure(args.exposure)
    if args.chunk is not None and args.chunk < 1:
        raise UsageError(f"--chunk must be a positive integer (receivers per piece), got {args.chunk}")
    if args.devices is not None and not 1 <= args.devices <= len(jax.devices()):
        raise UsageError(
            f"--devices must be in 1..{len(jax.devices())} (JAX devices available here), got {args.devices}"
        )
    _, scene = _load(args.config)
    out = _make_out(args.out)
    renderer = Renderer(
        scene,
        sphere_path=args.sphere_path,
        chunk=args.chunk,
        progress=scene.n_frames == 1,
        devices=args.devices,
        split_stages=args.split_stages,
        # a one-frame render has no later frame for the fixed-geometry readout to pay off in, and
        # its warm re-run (below) would time the readout's preparation instead of a frame
        static_readout=scene.n_frames > 1,
    )
    frames, exposure, gif = [], None, []
    n_plane = scene.receivers.points.shape[0]
    t_start = time.perf_counter()
    for f in tqdm(range(scene.n_frames), desc="render", unit="frame", disable=scene.n_frames < 2):
        res, times = renderer.frame(f)
        if f == 0 and scene.n_frames == 1 and not args.no_warm:
            res, warm = renderer.frame(0)  # same frame again: compiled, for a warm timing
            times = {"first_call": times, **warm}
        frames.append(times)
        _save_npz(out / f"frame_{f:04d}.npz", **_frame_arrays(scene, res))
        if exposure is None:
            exposure = args.exposure or exposure_for(np.asarray(res.radiance)[:n_plane])
        png = out / f"frame_{f:04d}.png"
        _picture(png, scene, res, frame_time(f, scene.n_frames), exposure, f"jshadow  frame {f}")
        if args.gif:
            import imageio.v3 as iio

            gif.append(iio.imread(png))
    wall = time.perf_counter() - t_start
    warm = frames[1:] if len(frames) > 1 else [frames[0]]
    summary = {
        "device": str(jax.devices()[0]),
        "receivers": int(np.asarray(res.points).shape[0]),
        "receivers_per_piece": renderer.piece_size(int(np.asarray(res.points).shape[0])),
        "devices": 1 if renderer.mesh is None else int(renderer.mesh.devices.size),
        "frames": len(frames),
        "first_frame_ms": frames[0].get("first_call", frames[0])["total_ms"],
        "median_ms": {k: float(np.median([fr[k] for fr in warm])) for k in warm[0] if k.endswith("_ms")},
        "bsv_computations": renderer.bsv_computations,
        "self_visibility_computations": renderer.self_visibility_computations,
        "light_image_computations": renderer.image_computations,
        "light_fraction_computations": renderer.fraction_computations,
        # what the [method] options that may be "auto" took (jshadow.config.build_scene)
        "light_visibility": scene.method.light_visibility,
        "environment_lights": scene.method.environment_lights,
        "self_visibility": scene.method.self_visibility,
        "directions": list(scene.method.directions),
        "light_cap": list(scene.method.light_cap),
        "lamp_images": scene.method.lamp_images,
        "lamp_penumbrae": scene.method.lamp_penumbrae,
        "readout_frames": renderer.readout_frames,
        "wall_s_including_pictures": wall,
        "per_frame": frames,
    }
    _save_json(out / "timings.json", summary)
    if gif:
        import imageio.v3 as iio

        _atomic_write(
            out / "animation.gif",
            lambda fh: fh.write(iio.imwrite("<bytes>", gif, extension=".gif", duration=80, loop=0)),
        )
    m = summary["median_ms"]
    split = f" = field {m['field_ms']:.1f} + combine {m['combine_ms']:.1f}" if "field_ms" in m else ""
    cast = "maps" if scene.method.self_visibility == "maps" else "rays"  # how the own vertices are cast
    own = f", own-vertex {cast} {m['self_visibility_ms']:.1f}" if "self_visibility_ms" in m else ""
    own += f", light images {m['light_images_ms']:.1f}" if "light_images_ms" in m else ""
    print(
        f"rendered {len(frames)} frame(s), {summary['receivers']} receivers -> {out}  "
        f"(warm median {m['total_ms']:.1f} ms/frame: BSV {m['bsv_ms']:.1f}{own}, "
        f"shading {m['shading_ms']:.1f}"
        f"{split}; first frame incl. compile {summary['first_frame_ms']:.0f} ms)"
    )
    return 0


def cmd_reference(args) -> int:
    import jax

    from .entities import frame_time
    from .picture import exposure_for
    from .reference import reference

    if args.spp < 1:
        raise UsageError(f"--spp must be a positive integer, got {args.spp}")
    _check_exposure(args.exposure)
    _, scene = _load(args.config)
    if args.frame is not None and not 0 <= args.frame < scene.n_frames:
        raise UsageError(
            f"--frame must be in 0..{scene.n_frames - 1} (the config's frames), got {args.frame}"
        )
    out = _make_out(args.out)
    frames = range(scene.n_frames) if args.frame is None else [args.frame]
    timings, exposure = [], None
    n_plane = scene.receivers.points.shape[0]
    for f in frames:
        key = jax.random.fold_in(jax.random.PRNGKey(args.seed), f)
        t0 = time.perf_counter()
        res = reference(scene, args.spp, key, frame=f, progress=True)
        jax.block_until_ready(res.irradiance)
        timings.append({"frame": f, "seconds": time.perf_counter() - t0, "spp": args.spp})
        _save_npz(
            out / f"frame_{f:04d}.npz",
            **_frame_arrays(scene, res, {"irradiance_stderr": res.irradiance_stderr}),
        )
        if exposure is None:
            exposure = args.exposure or exposure_for(np.asarray(res.radiance)[:n_plane])
        _picture(
            out / f"frame_{f:04d}.png",
            scene,
            res,
            frame_time(f, scene.n_frames),
            exposure,
            f"reference  {args.spp} spp  frame {f}",
        )
    _save_json(out / "timings.json", {"seed": args.seed, "frames": timings})
    print(f"reference: {len(timings)} frame(s) at {args.spp} spp -> {out}")
    return 0


def cmd_compare(args) -> int:
    from .compare import compare_outputs

    for d in (args.a, args.b):
        if not pathlib.Path(d).is_dir():
            raise UsageError(f"{d}: no such output folder")
    try:
        report = compare_outputs(args.a, args.b, out_png=args.out)
    except ValueError as err:
        raise UsageError(str(err)) from None
    print(json.dumps(report, indent=2))
    return 0


def cmd_bench(args) -> int:
    """Warm per-stage timings of the shadow-field renderer, and its error against the reference."""
    import jax

    from .compare import frame_errors
    from .reference import reference
    from .runner import Renderer

    if args.frames < 1 or (args.spp is not None and args.spp < 1):
        raise UsageError("--frames and --spp must be positive integers")
    _, scene = _load(args.config)
    if args.json:  # fail now, not after the timings
        parent = pathlib.Path(args.json).parent
        _make_out(str(parent) if str(parent) else ".")
        if pathlib.Path(args.json).is_dir():
            raise UsageError(f"--json {args.json} is a folder; expected a file name")
    rend = Renderer(scene)
    t0 = time.perf_counter()
    res, _ = rend.frame(0)
    first = time.perf_counter() - t0
    split = Renderer(scene, split_stages=True)  # the shading's split, timed after rend's frames
    split.frame(0)
    sel = [i % scene.n_frames for i in range(1, args.frames + 1)]
    rows = [rend.frame(f)[1] for f in sel]  # in sequence, as a render loop runs them
    split_rows = [split.frame(f)[1] for f in sel]
    med = {k: float(np.median([r[k] for r in rows])) for k in rows[0]}
    split_med = {k: float(np.median([r[k] for r in split_rows])) for k in split_rows[0]}
    out = {
        "config": args.config,
        "device": str(jax.devices()[0]),
        "receivers": int(res.points.shape[0]),
        "compile_s": max(first - med["total_ms"] / 1e3, 0.0),
        "median_ms": med,
        "split_median_ms": split_med,
        "fps": 1e3 / med["total_ms"],
    }
    print(f"{'stage':<12}{'median ms':>12}{'split stages':>14}")
    for k, v in split_med.items():
        print(f"{k:<12}{med[k] if k in med else float('nan'):>12.2f}{v:>14.2f}")
    print(f"receivers {out['receivers']}, {out['fps']:.1f} frames/s, compile {out['compile_s']:.1f} s")
    if args.spp:
        t0 = time.perf_counter()
        ref = reference(scene, args.spp, jax.random.PRNGKey(args.seed), frame=0, progress=True)
        ref_s = time.perf_counter() - t0
        err = frame_errors(res.irradiance, ref.irradiance)
        se = float(np.sqrt(np.mean(np.asarray(ref.irradiance_stderr, np.float64) ** 2)))
        err["ref_stderr_ratio"] = se / err["rmse"] if err["rmse"] > 0 else float("inf")
        out["reference"] = {"spp": args.spp, "seconds": ref_s, **err}
        print(
            f"vs reference ({args.spp} spp, {ref_s:.1f} s): relative RMSE {err['rel_rmse']:.2%}, "
            f"max error {err['max_rel_err']:.2%} of the mean; reference stderr / RMSE "
            f"{err['ref_stderr_ratio']:.2f} (want <= 0.1)"
        )
    if args.json:
        path = pathlib.Path(args.json)
        _make_out(str(path.parent) if str(path.parent) else ".")
        _save_json(path, out)
    return 0


def cmd_fit(args) -> int:
    import jax.numpy as jnp

    from .config import build_scene, get_param, set_param
    from .entities import frame_time
    from .optim import fit_params, plane_radiance
    from .picture import exposure_for
    from .scene import LIGHT_IMAGES_NO_DERIVATIVE, SELF_RAYS_NO_DERIVATIVE

    cfg, scene0 = _load(args.config)
    fit = cfg.fit
    if fit is None:
        raise UsageError(f"{args.config}: no [fit] table (see configs/fit_bend.toml)")
    paths = list(fit.params)
    if args.steps is not None:
        if args.steps < 1:
            raise UsageError(f"--steps must be a positive integer, got {args.steps}")
    steps = args.steps or fit.steps
    init = [jnp.asarray(v, jnp.float32) for v in fit.init] if fit.init is not None else None
    init = init or [get_param(cfg, p) for p in paths]

    def with_params(values):
        c = cfg
        for p, v in zip(paths, values, strict=True):
            c = set_param(c, p, v)
        return c

    frame = fit.frame
    if fit.target_values is not None:
        target_values = [jnp.asarray(v, jnp.float32) for v in fit.target_values]
        target_scene = build_scene(with_params(target_values))
        target = plane_radiance(target_scene, frame)
    else:
        target_values = None
        target = _target_from_image(
            fit.target_image, scene0, plane_radiance(build_scene(with_params(init)), frame)
        )
    out = _make_out(args.out)
    if cfg.method.bsv_images == "auto" and scene0.method.bsv_images == "coverage":
        print(
            "fit: [method] bsv_images = 'auto' is 'coverage' here (a mesh's deformation is fitted: "
            "the loss is continuous in the shape and its gradient exact)",
            file=sys.stderr,
        )
    try:
        res = fit_params(
            lambda v: build_scene(with_params(v)),
            init,
            target,
            steps=steps,
            learning_rate=fit.learning_rate,
            progress=True,
            frame=frame,
            regularization=fit.regularization,
        )
    except ValueError as err:  # a fitted sphere occluder under the images, or own-vertex rays
        if str(err) not in (SELF_RAYS_NO_DERIVATIVE, LIGHT_IMAGES_NO_DERIVATIVE):
            raise
        raise UsageError(f"{args.config}: {err}") from None
    report = {
        "params": {p: np.asarray(v).tolist() for p, v in zip(paths, res.params, strict=True)},
        "init": {p: np.asarray(v).tolist() for p, v in zip(paths, init, strict=True)},
        "target_values": None
        if target_values is None
        else {p: np.asarray(v).tolist() for p, v in zip(paths, target_values, strict=True)},
        "loss": res.loss,
        "history": res.history,
        "steps": steps,
        "learning_rate": fit.learning_rate,
        "retraced": res.retraced,  # steps traced again after a static-size overflow
        "bsv_images": scene0.method.bsv_images,  # what [method] bsv_images = "auto" chose
    }
    _save_json(out / "fit.json", report)
    _loss_plot(out / "loss.png", res.loss)
    exposure = exposure_for(np.asarray(target))
    t = frame_time(frame, scene0.n_frames)
    for name, values in (("before", init), ("after", res.params)):
        from .scene import render

        sc = build_scene(with_params(values))
        _picture(out / f"{name}.png", sc, render(sc, frame), t, exposure, f"fit: {name}")
    if target_values is not None:
        _picture(out / "target.png", target_scene, render(target_scene, frame), t, exposure, "fit: target")
    final = ", ".join(f"{p} = {np.round(np.asarray(v), 4).tolist()}" for p, v in report["params"].items())
    print(f"fit: loss {res.loss[0]:.3e} -> {res.loss[-1]:.3e} in {steps} steps; {final} -> {out}")
    return 0


def _target_from_image(path, scene, current):
    """Plane radiance target from a picture of the plane: sRGB → linear, resized to the plane grid
    (nearest), scaled to the mean of the current rendering (a picture carries no absolute scale)."""
    import imageio.v3 as iio

    rows_cols = scene.receivers.grid_shape
    if rows_cols is None:
        raise UsageError("fit.target_image needs a plane receiver")
    try:
        img = np.asarray(iio.imread(path), float)
    except Exception as err:  # imageio raises many types for unreadable files
        raise UsageError(f"{path}: cannot read the target image ({err})") from None
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, -1)
    img = img[..., :3] / (255.0 if img.max() > 1.0 else 1.0)
    lin = np.where(img <= 0.04045, img / 12.92, ((img + 0.055) / 1.055) ** 2.4)
    rows, cols = rows_cols
    ri = (np.arange(rows) * lin.shape[0] / rows).astype(int)
    ci = (np.arange(cols) * lin.shape[1] / cols).astype(int)
    grid = lin[ri][:, ci].reshape(-1, 3)
    cur = np.asarray(current)
    scale = cur.mean() / max(grid.mean(), 1e-12)
    return np.asarray(grid * scale, np.float32)


def _loss_plot(path, loss):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(5, 3.2), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    ax.semilogy(np.arange(1, len(loss) + 1), np.maximum(loss, 1e-12))
    ax.set_xlabel("step")
    ax.set_ylabel("relative MSE")
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    _atomic_write(path, lambda fh: fig.savefig(fh, format="png"))


class _Parser(argparse.ArgumentParser):
    """Argument errors as one line on stderr (exit status 2), like every other bad input."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="jshadow", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("render", help="render a scene config with shadow fields")
    r.add_argument("config")
    r.add_argument("--out", required=True)
    r.add_argument("--gif", action="store_true", help="also write animation.gif")
    r.add_argument(
        "--sphere-path",
        choices=("analytic", "bsv"),
        default="analytic",
        help="sphere occluders: exact cap (default) or through the BSV path",
    )
    r.add_argument("--exposure", type=float, default=None, help="fixed exposure for the pictures")
    r.add_argument("--no-warm", action="store_true", help="single frame: skip the warm re-run")
    r.add_argument(
        "--chunk",
        type=int,
        default=None,
        help="receivers evaluated per step (default 131072); lower it to bound memory",
    )
    r.add_argument("--devices", type=int, default=None, help="shard the receivers over this many JAX devices")
    r.add_argument(
        "--split-stages",
        action="store_true",
        help="time field evaluation and combination separately (three calls per frame, slower)",
    )
    r.set_defaults(func=cmd_render)

    q = sub.add_parser("reference", help="Monte Carlo ground truth for a scene config")
    q.add_argument("config")
    q.add_argument("--spp", type=int, required=True, help="samples per receiver and strategy")
    q.add_argument("--out", required=True)
    q.add_argument("--seed", type=int, default=0)
    q.add_argument("--frame", type=int, default=None, help="only this frame (default: all)")
    q.add_argument("--exposure", type=float, default=None)
    q.set_defaults(func=cmd_reference)

    c = sub.add_parser("compare", help="error of output folder A against reference folder B")
    c.add_argument("a")
    c.add_argument("b")
    c.add_argument("--out", default=None, help="PNG of the difference (frame 0)")
    c.set_defaults(func=cmd_compare)

    b = sub.add_parser("bench", help="per-stage timings, and error against the reference with --spp")
    b.add_argument("config")
    b.add_argument("--frames", type=int, default=10, help="warm frames timed (after a first, compiling one)")
    b.add_argument("--spp", type=int, default=None, help="also compute the reference at this spp (frame 0)")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--json", default=None, help="write the figures to this JSON file")
    b.set_defaults(func=cmd_bench)

    f = sub.add_parser("fit", help="fit config parameters to a target shadow ([fit] table)")
    f.add_argument("config")
    f.add_argument("--out", required=True)
    f.add_argument("--steps", type=int, default=None, help="override fit.steps")
    f.set_defaults(func=cmd_fit)
    return p


def _one_line_warning(message, category, filename, lineno, file=None, line=None):
    """Warnings (e.g. an open mesh) as one line on stderr, without the source line."""
    print(f"jshadow: warning: {category.__name__}: {message}", file=file or sys.stderr)


def _out_of_memory(err: BaseException) -> bool:
    if isinstance(err, MemoryError):
        return True
    text = str(err)
    return type(err).__name__ == "JaxRuntimeError" and (
        "RESOURCE_EXHAUSTED" in text or "Out of memory" in text
    )


def main(argv=None) -> int:
    """Run one command; returns the exit status (0 ok, 1 out of memory, 2 bad input)."""
    args = build_parser().parse_args(argv)
    show = warnings.showwarning
    warnings.showwarning = _one_line_warning
    try:
        return args.func(args)
    except UsageError as err:
        print(f"jshadow {args.command}: error: {err}", file=sys.stderr)
        return 2
    except Exception as err:
        if not _out_of_memory(err):
            raise
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        print(
            f"jshadow {args.command}: error: out of memory ({first[:200]}); render in smaller pieces "
            "with --chunk N (receivers per step)",
            file=sys.stderr,
        )
        return 1
    finally:
        warnings.showwarning = show


if __name__ == "__main__":
    sys.exit(main())
