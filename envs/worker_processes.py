"""How the package's worker processes start: env workers (``ParallelEnv``), dataset builders
(:func:`envs.tensor_store.worker_pool`).

Where the platform has it (Linux, macOS), they fork from a *fork server*: one clean process,
started at the first worker, that imports :data:`PRELOAD` (torch, TorchRL, the env) once. Each
later worker starts without importing them anew, as a ``spawn`` worker does: a 2-worker
``ParallelEnv`` of :class:`~envs.nav_env.PathFollowEnv`, started and stepped once, took 0.16x the
time of a ``spawn`` one (``python benchmarks/bench_worker_start.py``,
``benchmarks/results/worker_start.json``; the first start of a process also starts the server).
Like ``spawn``, and unlike ``fork``, no worker inherits the parent's threads, GL contexts or CUDA
state: the server has only imported modules.

A worker sees the environment variables of the moment the server started (the first worker of
the process), not later changes. Elsewhere (Windows) workers are spawned.
"""
from __future__ import annotations

import multiprocessing

#: Imported once by the fork server, before any worker forks from it. ``__main__`` (a script's own
#: module, imported as ``__mp_main__`` so that its ``if __name__ == "__main__"`` block does not run)
#: comes first, as ``spawn`` and the fork server's own default import it.
PRELOAD = ("__main__", "torch", "tensordict", "torchrl.envs", "envs.nav_env")


def start_method() -> str:
    """The start method of the package's worker processes: ``"forkserver"`` where the platform has it
    (its server preloads :data:`PRELOAD`), else ``"spawn"``.

    Examples:
        >>> start_method() in ("forkserver", "spawn")
        True
    """
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return "spawn"
    multiprocessing.get_context("forkserver").set_forkserver_preload(list(PRELOAD))
    return "forkserver"


def worker_context() -> multiprocessing.context.BaseContext:
    """The multiprocessing context of :func:`start_method` (for ``concurrent.futures`` pools).

    Examples:
        >>> worker_context().get_start_method() == start_method()
        True
    """
    return multiprocessing.get_context(start_method())


__all__ = ["PRELOAD", "start_method", "worker_context"]
