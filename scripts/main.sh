#!/usr/bin/env bash
# Install the package with its figures extra, at the lock's exact versions (scripts/install.sh,
# constraints.txt), and run the main job: behaviour cloning of SPF (sparsity 0.8) with a pointer loss
# (recipes/configs/bc_main.yaml; 1,500 gradient steps on 2,000 episodes), then test-split evaluation.
# Arguments are passed to recipes/bc.py.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh viz
export MUJOCO_GL="${MUJOCO_GL:-egl}"
python recipes/bc.py "$@"
