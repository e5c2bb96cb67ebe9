#!/usr/bin/env bash
# Install what is needed, then run the default (fast) test suite; slow checks are
# marked `slow` and run by the benchmark commands.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
export MUJOCO_GL="${MUJOCO_GL:-egl}"
python3 -m pytest -q "$@"
