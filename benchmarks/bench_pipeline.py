"""Benchmark: the learning pipelines against this machine's limits, in one invocation.

Each pipeline figure is a ratio to a reference measured in the same run, so it
carries from one machine of a kind to another:

* **collection** (``ratios_to_raw``): frames rendered per second by BC dataset
  generation, one DAgger round's collection (the learner driving) and evaluation,
  each divided by the frames per second of the raw render loop of one process
  (pose update, render, uint8 tensor; ``bench_env_paths.bench_raw``);
* **training**: the achieved FLOP/s of the BC training step (the FLOPs of the timed
  steps counted from the model, forward and backward), divided by the FLOP/s of a dense
  fp32 matmul of size 2048 at the training's thread count (``fraction_of_matmul``); and
  its ceiling, the same FLOPs over the seconds of the step's matmuls and convolutions
  replayed alone (``kernel_fraction_of_matmul``; ``kernel_share_of_step``: those seconds
  over the step's, :mod:`kernel_ceiling`).

``baseline`` is the training speed of :data:`BASELINE_COMMIT` (``--baseline``: main
when issue #30 was filed), run from a ``git worktree`` of it in the same invocation,
for the training speed-up (``training_speedup``: labelled steps/s new / baseline).
Every figure is the median of ``--repeats`` (at least 3) repeats, interleaved
(baseline training, then the working tree's measures, then again). Each repeat runs
in fresh child processes (``benchmarks/bench_pipeline_worker.py``): the baseline's
training; the working tree's raw loop and collection pipelines; its matmul and training.

Writes ``benchmarks/results/pipeline.json`` (or ``--output``), atomically::

    {"raw_fps": x, "matmul_flops": x, "workers": n, "quick": bool,
     "ratios_to_raw": {"dataset_generation": x, "dagger_collection": x, "evaluation": x},
     "training": {"labelled_steps_per_s": x, "flops_per_s": x, "fraction_of_matmul": x,
                  "kernel_fraction_of_matmul": x, "kernel_share_of_step": x},
     "baseline": {"commit": sha, "labelled_steps_per_s": x},
     "training_speedup": x, "targets": {...}, "measures": {...}, "setup": {...}, "runs": {...}}

Usage::

    python benchmarks/bench_pipeline.py            # the default sizes
    python benchmarks/bench_pipeline.py --quick    # at most 10 minutes on 2 idle cores
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import statistics
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Sequence

from bench_baseline import BASELINE_COMMIT, BASELINE_DIR, baseline_worktree, resolve_commit, run_json_child

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "pipeline.json"
WORKER = Path(__file__).resolve().parent / "bench_pipeline_worker.py"
#: Repeats: each figure is the median of at least this many.
MIN_REPEATS = 3
#: Seconds one child may take before the benchmark gives up.
WORKER_TIMEOUT_S = 3600

logger = logging.getLogger("bench_pipeline")

#: Each measure and the unit of its figure, in the order a repeat runs them.
UNITS = {
    "raw": "frames/s",
    "matmul": "FLOP/s",
    "dataset_generation": "frames/s",
    "dagger_collection": "frames/s",
    "evaluation": "frames/s",
    "training": "labelled steps/s",
}
MEASURES = tuple(UNITS)
#: The collection pipelines, each reported as a ratio to the raw loop.
COLLECTION = ("dataset_generation", "dagger_collection", "evaluation")
#: What each child process of the working tree measures: the raw loop with the collection
#: pipelines, and the matmul with the training (at the same thread count; the baseline's
#: child runs ``training`` alone, so each tree's training runs in a fresh process).
CHILDREN = (("raw", *COLLECTION), ("matmul", "training"))
#: The issue's targets: figure -> minimum.
TARGETS = {
    "dataset_generation": 0.8,
    "dagger_collection": 0.6,
    "evaluation": 0.6,
    "training_speedup": 1.3,
    "fraction_of_matmul": 0.5,
}


@dataclass(frozen=True)
class Sizes:
    """What every measure plays.

    Args:
        dataset_episodes: episodes of the BC dataset built (``dataset_generation``; the dataset
            ``training`` samples from is built once per tree, untimed, at this size).
        dagger_episodes: episodes of the DAgger round collected.
        eval_episodes: episodes evaluated.
        train_steps: timed gradient steps (after ``train_warmup_steps``).
        train_warmup_steps: gradient steps before timing.
        raw_chunks, raw_chunk_frames: the raw render loop's timed chunks (median kept).
        workers: worker processes of dataset generation (evaluation runs ``EvalConfig()``'s collectors).
        collectors: collectors of the DAgger round (``None``: the measured tree's ``CollectorConfig`` default).
        num_agents: agents per DAgger collector (``None``: the measured tree's ``CollectorConfig`` default).
        eval_agents: agents stepped together by the evaluation (``None``: the measured tree's ``EvalConfig`` default).
        num_houses: houses of each split.
        demo_length, max_steps, image_size: the episodes' sizes (the defaults').
        seed: seed of weights, episodes and batches.
    """

    dataset_episodes: int = 512
    dagger_episodes: int = 256
    eval_episodes: int = 500
    train_steps: int = 40
    train_warmup_steps: int = 3
    raw_chunks: int = 5
    raw_chunk_frames: int = 2000
    workers: int = 2
    collectors: int | None = None
    num_agents: int | None = None
    eval_agents: int | None = None
    num_houses: int = 4
    demo_length: int = 30
    max_steps: int = 50
    image_size: int = 64
    seed: int = 0


#: ``--quick``: at most 10 minutes on 2 idle cores with 3 repeats.
QUICK_SIZES = Sizes(
    dataset_episodes=128, dagger_episodes=64, eval_episodes=100, train_steps=12, train_warmup_steps=2,
    raw_chunks=3, raw_chunk_frames=800,
)


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The options, checked before any work: the baseline resolved to its SHA (``args.baseline_sha``)
    and ``args.sizes`` the :class:`Sizes`."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--baseline", default=BASELINE_COMMIT, help="the training baseline's commit (default: %(default)s)")
    parser.add_argument("--baseline-dir", type=Path, default=BASELINE_DIR, help="its worktree, reused if already there")
    parser.add_argument("--quick", action="store_true", help="smaller sizes (at most 10 minutes on 2 idle cores)")
    parser.add_argument("--repeats", type=int, default=MIN_REPEATS, help=f"interleaved repeats (>= {MIN_REPEATS})")
    parser.add_argument("--workers", type=int, default=None, help="dataset generation's worker processes (default: 2)")
    parser.add_argument("--output", type=Path, default=RESULTS)
    parser.add_argument("--scratch", type=Path, default=None, help="datasets and stores (default: a temporary directory)")
    args = parser.parse_args(argv)
    if args.repeats < MIN_REPEATS:
        parser.error(f"--repeats must be >= {MIN_REPEATS} (each figure is a median of interleaved repeats), got {args.repeats}")
    if args.workers is not None and args.workers < 1:
        parser.error(f"--workers must be >= 1, got {args.workers}")
    try:
        args.baseline_sha = resolve_commit(args.baseline, ROOT)
    except ValueError as err:
        parser.error(f"--baseline: {err}")
    sizes = QUICK_SIZES if args.quick else Sizes()
    args.sizes = sizes if args.workers is None else dataclasses.replace(sizes, workers=args.workers)
    return args


def _median(values: list[float]) -> float | None:
    return float(statistics.median(values)) if values else None


def _ratio(numerator: float | None, denominator: float | None) -> float | None:
    return numerator / denominator if numerator is not None and denominator else None


def summarise(new: list[dict], baseline: list[dict]) -> dict:
    """Medians over repeats, the ratios and the targets, from the children's outputs (one per repeat).

    Each ratio is taken within a repeat (the pipeline and its reference measured minutes apart),
    and the median of those is reported; ``measures`` holds every repeat's figures.
    """

    def values(runs: list[dict], name: str, key: str = "value") -> list[float]:
        return [run["measures"][name][key] for run in runs]

    raw, matmul = values(new, "raw"), values(new, "matmul")
    ratios = {name: _median([v / r for v, r in zip(values(new, name), raw)]) for name in COLLECTION}
    flops = values(new, "training", "flops_per_s")
    labelled, base = _median(values(new, "training")), _median(values(baseline, "training"))
    speedup = _median([v / b for v, b in zip(values(new, "training"), values(baseline, "training"))])
    fraction = _median([f / m for f, m in zip(flops, matmul)])
    training_runs = [run["measures"]["training"] for run in new]
    kernel_fraction = _median(
        [run["kernel_flops"] / run["kernel_seconds"] / m for run, m in zip(training_runs, matmul) if run.get("kernel_seconds")]
    )
    kernel_share = _median([run["kernel_seconds"] / run["seconds"] for run in training_runs if run.get("kernel_seconds")])
    measured = {**ratios, "training_speedup": speedup, "fraction_of_matmul": fraction}
    return {
        "raw_fps": _median(raw),
        "matmul_flops": _median(matmul),
        "ratios_to_raw": ratios,
        "training": {
            "labelled_steps_per_s": labelled, "flops_per_s": _median(flops), "fraction_of_matmul": fraction,
            "kernel_fraction_of_matmul": kernel_fraction, "kernel_share_of_step": kernel_share,
        },
        "training_speedup": speedup,
        "targets": {
            name: {"target": minimum, "measured": measured[name], "holds": measured[name] >= minimum}
            for name, minimum in TARGETS.items()
        },
        "measures": {
            name: {"unit": UNITS[name], "median": _median(values(new, name)), "repeats": values(new, name)}
            for name in MEASURES
        },
        "baseline_training_repeats": values(baseline, "training"),
        "baseline_labelled_steps_per_s": base,
    }


def _child(measures: Sequence[str], sizes: Sizes, scratch: Path, tree: Path) -> dict:
    argv = [str(WORKER), "--measures", ",".join(measures), "--sizes", json.dumps(asdict(sizes)), "--scratch", str(scratch)]
    start = time.perf_counter()
    output = run_json_child(argv, tree, timeout=WORKER_TIMEOUT_S, after=[WORKER.parent])
    imported = Path(output["spf_rl_file"]).resolve()
    if not imported.is_relative_to(tree.resolve()):
        raise RuntimeError(f"a child imported spf_rl from {imported}, not from its tree {tree}.")
    figures = ", ".join(f"{name} {m['value']:.4g} {m['unit']}" for name, m in output["measures"].items())
    logger.info("%s (%.0f s): %s", tree, time.perf_counter() - start, figures)
    return {**output, "wall_seconds": time.perf_counter() - start}


def run_benchmark(args: argparse.Namespace, baseline_tree: Path, scratch: Path) -> tuple[list[dict], list[dict]]:
    """Every repeat, interleaved: the baseline's training, then the working tree's children
    (:data:`CHILDREN`); the working tree's outputs are merged into one per repeat."""
    new, baseline = [], []
    for repeat in range(args.repeats):
        logger.info("repeat %d/%d", repeat + 1, args.repeats)
        baseline.append(_child(["training"], args.sizes, scratch / "baseline", baseline_tree))
        outputs = [_child(names, args.sizes, scratch / "new", ROOT) for names in CHILDREN]
        merged = {**outputs[-1], "measures": {}, "wall_seconds": sum(output["wall_seconds"] for output in outputs)}
        for output in outputs:
            merged["measures"].update(output["measures"])
        new.append(merged)
    return new, baseline


def main(argv: Sequence[str] | None = None) -> dict:
    args = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    from bench_env_report import MachineLoad

    from envs.atomic_io import atomic_write_json

    start = time.perf_counter()
    load = MachineLoad.start()
    with baseline_worktree(ROOT, args.baseline_sha, args.baseline_dir) as worktree, tempfile.TemporaryDirectory(
        prefix="bench_pipeline-"
    ) as temporary:
        new, baseline = run_benchmark(args, worktree, args.scratch or Path(temporary))
    machine, note = load.finish()
    summary = summarise(new, baseline)
    result = {
        "raw_fps": summary.pop("raw_fps"),
        "matmul_flops": summary.pop("matmul_flops"),
        "workers": args.sizes.workers,
        "quick": args.quick,
        "ratios_to_raw": summary.pop("ratios_to_raw"),
        "training": summary.pop("training"),
        "baseline": {"commit": args.baseline_sha, "labelled_steps_per_s": summary.pop("baseline_labelled_steps_per_s")},
        **summary,
        "setup": {
            "repeats": args.repeats,
            "order": "interleaved: baseline training, then the working tree's measures, each repeat",
            "sizes": asdict(args.sizes),
            "torch_threads": new[0]["torch_threads"],
            "learner": "ModelConfig() SPF policy, random weights (torch.manual_seed(sizes.seed))",
            "frames": "demonstration frames + each episode's observations (reset and every step)",
        },
        "machine": machine,
        "notes": [note] if note else [],
        "wall_seconds": time.perf_counter() - start,
        "command": "python benchmarks/bench_pipeline.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "runs": {"new": new, "baseline": baseline},
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(args.output, result, default=str)
    for name, target in result["targets"].items():
        logger.info("target %s >= %.2f: measured %.3f, holds %s", name, target["target"], target["measured"], target["holds"])
    logger.info("wrote %s", args.output)
    return result


if __name__ == "__main__":
    main()
