"""The wheel works outside the clone: built with ``pip wheel .``, installed (without its
dependencies, which come from this environment) into a fresh virtual environment and used from
another directory, it loads every shipped name, lists the checkpoints, reads the config presets
and builds the env, from the installed copy."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import textwrap
from pathlib import Path

import pytest

import spf_rl

CLONE = Path(spf_rl.__file__).resolve().parents[1]
#: What the wheel's build does not read (run state, results, virtual environments, build leftovers).
BUILD_IGNORES = (".git", ".venv*", "runs", "data", "results", "build", "*.egg-info", "__pycache__", ".pytest_cache")

pytestmark = pytest.mark.skipif(
    not (CLONE / "pyproject.toml").is_file() or not (CLONE / "checkpoints" / "manifest.json").is_file(),
    reason="needs the clone the package is installed from (an editable install)",
)

USE = textwrap.dedent(
    """
    import json, sys
    import envs, spf_rl
    from spf_rl.config import load_config
    from spf_rl.train.bc import BCConfig

    names = spf_rl.list_checkpoints()
    for name in names:
        policy, config = spf_rl.load_policy(name)
    quick = load_config(BCConfig, "bc", [], preset="bc_quick")
    env = envs.make_path_follow_env(num_houses=1, demo_length=5, render=False)
    print(json.dumps({"spf_rl": spf_rl.__file__, "envs": envs.__file__, "names": sorted(names),
                      "quick_episodes": quick.data.num_episodes, "batch": list(env.batch_size)}))
    """
)


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> Path:
    """A fresh virtual environment holding only the wheel; this environment's packages behind it."""
    root = tmp_path_factory.mktemp("wheel")
    source = root / "source"  # a copy of what the wheel is built from: the build leaves the clone as it is
    shutil.copytree(CLONE, source, ignore=shutil.ignore_patterns(*BUILD_IGNORES))
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(source), "--no-deps", "--no-build-isolation", "--quiet",
         "--disable-pip-version-check", "--wheel-dir", str(root / "dist")],
        check=True, cwd=root,
    )
    (wheel,) = (root / "dist").glob("spf_rl-*.whl")
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(root / "venv")], check=True)
    python = root / "venv" / "bin" / "python"
    site = Path(subprocess.run([python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                               check=True, capture_output=True, text=True).stdout.strip())
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "--no-index", "--quiet", "--disable-pip-version-check",
         "--target", str(site), str(wheel)],
        check=True, cwd=root,
    )
    # the dependencies (torch, torchrl, mujoco, ...) from this environment, after the wheel's copy: a plain
    # path entry, so this environment's editable spf_rl finder (a .pth of its own) is not loaded there
    (site / "zz_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    return python


def test_the_installed_wheel_works_outside_the_clone(installed, tmp_path):
    env = {key: value for key, value in os.environ.items() if key not in ("PYTHONPATH", "PYTHONHOME")}
    env.setdefault("MUJOCO_GL", "egl")
    result = subprocess.run([installed, "-c", USE], check=True, capture_output=True, text=True, cwd=tmp_path, env=env)
    used = json.loads(result.stdout.strip().splitlines()[-1])
    venv = installed.parents[1]
    assert Path(used["spf_rl"]).is_relative_to(venv) and Path(used["envs"]).is_relative_to(venv)  # the installed copy
    manifest = json.loads((CLONE / "checkpoints" / "manifest.json").read_text())
    assert used["names"] == sorted(manifest["names"]) and used["quick_episodes"] == 96 and used["batch"] == []


def test_the_wheel_carries_what_the_names_load_and_the_presets(installed):
    package = next(installed.parents[1].glob("lib/python*/site-packages/spf_rl"))
    manifest = json.loads((package / "checkpoints" / "manifest.json").read_text())
    shipped = {str(p.relative_to(package / "checkpoints")) for p in (package / "checkpoints").rglob("*.pt")}
    assert shipped == set(manifest["names"].values())  # the named files, once each; not the whole directory
    presets = {p.name for p in (package / "presets").glob("*.yaml")}
    assert presets == {p.name for p in (CLONE / "recipes" / "configs").glob("*.yaml")}
