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
# LLVM's backend at optimisation level 1 instead of XLA's default 3: compiles 10-15 % faster (one
# 60-step gradient program timed at each level).
# (Level 0 compiles ~30 % faster but is not used: in one full run it aborted one compile, and it
# gives a non-finite gradient in tests/test_stress.py that levels 1 and 3 do not.) Every token of
# XLA_FLAGS must be a `--xla_...` flag: XLA silently stops reading at the first one that is not.
export XLA_FLAGS="${XLA_FLAGS:-} --xla_cpu_multi_thread_eigen=false --xla_backend_optimization_level=1"
.venv/bin/python -m pytest -q -n "${PYTEST_WORKERS:-2}" "$@"
