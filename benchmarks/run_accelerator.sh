#!/usr/bin/env bash
# The benchmarks on JAX's default device (an accelerator where JAX finds one), in one go.
#
#   bash benchmarks/run_accelerator.sh OUTDIR
#
# Stages, each under its own time limit so that one slow stage cannot starve the others:
#   devices  bench_devices.py save: every shipped config's middle frame (default and highest matmul
#            precision) and the egg's vertex gradient, for `bench_devices.py compare` against a CPU run;
#   render   bench_render.py --frames 8: per-stage frame times, shading per receiver per occluder,
#            receiver sweep, throughput, 1/4/16 occluders;
#   grad     bench_frame_grad.py: full-frame forward and value_and_grad of three deforming configs.
# Logs and JSON go to OUTDIR; a one-line summary of each stage is printed.
set -u
out=${1:?usage: bash benchmarks/run_accelerator.sh OUTDIR}
py=${PYTHON:-python3}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
{ nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm,clocks.max.sm --format=csv 2>&1 || true
  $py -c "import jax, jaxlib, equinox, optax; print('jax', jax.__version__, 'jaxlib', jaxlib.__version__, 'equinox', equinox.__version__, 'optax', optax.__version__); print(jax.devices())"
} | tee "$out/machine.txt"
stage() {
    local name=$1 limit=$2 t=$SECONDS
    shift 2
    timeout "$limit" "$@" > "$out/$name.log" 2>&1
    local rc=$?
    echo "== $name: rc=$rc after $((SECONDS - t)) s (limit $limit s)"
    tail -n 25 "$out/$name.log"
}
stage render "${RENDER_LIMIT:-220}" $py benchmarks/bench_render.py --frames 8 --json "$out/render.json"
stage grad "${GRAD_LIMIT:-170}" $py benchmarks/bench_frame_grad.py --runs 5 --json "$out/frame_grad.json"
stage devices "${DEVICES_LIMIT:-130}" $py benchmarks/bench_devices.py save "$out/devices.npz" --precision default highest
