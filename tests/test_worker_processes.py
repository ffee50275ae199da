"""envs.worker_processes: the package's worker processes fork from a server that has imported torch,
TorchRL and the env once (where the platform has a fork server)."""
from __future__ import annotations

import pytest

from envs.tensor_store import worker_pool
from envs.worker_processes import PRELOAD, start_method


@pytest.mark.skipif(start_method() != "forkserver", reason="no fork server on this platform: workers are spawned")
def test_a_worker_starts_with_the_preloaded_modules_imported():
    """Asked before it imports anything itself (``eval`` of a builtin expression), a worker already holds the
    env's module: it forked from the server rather than importing anew."""
    with worker_pool(1) as pool:
        modules = pool.submit(eval, "sorted(__import__('sys').modules)").result()
    assert {"torch", "torchrl.envs", "envs.nav_env"} <= set(modules) and "envs.nav_env" in PRELOAD
