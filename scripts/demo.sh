#!/usr/bin/env bash
# Install what is needed, then run the demo on a bundled clip; the report and video go to
# runs/demo (override with -o DIR; see `crisp demo --help`).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
export MUJOCO_GL="${MUJOCO_GL:-egl}"
crisp demo "$@"
