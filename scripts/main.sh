#!/usr/bin/env bash
# Set up (system packages, .venv, the toolkit) and run the main job on the embedded default
# world: the quick benchmark (about 30 tasks, the oracle check and the OnFly pilot under the
# nominal simulated-VLM error model). Results: runs/quick/ (JSON lines per episode, summary
# table) and runs/quick.json. Extra arguments go to `onfly bench`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
exec .venv/bin/onfly bench --config experiments/configs/quick.toml --out runs/quick --json runs/quick.json "$@"
