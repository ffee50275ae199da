"""Shared test set-up: headless rendering, a fixed matplotlib back-end, small envs."""
from __future__ import annotations

import os
import runpy
import shutil
import sys
from collections.abc import Callable
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import pytest
import torch
from torch import nn

import envs  # noqa: F401  (selects the GL back-end before mujoco opens a context)
from spf_rl.evaluation import EPISODE_STORE_ROOT_ENV
from spf_rl.modules.encoder import ImageEncoder

#: Scripts that made the committed test data: run by hand, never collected (``--doctest-modules``).
collect_ignore_glob = ["data/*.py"]


def _share_the_cores_between_xdist_workers() -> None:
    """Under pytest-xdist, give each worker its share of the cores for torch's intra-op threads.

    Otherwise every worker (and every process it spawns: env workers, collectors, Ray actors,
    benchmark children) runs one OpenMP thread per core, and N workers oversubscribe the
    machine N-fold: measured on 2 cores with 2 workers, the torch-heavy tests ran 2.5-6x
    slower. The children inherit ``OMP_NUM_THREADS``; an ``OMP_NUM_THREADS`` set by the user
    is left as it is.
    """
    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers <= 1 or "OMP_NUM_THREADS" in os.environ:
        return
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    threads = max(1, cores // workers)
    os.environ["OMP_NUM_THREADS"] = str(threads)
    torch.set_num_threads(threads)


_share_the_cores_between_xdist_workers()


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--full-samples",
        action="store_true",
        default=False,
        help="run the property tests on their full samples (1,000 houses, 500 expert episodes per rate)",
    )


@pytest.fixture(scope="session")
def full_samples(request: pytest.FixtureRequest) -> bool:
    """Whether the property tests take their full samples (``pytest --full-samples``)."""
    return bool(request.config.getoption("--full-samples"))


@pytest.fixture(scope="session")
def ray_cluster():
    """One local Ray cluster (2 CPUs) shared by the Ray tests of a test process, shut down at its end.

    Each Ray test shuts its collectors down (their actors free their CPUs for the next test).
    """
    import ray

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    yield ray
    ray.shutdown()


@pytest.fixture
def tf32_flags():
    """Saves the two TF32 flags of CUDA and restores them after the test.

    ``monkeypatch.setattr`` cannot undo them: ``torch.backends.cuda.matmul.allow_tf32``
    is served by the module object's ``__getattr__`` (torch 2.13), so monkeypatch finds
    no attribute to restore and its teardown raises ``AttributeError``.
    """
    saved = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    yield
    torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved


@pytest.fixture(autouse=True, scope="session")
def _episode_stores_in_a_temporary_directory(tmp_path_factory):
    """Evaluation episode stores of the tests (and of the recipes they run) go to a temporary
    directory, never to the checkout's ``data/episodes``."""
    previous = os.environ.get(EPISODE_STORE_ROOT_ENV)
    os.environ[EPISODE_STORE_ROOT_ENV] = str(tmp_path_factory.mktemp("episode_stores"))
    yield
    if previous is None:
        os.environ.pop(EPISODE_STORE_ROOT_ENV, None)
    else:
        os.environ[EPISODE_STORE_ROOT_ENV] = previous


#: The repository root, where the recipes (``recipes/<name>.py``) run from.
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def run_recipe(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture):
    """``run_recipe(name, args) -> (status, stderr)``: ``recipes/<name>.py`` run as its script runs (its
    ``__main__`` block, :func:`runpy.run_path`) in this process, from the repository root; the status is
    its ``SystemExit`` code, 0 where it returned. A new interpreter would add about 4 s of CPU (torch's
    import) to each."""

    def run(name: str, args: list[str]) -> tuple[int, str]:
        monkeypatch.chdir(ROOT)
        monkeypatch.setattr(sys, "argv", [f"{name}.py", *args])
        capsys.readouterr()
        try:
            runpy.run_path(str(ROOT / "recipes" / f"{name}.py"), run_name="__main__")
        except SystemExit as exit_info:
            code = exit_info.code
            return (code if isinstance(code, int) else 1), capsys.readouterr().err
        return 0, capsys.readouterr().err

    return run


@pytest.fixture(scope="session")
def shared_build(tmp_path_factory: pytest.TempPathFactory) -> Callable[[str, Callable[[Path], object]], Path]:
    """``shared_build(name, build) -> directory``: ``build(directory)`` run once in the test session, by whichever
    pytest-xdist worker asks first. A worker asking meanwhile waits for it (a file lock); later ones find it done (a
    ``.built`` file, written once ``build`` has returned) and read what it wrote, never changing it. For costly
    read-only fixtures that tests of several workers share (an export, a training run)."""
    from filelock import FileLock

    base = tmp_path_factory.getbasetemp()
    root = (base.parent if "PYTEST_XDIST_WORKER" in os.environ else base) / "shared-builds"  # every worker's
    root.mkdir(exist_ok=True)

    def get(name: str, build: Callable[[Path], object]) -> Path:
        directory = root / name
        with FileLock(str(root / f"{name}.lock")):
            if not (root / f"{name}.built").is_file():
                shutil.rmtree(directory, ignore_errors=True)  # an interrupted build's
                build(directory)
                (root / f"{name}.built").touch()
        return directory

    return get


class CountingEncoder(nn.Module):
    """Wraps an encoder and counts the frames it encodes (tests of encode-once memory)."""

    def __init__(self, encoder: ImageEncoder):
        super().__init__()
        self.inner = encoder
        self.feature_dim = encoder.feature_dim
        self.frames = 0

    def check_frames(self, frames, name="frames"):
        self.inner.check_frames(frames, name)

    def forward(self, x):
        self.frames += x.reshape(-1, *x.shape[-3:]).shape[0]
        return self.inner(x)


@pytest.fixture(scope="session")
def unobstructed_route():
    """A function ``(actions, houses) -> (house, demo)``: ``actions`` driven noise-free from the
    spawn point of the first of ``houses`` train houses, at the first heading (in 20-degree
    steps) where every forward step moves its full 0.3 m (no wall touched)."""
    import numpy as np

    from envs.demos import demonstration_from_route, move_agents, nominal_motion
    from envs.expert import FORWARD, FORWARD_STEP_M
    from envs.scenes import build_house, split_seeds

    def make(actions, houses: int = 12):
        actions = np.asarray(actions)
        for seed in split_seeds("train", houses):
            house = build_house(seed)
            for heading in np.deg2rad(np.arange(0, 360, 20)):
                pose = np.array([[*house.spawn_xy, heading]])
                poses = [pose[0].copy()]
                for action in actions:
                    move_agents([house], pose, nominal_motion(np.array([action])))
                    poses.append(pose[0].copy())
                poses = np.array(poses)
                if np.allclose(np.hypot(*np.diff(poses[:, :2], axis=0)[actions == FORWARD].T), FORWARD_STEP_M, atol=1e-6):
                    return house, demonstration_from_route(house, poses, actions)
        raise AssertionError(f"no spawn point of {houses} train houses has room for the route")

    return make
