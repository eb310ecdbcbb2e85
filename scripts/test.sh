#!/usr/bin/env bash
# Sets up a local virtual environment (.venv) with jshadow and its dev tools, then lints and runs the tests.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then "$PY" -m venv .venv; fi
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e '.[dev,bench]'
.venv/bin/ruff check jshadow tests experiments benchmarks
# Two pytest workers, each with single-threaded XLA: on a 2-core machine this is ~1.35x faster than
# one process whose XLA uses both cores (most test time is compilation, which is single-threaded).
# Three settings make compilation cheaper (they change how fused kernels are generated, not what
# is computed; jshadow's own runs keep XLA's defaults):
# - LLVM's backend at optimisation level 1 instead of XLA's default 3: compiles 10-15 % faster (one
#   60-step gradient program timed at each level). Level 0 compiles ~30 % faster but is not used:
#   in one of three full runs it aborted one compile (not reproduced alone).
# - XLA:CPU's elemental kernel emitters instead of its newer MLIR fusion emitters
#   (--xla_cpu_use_fusion_emitters=false): two of the slowest gradient tests (edge-scan node
#   compaction and transposed jvp, no compilation cache) took 56-62 s against 73-76 s with them;
#   the full suite, 822 tests, 14:49 (809 tests without this flag: 20:22, earlier the same day).
# - LLVM's module compiled whole (--xla_cpu_parallel_codegen_split_count=1) instead of split into
#   up to 32 parts for parallel code generation, which two single-threaded workers cannot use: eight
#   of the slowest compiling tests (four files, two workers) took 91 and 91 s against 97 and 98 s
#   (XLA compilation 137-138 against 143-145 s summed; 2026-12-07).
# Every token of XLA_FLAGS must be a `--xla_...` flag: XLA silently stops reading at the first one
# that is not (an unknown `--xla_` flag aborts).
export XLA_FLAGS="${XLA_FLAGS:-} --xla_cpu_multi_thread_eigen=false --xla_backend_optimization_level=1 --xla_cpu_use_fusion_emitters=false --xla_cpu_parallel_codegen_split_count=1"
# --dist worksteal: a worker that runs out of tests takes queued ones from the other. Under the
# default load scheduling the first worker was sent the whole block of slow modules that conftest.py
# puts first (xdist sends each worker a run of consecutive tests to start with), and the other one
# stood idle for the last 8 of 41 minutes (2026-12-05, scripts/compile_report.py's per-worker JSON).
.venv/bin/python -m pytest -q -n "${PYTEST_WORKERS:-2}" --dist worksteal "$@"
