#!/usr/bin/env bash
# Sets up a local virtual environment (.venv) with jshadow, then renders the default scene to out/default/.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then "$PY" -m venv .venv; fi
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e .
.venv/bin/jshadow render "${1:-configs/sphere.toml}" --out "${2:-out/default}"
