"""How long env worker processes take to start: a 2-worker ``ParallelEnv`` of
:class:`~envs.nav_env.PathFollowEnv` built, reset and stepped once, then closed, with ``spawn`` and
with the package's start method (:func:`envs.worker_processes.start_method`, a fork server that
preloads torch, TorchRL and the env).

Each method runs in a child process of its own (a fork server lives as long as its parent), which
starts its env ``--repeats`` times: the first start pays for the server, the later ones are what
every further ``ParallelEnv`` of the process pays. Written to ``--output`` with the ratio of the
later starts' medians (package / spawn), the figure to compare across machines.

Usage::

    python benchmarks/bench_worker_start.py     # -> benchmarks/results/worker_start.json
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

RESULTS = Path("benchmarks/results/worker_start.json")
#: The env's sizes (small: the start is what is timed, not the steps).
ENV = dict(split="train", num_houses=2, demo_length=5, max_steps=8, image_size=32)


def time_starts(method: str, repeats: int) -> list[float]:
    """Seconds of each of ``repeats`` starts of a 2-worker env with ``method`` (``"package"``: the package's)."""
    import multiprocessing

    from torchrl.envs import ParallelEnv

    from envs.nav_env import PathFollowEnv
    from envs.worker_processes import start_method

    chosen = start_method() if method == "package" else method
    multiprocessing.get_context(chosen)  # refused here if the platform lacks it
    seconds = []
    for _ in range(repeats):
        start = time.perf_counter()
        env = ParallelEnv(2, partial(PathFollowEnv, **ENV), mp_start_method=chosen)
        env.rand_step(env.reset())
        env.close()
        seconds.append(time.perf_counter() - start)
    return seconds


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=4, help="starts per method (>= 2; default %(default)s)")
    parser.add_argument("--output", type=Path, default=RESULTS)
    parser.add_argument("--child", choices=("spawn", "package"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.repeats < 2:
        parser.error(f"--repeats must be >= 2 (the first start and the later ones), got {args.repeats}")
    if args.child:
        print(json.dumps(time_starts(args.child, args.repeats)))
        return {}
    from envs.atomic_io import atomic_write_json
    from envs.worker_processes import start_method

    runs = {}
    for method in ("spawn", "package"):
        out = subprocess.run([sys.executable, __file__, "--child", method, "--repeats", str(args.repeats)],
                             capture_output=True, text=True, check=True)
        seconds = json.loads(out.stdout.strip().splitlines()[-1])
        later = sorted(seconds[1:])
        runs[method] = {"seconds": seconds, "first": seconds[0], "later_median": later[len(later) // 2]}
    result = {
        "command": "python benchmarks/bench_worker_start.py" + "".join(f" {a}" for a in (argv if argv is not None else sys.argv[1:])),
        "package_start_method": start_method(), "env": ENV, "runs": runs,
        "later_start_ratio_package_to_spawn": runs["package"]["later_median"] / runs["spawn"]["later_median"],
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(args.output, result)
    return result


if __name__ == "__main__":
    main()
