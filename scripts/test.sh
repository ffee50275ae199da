#!/usr/bin/env bash
# Install the package with the extras the tests need, at the lock's exact versions
# (scripts/install.sh, constraints.txt), then lint it (ruff) and run the test suite and the
# benchmarks' tests and the examples in the docstrings of envs/ and spf_rl/ in one pytest run, on one worker per core
# (pytest-xdist). Exits non-zero if any of them fails.
# Arguments are passed to pytest, e.g. --full-samples (docs/reproducing.md).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh dev,distributed,viz,deploy
export MUJOCO_GL="${MUJOCO_GL:-egl}"
status=0
python -m ruff check . || status=$?
python -m pytest --numprocesses auto --doctest-modules tests benchmarks/tests envs spf_rl runtime/spf_rl_runtime -q "$@" || status=$?
exit "$status"
