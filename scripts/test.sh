#!/usr/bin/env bash
# Set up (system packages, .venv, the toolkit) and run the default test suite.
# Extra arguments go to pytest, e.g. `bash scripts/test.sh -m slow` for the slow tests. The run
# is spread over every core (pytest-xdist; one test file per worker at a time); `-n 0` runs it in
# one process.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/python -m pytest -n auto --dist loadfile "$@"
