#!/usr/bin/env bash
# Sets up a local virtual environment (.venv) with jshadow and its dev tools, then lints and runs the tests.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then "$PY" -m venv .venv; fi
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e '.[dev,bench]'
.venv/bin/ruff check jshadow tests experiments benchmarks
.venv/bin/python -m pytest -q "$@"
