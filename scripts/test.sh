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
# LLVM's backend optimisation off: compiles about 30 % faster, and the tests' arrays are small enough
# that the slower generated code costs less than that. (Every token of XLA_FLAGS must be a
# `--xla_...` flag: XLA stops reading at the first one that is not, silently.)
export XLA_FLAGS="${XLA_FLAGS:-} --xla_cpu_multi_thread_eigen=false --xla_backend_optimization_level=0"
.venv/bin/python -m pytest -q -n "${PYTEST_WORKERS:-2}" "$@"
