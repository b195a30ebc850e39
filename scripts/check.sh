#!/usr/bin/env bash
# The test command: lint, format check, type check, then the test suite (slow tests excluded).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup-venv.sh
. .venv/bin/activate
ruff check .
ruff format --check .
mypy
python -m pytest "$@"
