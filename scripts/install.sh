#!/usr/bin/env bash
# Install spf-rl (editable) with the extras named in $1, e.g. "viz" or "dev,distributed,viz,deploy",
# at the exact versions of the lock, constraints.txt: the build tools first, then the package
# and everything it needs, without build isolation, so that nothing is resolved outside the
# lock. torch==2.13.0 comes as the CPU or the CUDA build, whichever the package index serves.
# Regenerate the lock with: bash scripts/lock.sh
set -euo pipefail
cd "$(dirname "$0")/.."
extras="${1:-}"
pip=(python -m pip install --quiet --disable-pip-version-check --constraint constraints.txt)
"${pip[@]}" setuptools wheel
"${pip[@]}" --no-build-isolation --editable ".${extras:+[$extras]}"
# the deploy extra brings the torch-free runtime too (runtime/, its own distribution: spf-rl-runtime)
if [[ ",$extras," == *",deploy,"* ]]; then
    "${pip[@]}" --no-build-isolation --editable ./runtime
fi
