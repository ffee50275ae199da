"""Benchmark: the SPF policy's speed at a baseline commit and in the working tree, side by side.

Measures, in one invocation on one machine, with the same inputs and thread count:

* ``bc_training``: labelled steps per second through a BC update (sequence mode
  over ``[episodes, steps]``, cross-entropy, backward, Adam step);
* ``step_mode``: agent steps per second of step-mode inference (what a collector
  runs), memory encoded at the first step and carried after.

The baseline runs from a ``git worktree`` of ``--baseline`` (default: the commit
before the policy was split into TensorDict parts), imported through
``PYTHONPATH``; each figure is the median of ``--repeats`` interleaved runs.
Writes ``benchmarks/results/policy_parts.json``.

Usage::

    python benchmarks/bench_policy.py            # a few minutes on 2 CPU cores
    python benchmarks/bench_policy.py --quick
"""
from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

from bench_baseline import baseline_worktree, interleaved_runs, resolve_commit, run_json_child

from envs.atomic_io import atomic_write_json

ROOT = Path(__file__).resolve().parents[1]
#: The commit before the SPF policy was composed of TensorDict modules.
DEFAULT_BASELINE = "5b5e344"
RESULTS = ROOT / "benchmarks" / "results" / "policy_parts.json"


def measure(episodes: int, steps: int, iterations: int, threads: int) -> dict[str, float]:
    """Run in a child process: steps/s of BC training and of step-mode inference for the importable ``spf_rl``."""
    import time

    import torch
    from tensordict import TensorDict
    from torchrl.modules import set_recurrent_mode

    from spf_rl.modules import SPFConfig, SPFPolicy

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    config = SPFConfig(sparsity=0.8, initial_pointer_step=0.9)
    policy = SPFPolicy(config)
    n, size = config.demo_length, config.image_size[0]
    generator = torch.Generator().manual_seed(0)
    frames = torch.randint(0, 256, (episodes, steps, size, size, 3), dtype=torch.uint8, generator=generator)
    demo = torch.randint(0, 256, (episodes, 1, n, size, size, 3), dtype=torch.uint8, generator=generator)
    try:  # the layout of the tree under test: HWC, or CHW before the pixel-layout change
        policy(TensorDict({"pixels": frames[:1, 0], "demo_frames": demo[:1, 0], "demo_actions": torch.zeros(1, n, dtype=torch.long)}, [1]))
    except ValueError:
        frames, demo = frames.permute(0, 1, 4, 2, 3), demo.permute(0, 1, 2, 5, 3, 4)
    is_init = torch.zeros(episodes, steps, 1, dtype=torch.bool)
    is_init[:, 0] = True
    batch = TensorDict(
        {
            "pixels": frames,
            "demo_frames": demo.expand(-1, steps, *demo.shape[2:]),
            "demo_actions": torch.randint(0, 3, (episodes, 1, n), generator=generator).expand(-1, steps, -1),
            "is_init": is_init,
        },
        [episodes, steps],
    )
    labels = torch.randint(0, 3, (episodes, steps), generator=generator)
    optimizer = torch.optim.Adam(policy.parameters(), lr=1e-4)

    def train_step() -> None:
        with set_recurrent_mode(True):
            logits = policy(batch.clone(False))["logits"]
        loss = torch.nn.functional.cross_entropy(logits.reshape(-1, logits.shape[-1]), labels.reshape(-1))
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    def inference_episode() -> None:
        state = TensorDict({}, [episodes])
        with torch.no_grad():
            for t in range(steps):
                out = policy(batch[:, t].clone(False).update(state))
                state = out["next"].exclude("pixels")

    results = {}
    for name, run, per_call in (("bc_training", train_step, episodes * steps), ("step_mode", inference_episode, episodes * steps)):
        run()  # warm-up
        start = time.perf_counter()
        for _ in range(iterations):
            run()
        results[name] = per_call * iterations / (time.perf_counter() - start)
    return results


def _run_child(tree: Path, args: argparse.Namespace) -> dict[str, float]:
    code = (
        f"import json, bench_policy; "
        f"print(json.dumps(bench_policy.measure({args.episodes}, {args.steps}, {args.iterations}, {args.threads})))"
    )
    return run_json_child(["-c", code], tree, after=[Path(__file__).resolve().parent])


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--baseline", default=DEFAULT_BASELINE, help="git commit to compare against")
    parser.add_argument("--quick", action="store_true", help="smaller batches and fewer repeats")
    parser.add_argument("--repeats", type=int, default=3, help="interleaved runs per tree (median kept)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads in each run")
    parser.add_argument("--output", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    args.episodes, args.steps, args.iterations = (4, 20, 2) if args.quick else (16, 50, 3)
    if args.repeats < 1 or args.threads < 1:
        parser.error("--repeats and --threads must be >= 1")
    try:
        baseline = resolve_commit(args.baseline, ROOT)
    except ValueError as err:
        parser.error(f"--baseline: {err}")
    with baseline_worktree(ROOT, baseline) as worktree:  # a temporary worktree, removed afterwards
        runs = interleaved_runs(lambda side, _: _run_child(worktree if side == "old" else ROOT, args), args.repeats)
    measures = {
        name: {
            "old": statistics.median(run[name] for run in runs["old"]),
            "new": statistics.median(run[name] for run in runs["new"]),
            "unit": "labelled steps/s" if name == "bc_training" else "agent steps/s",
        }
        for name in runs["old"][0]
    }
    result = {
        "baseline_commit": baseline,
        "quick": args.quick,
        "setup": {"episodes": args.episodes, "steps": args.steps, "iterations": args.iterations, "threads": args.threads, "repeats": args.repeats},
        "measures": measures,
        "ratios_new_over_old": {name: m["new"] / m["old"] for name, m in measures.items()},
        "runs": runs,
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(args.output, result)
    print(json.dumps(result["ratios_new_over_old"], indent=2))
    return result


if __name__ == "__main__":
    main()
