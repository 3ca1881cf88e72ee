#!/usr/bin/env bash
# Idempotent set-up for a fresh clone: system packages, a .venv, and the toolkit with its
# test extras at the versions of constraints.txt. Re-running is cheap: pip is skipped while
# pyproject.toml and constraints.txt are unchanged.
set -euo pipefail
cd "$(dirname "$0")/.."

need_apt=()
# Open3D links against libusb-1.0 and libgomp at import time.
ldconfig -p | grep -q 'libusb-1.0.so.0' || need_apt+=(libusb-1.0-0)
ldconfig -p | grep -q 'libgomp.so.1' || need_apt+=(libgomp1)
# The planner compiles its CasADi-generated QP data once per formulation (planning/mpc_codegen.py);
# without a C compiler it falls back to the slower NumPy path.
command -v gcc >/dev/null 2>&1 || command -v cc >/dev/null 2>&1 || need_apt+=(gcc libc6-dev)
if [ ${#need_apt[@]} -gt 0 ]; then
  if [ "$(id -u)" -eq 0 ]; then SUDO=""; else SUDO="sudo"; fi
  echo "setup: installing system packages: ${need_apt[*]}"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq "${need_apt[@]}"
fi

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv"
  "$PY" -m venv .venv
fi
stamp=.venv/.onfly-installed
want=$(cat pyproject.toml constraints.txt scripts/setup.sh | sha256sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  echo "setup: installing the toolkit into .venv (first run takes a few minutes)"
  .venv/bin/python -m pip install -q --upgrade pip
  # The CPU build of torch first: a looser range would pull a multi-GB CUDA build.
  .venv/bin/python -m pip install -q "torch==2.13.0"
  .venv/bin/python -m pip install -q -c constraints.txt -e ".[test]"
  echo "$want" > "$stamp"
fi

# Build the default planner's compiled QP data into the user cache now (once per formulation;
# seconds on a quiet machine), so the first episode or test does not pay for it.
if command -v gcc >/dev/null 2>&1 || command -v cc >/dev/null 2>&1; then
  OMP_NUM_THREADS=1 .venv/bin/python -c "from planning.planner import Planner; p = Planner(); print('setup: planner QP data backend:', p.qp_backend)" \
    || echo "setup: warning: could not pre-build the planner's compiled QP data (it falls back to NumPy)"
fi
