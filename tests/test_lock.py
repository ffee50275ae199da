"""The lock (``constraints.txt``) against ``pyproject.toml`` and the installed packages.

``scripts/install.sh`` installs with ``pip install -c constraints.txt``, so every direct
dependency the README's commands install must be installed at its locked version, and
every locked version must lie in pyproject's ranges. ``bash scripts/lock.sh`` makes the
lock again.
"""
from __future__ import annotations

import tomllib
from importlib import metadata
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

ROOT = Path(__file__).resolve().parents[1]
LOCK = ROOT / "constraints.txt"
REGENERATE = "regenerate the lock with `bash scripts/lock.sh`, or reinstall with `bash scripts/install.sh EXTRAS`"


def read_lock(path: Path = LOCK) -> dict[str, str]:
    """``{canonical name: version}`` of a constraints file of ``name==version`` lines."""
    pins = {}
    for number, line in enumerate(path.read_text().splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        name, sep, version = line.partition("==")
        if not sep or not version:
            raise ValueError(f"{path.name}:{number}: {line!r} is not an exact pin name==version")
        pins[canonicalize_name(name)] = version.strip()
    return pins


def direct_requirements() -> list[Requirement]:
    """The dependencies and every extra's dependencies of ``pyproject.toml``."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    texts = [*project["dependencies"], *(r for extra in project["optional-dependencies"].values() for r in extra)]
    return [Requirement(text) for text in texts]


def lock_mismatches(pins: dict[str, str], installed: dict[str, str]) -> list[str]:
    """One message per installed direct dependency whose public version differs from its pin."""
    messages = []
    for requirement in direct_requirements():
        name = canonicalize_name(requirement.name)
        if name not in installed:
            continue  # an extra this environment did not install
        if name not in pins:
            messages.append(f"{requirement.name} {installed[name]} is installed but not in constraints.txt")
        elif Version(installed[name]).public != Version(pins[name]).public:
            messages.append(f"{requirement.name}: installed {installed[name]}, locked {pins[name]}")
    return messages


def installed_versions() -> dict[str, str]:
    return {canonicalize_name(dist.metadata["Name"]): dist.version for dist in metadata.distributions()}


def test_the_lock_pins_every_direct_dependency_inside_pyprojects_ranges():
    pins = read_lock()
    for requirement in direct_requirements():
        name = canonicalize_name(requirement.name)
        assert name in pins, f"{requirement.name} is a dependency in pyproject.toml but not in constraints.txt; {REGENERATE}"
        assert requirement.specifier.contains(pins[name], prereleases=True), (
            f"constraints.txt pins {requirement.name}=={pins[name]}, outside pyproject's {requirement}"
        )


def test_installed_direct_dependencies_match_the_lock():
    mismatches = lock_mismatches(read_lock(), installed_versions())
    assert not mismatches, "the environment differs from constraints.txt:\n  " + "\n  ".join(mismatches) + f"\n{REGENERATE}"


def test_a_drifted_package_is_named_with_both_versions(tmp_path):
    lock = tmp_path / "constraints.txt"
    lock.write_text("# a lock\nnumpy==2.4.6\ntorch==2.13.0\nscipy==1.17.1  # comment\n")
    pins = read_lock(lock)
    assert pins == {"numpy": "2.4.6", "torch": "2.13.0", "scipy": "1.17.1"}
    # a local build label (+cpu) is the same release; another release is a drift
    assert lock_mismatches(pins, {"numpy": "2.4.6", "torch": "2.13.0+cpu", "scipy": "1.17.1"}) == []
    assert lock_mismatches(pins, {"numpy": "2.5.0", "torch": "2.13.0", "scipy": "1.17.1"}) == [
        "numpy: installed 2.5.0, locked 2.4.6"
    ]
    assert "omegaconf 2.4.0 is installed but not in constraints.txt" in lock_mismatches(pins, {"omegaconf": "2.4.0"})
    lock.write_text("numpy>=2\n")
    with pytest.raises(ValueError, match=r"constraints.txt:1: 'numpy>=2' is not an exact pin"):
        read_lock(lock)
