#!/usr/bin/env bash
# Install everything (CPU torch pinned in pyproject.toml) and run the main job:
# behaviour cloning of SPF (sparsity 0.8) on the default config, then test-split evaluation.
set -euo pipefail
cd "$(dirname "$0")/.."
python -m pip install --quiet --disable-pip-version-check -e .
export MUJOCO_GL="${MUJOCO_GL:-egl}"
python recipes/bc.py "$@"
