"""What travels in the wheel beyond the packages (the metadata is in pyproject.toml).

A clone keeps the shipped checkpoints in ``checkpoints/`` and the recipes' presets in
``recipes/configs/``. A wheel carries them inside the package, as ``spf_rl/checkpoints``
(the manifest and the files its names load) and ``spf_rl/presets`` (every preset), so that
``spf_rl.load_policy("routes-spf")`` and ``spf_rl.config.load_config`` work outside a clone.
:mod:`spf_rl.hub` and :mod:`spf_rl.config` look inside the package first, then in the clone.
"""
import json
from pathlib import Path

from setuptools import find_packages, setup

ROOT = Path(__file__).resolve().parent
#: Package name -> the clone directory it is built from.
DATA_PACKAGES = {"spf_rl.checkpoints": "checkpoints", "spf_rl.presets": "recipes/configs"}

names = json.loads((ROOT / "checkpoints" / "manifest.json").read_text())["names"]
setup(
    packages=find_packages(where=str(ROOT), include=["spf_rl", "spf_rl.*", "envs", "envs.*"]) + list(DATA_PACKAGES),
    package_dir=DATA_PACKAGES,
    package_data={"spf_rl.checkpoints": ["manifest.json", *sorted(set(names.values()))], "spf_rl.presets": ["*.yaml"]},
)
