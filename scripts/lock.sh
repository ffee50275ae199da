#!/usr/bin/env bash
# Regenerate constraints.txt, the lock of exact versions that scripts/install.sh installs:
# a fresh virtual environment gets the newest releases that pyproject.toml's ranges admit,
# with every extra the README's commands install (plus tensorboard), and the lock is that
# environment's `pip freeze`. Run the tests after it (bash scripts/test.sh): the lock is
# only worth committing once the suite passes with it.
#   bash scripts/lock.sh            # writes constraints.txt
set -euo pipefail
cd "$(dirname "$0")/.."
venv="$(mktemp -d)/venv"
trap 'rm -rf "$(dirname "$venv")"' EXIT
python -m venv "$venv"
pip=("$venv/bin/python" -m pip install --quiet --disable-pip-version-check)
"${pip[@]}" setuptools wheel
"${pip[@]}" --no-build-isolation --editable ".[dev,distributed,viz,deploy,tensorboard]"
{
    echo "# The lock of exact versions that scripts/install.sh installs (pip install -c constraints.txt)."
    echo "# Made by: bash scripts/lock.sh, on $(date -u +%Y-%m-%d), with $("$venv/bin/python" --version)."
    # a local version label (2.13.0+cpu) is dropped: the pin then matches the CPU and CUDA builds alike
    "$venv/bin/python" -m pip freeze --all --exclude-editable --disable-pip-version-check \
        | grep -v -E '^(pip)==' | sed -E 's/^([A-Za-z0-9_.-]+==[^+ ]+)\+[A-Za-z0-9.]+$/\1/' | LC_ALL=C sort -f
} > constraints.txt.tmp
mv constraints.txt.tmp constraints.txt
echo "constraints.txt: $(grep -c '==' constraints.txt) packages"
