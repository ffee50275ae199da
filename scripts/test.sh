#!/usr/bin/env bash
# Install the package with the extras the tests need (torch==2.13.0 from the configured
# package index) and run the test suite, then the examples in the docstrings of envs/ and
# spf_rl/. Exits non-zero if either fails.
set -euo pipefail
cd "$(dirname "$0")/.."
python -m pip install --quiet --disable-pip-version-check -e ".[dev,distributed,viz]"
export MUJOCO_GL="${MUJOCO_GL:-egl}"
status=0
python -m pytest tests -q || status=$?
python -m pytest --doctest-modules envs spf_rl -q || status=$?
exit "$status"
