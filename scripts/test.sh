#!/usr/bin/env bash
# Install everything (CPU torch pinned in pyproject.toml) and run the test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
python -m pip install --quiet --disable-pip-version-check -e ".[dev,distributed]"
export MUJOCO_GL="${MUJOCO_GL:-egl}"
python -m pytest tests -q
