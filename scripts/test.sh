#!/usr/bin/env bash
# Install what is needed, then run the default (fast) test suite; slow checks are
# marked `slow` and run by the benchmark commands.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
export MUJOCO_GL="${MUJOCO_GL:-egl}"
# Two test processes share the machine (CI has two cores), each on one thread: torch's and the
# BLAS libraries' own thread pools would otherwise fight over the cores (one process with their
# threads: 15.6 min on two cores; two processes with one thread each: 10.8 min).
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}" MKL_NUM_THREADS="${MKL_NUM_THREADS:-1}"
export OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}"
python3 -m pytest -q -n 2 --dist worksteal "$@"
