#!/usr/bin/env bash
# The test command: lint, format check, type check, then the test suite (slow tests excluded).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup-venv.sh
# The station's browser tests drive Debian's chromium through playwright (never a downloaded
# browser): as root on Debian it is installed here when missing; elsewhere they are skipped.
if [[ ! -x /usr/bin/chromium && $(id -u) -eq 0 ]] && command -v apt-get >/dev/null; then
  echo "installing Debian's chromium for the station's browser tests" >&2
  if ! { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium; } >&2
  then
    echo "chromium could not be installed: the browser tests will be skipped" >&2
  fi
fi
. .venv/bin/activate
ruff check .
ruff format --check .
mypy
python -m pytest "$@"
