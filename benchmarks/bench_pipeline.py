"""Benchmark: the learning pipelines' old and new paths side by side, in one invocation (issue #10 point 5).

*Old* is the commit before issue #10's first change (:data:`BASELINE_COMMIT`,
``--baseline``), run from a ``git worktree`` of it (``--baseline-dir``, reused when
it is already there at that commit); *new* is the working tree. Both trees share
module names (``envs``, ``spf_rl``), so each runs in its own child process with
``PYTHONPATH`` pointing at it (``benchmarks/bench_pipeline_worker.py``, the same
script for both, calling only what both trees have), with the same worker counts
and episode counts (:class:`Sizes`). Measures:

* ``dataset_generation`` (episodes/s): ``EpisodeDataset.build`` of a BC dataset into a
  fresh directory, ``--workers`` processes;
* ``dagger_collection`` (episodes/s): one DAgger round's collection with the learner
  driving (``spf_rl.train.dagger._collect_round``, ``beta = 0``);
* ``evaluation`` (episodes/s): ``evaluate_policy`` of the learner;
* ``evaluation_repeat`` (episodes/s): a second evaluation of the same episodes, as
  every validation of a training run after the first (the new tree reads the episode
  store the first one kept under ``store_root``);
* ``bc_training`` (labelled steps/s): expert-labelled (``mask``-ed) steps through
  ``bc_loss`` + backward + Adam step per second, at each tree's default batch size;
* ``collection`` (frames/s): the learner in ``make_collector`` with the expert's
  labels and ``paper`` noise (from a demo store with policy-side look-up where the tree
  has one, else the default env), and the raw render loop (``bench_env_paths.bench_raw``)
  in the same process, as the reference of the ratio.

The learner is each tree's default SPF model with random weights. Each figure is
the median of ``--repeats`` (at least 3) repeats interleaved between the trees
(old, new, old, new, ...). Speed-ups are new/old.

Targets of the issue (ratios measured in one run on 2 cores), recorded in the
JSON's ``targets`` with whether each holds:

* dataset generation >= 4x old; evaluation >= 4x old; BC training >= 1.5x old;
* collection as the pipelines run it >= 1.0x the raw render loop (the new tree's).

Writes ``benchmarks/results/pipeline.json`` (or ``--output``), atomically::

    {"baseline_commit": sha, "quick": bool, "raw_fps": x,
     "measures": {name: {"old": x, "new": x, "unit": "...", ...}},
     "speedups": {"dataset_generation": x, "dagger_collection": x, "evaluation": x, "bc_training": x},
     "store_lookup_ratio_to_raw": x, "targets": {...}, "setup": {...}, "machine": {...}, "runs": {...}}

Usage::

    python benchmarks/bench_pipeline.py                    # sized for well under an hour on 2 cores
    python benchmarks/bench_pipeline.py --quick            # sized for at most 10 minutes on 2 idle cores

(Both sizes are estimates from single measures timed on a loaded machine; neither run
has been timed on idle cores yet.)
    python benchmarks/bench_pipeline.py --only evaluation,bc_training --repeats 5
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

# this checkout's recipes; never its packages here: the workers import this module, and each
# must import ``envs`` and ``spf_rl`` from its own tree (its ``PYTHONPATH``)
from bench_baseline import SIDES, baseline_worktree, interleaved_runs, resolve_commit, run_json_child

ROOT = Path(__file__).resolve().parents[1]
#: The commit before issue #10's first change: the "old" paths.
BASELINE_COMMIT = "5b5e344"
RESULTS = ROOT / "benchmarks" / "results" / "pipeline.json"
#: Where the baseline's worktree is made (and reused by later runs).
BASELINE_DIR = ROOT / "runs" / "bench_pipeline" / "baseline"
WORKER = Path(__file__).resolve().parent / "bench_pipeline_worker.py"
#: Repeats per tree: each figure is the median of at least this many.
MIN_REPEATS = 3
#: Seconds one worker run may take before the benchmark gives up.
WORKER_TIMEOUT_S = 3600

logger = logging.getLogger("bench_pipeline")

#: Each measure and the unit of its figure.
UNITS = {
    "dataset_generation": "episodes/s",
    "dagger_collection": "episodes/s",
    "evaluation": "episodes/s",
    "evaluation_repeat": "episodes/s",
    "bc_training": "labelled steps/s",
    "collection": "frames/s",
}
MEASURES = tuple(UNITS)
#: The measures whose new/old ratio goes to ``speedups``.
SPEEDUPS = ("dataset_generation", "dagger_collection", "evaluation", "evaluation_repeat", "bc_training")
#: The issue's targets: (minimum, what is compared).
TARGETS = {
    "dataset_generation": (4.0, "speed-up new/old"),
    "evaluation": (4.0, "speed-up new/old"),
    "bc_training": (1.5, "speed-up new/old"),
    "collection": (1.0, "new collection frames/s over the raw render loop's (store_lookup_ratio_to_raw)"),
}


@dataclass(frozen=True)
class Sizes:
    """What every measure plays, the same for both trees.

    Args:
        dataset_episodes: episodes of the BC dataset built (``dataset_generation``,
            and the dataset ``bc_training`` samples from).
        dagger_episodes: episodes of the DAgger round collected.
        eval_episodes: episodes evaluated.
        bc_steps: timed gradient steps (after ``bc_warmup_steps``).
        bc_warmup_steps: gradient steps before timing.
        collection_batches: timed collector batches (after one warm-up batch).
        raw_chunks, raw_chunk_frames: the raw render loop's timed chunks (median kept).
        workers: worker processes of dataset generation (and of evaluation, in a tree whose
            ``EvalConfig`` has ``num_workers`` or ``num_collectors``).
        collectors: collectors of DAgger and of collection (``CollectorConfig``'s default;
            more than one fails in DAgger rounds of more than one batch, in both trees).
        num_agents: agents per collector (``CollectorConfig``'s default).
        eval_agents: agents stepped together by the evaluation (``EvalConfig``'s default).
        num_houses: houses of each split.
        demo_length, max_steps, image_size: the episodes' sizes.
        store_demos: demonstrations of the demo store, where a tree collects from one.
        seed: seed of weights, episodes and batches.
    """

    dataset_episodes: int = 512
    dagger_episodes: int = 256
    eval_episodes: int = 500
    bc_steps: int = 30
    bc_warmup_steps: int = 2
    collection_batches: int = 10
    raw_chunks: int = 5
    raw_chunk_frames: int = 2000
    workers: int = 2
    collectors: int = 1
    num_agents: int = 8
    eval_agents: int = 25
    num_houses: int = 4
    demo_length: int = 30
    max_steps: int = 50
    image_size: int = 64
    store_demos: int = 1000
    seed: int = 0


#: ``--quick``: sized for at most 10 minutes on 2 idle cores with 3 repeats of both trees (an
#: estimate from runs of single measures on a loaded machine, not yet timed on idle cores).
QUICK_SIZES = Sizes(
    dataset_episodes=128, dagger_episodes=64, eval_episodes=100, bc_steps=8, bc_warmup_steps=1,
    collection_batches=4, raw_chunks=3, raw_chunk_frames=800, store_demos=200,
)


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The options, checked before any work: the baseline resolved to its SHA (``args.baseline_sha``),
    ``args.measures`` the measures to run and ``args.sizes`` their :class:`Sizes`."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--baseline", default=BASELINE_COMMIT, help="the old paths' commit (default: %(default)s)")
    parser.add_argument("--baseline-dir", type=Path, default=BASELINE_DIR, help="its worktree, reused if already there")
    parser.add_argument("--quick", action="store_true", help="smaller sizes (at most 10 minutes on 2 idle cores)")
    parser.add_argument("--repeats", type=int, default=MIN_REPEATS, help=f"interleaved repeats per tree (>= {MIN_REPEATS})")
    parser.add_argument("--only", default=None, help=f"comma-separated measures (default: all of {', '.join(MEASURES)})")
    parser.add_argument("--workers", type=int, default=None, help="worker processes / collectors (default: 2)")
    parser.add_argument("--threads", type=int, default=None, help="torch threads in each worker (default: torch's)")
    parser.add_argument("--output", type=Path, default=RESULTS)
    parser.add_argument("--scratch", type=Path, default=None, help="datasets and stores (default: a temporary directory)")
    args = parser.parse_args(argv)
    if args.repeats < MIN_REPEATS:
        parser.error(f"--repeats must be >= {MIN_REPEATS} (each figure is a median of interleaved repeats), got {args.repeats}")
    args.measures = list(MEASURES) if args.only is None else [name.strip() for name in args.only.split(",") if name.strip()]
    unknown = [name for name in args.measures if name not in MEASURES]
    if unknown or not args.measures:
        parser.error(f"--only: unknown measure(s) {unknown or [args.only]}; choose from {', '.join(MEASURES)}")
    for name in ("workers", "threads"):
        if getattr(args, name) is not None and getattr(args, name) < 1:
            parser.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    try:
        args.baseline_sha = resolve_commit(args.baseline, ROOT)
    except ValueError as err:
        parser.error(f"--baseline: {err}")
    sizes = QUICK_SIZES if args.quick else Sizes()
    args.sizes = sizes if args.workers is None else dataclasses.replace(sizes, workers=args.workers)
    return args


def _median(values: list[float | None]) -> float | None:
    present = [value for value in values if value is not None]
    return float(statistics.median(present)) if present else None


def _ratio(numerator: float | None, denominator: float | None) -> float | None:
    return numerator / denominator if numerator is not None and denominator else None


def evaluate_targets(speedups: dict[str, float | None], ratio_to_raw: float | None) -> dict:
    """Each target of the issue: its minimum, the measured figure (``None``: not measured) and whether it holds."""
    measured = {**speedups, "collection": ratio_to_raw}
    return {
        name: {
            "target": minimum,
            "of": what,
            "measured": measured.get(name),
            "holds": None if measured.get(name) is None else measured[name] >= minimum,
        }
        for name, (minimum, what) in TARGETS.items()
    }


def summarise(runs: dict[str, list[dict]], measures: Sequence[str]) -> dict:
    """Medians over repeats, speed-ups, the raw loop, the ratio to it and the targets, from the workers' outputs
    (``runs[side]``: one output per repeat, in order)."""
    table = {}
    for name in measures:
        repeats = {side: [run["measures"][name]["value"] for run in runs[side]] for side in SIDES}
        old, new = _median(repeats["old"]), _median(repeats["new"])
        table[name] = {
            "old": old,
            "new": new,
            "unit": UNITS[name],
            "new_over_old": _ratio(new, old),
            "old_repeats": repeats["old"],
            "new_repeats": repeats["new"],
        }
    speedups = {name: table[name]["new_over_old"] if name in table else None for name in SPEEDUPS}
    raw = {
        side: [run["measures"]["collection"]["raw_fps"] for run in runs[side]] if "collection" in table else []
        for side in SIDES
    }
    raw_fps = _median(raw["new"])
    ratio = _ratio(table["collection"]["new"], raw_fps) if "collection" in table else None
    return {
        "raw_fps": raw_fps,
        "measures": table,
        "speedups": speedups,
        "store_lookup_ratio_to_raw": ratio,
        "targets": evaluate_targets(speedups, ratio),
        "raw_loop": {
            "what": "benchmarks/bench_env_paths.py bench_raw (working tree's code) run in each tree's collection worker; "
            "raw_fps and the ratio use the new tree's",
            "old_tree_fps": _median(raw["old"]),
            "old_repeats": raw["old"],
            "new_repeats": raw["new"],
            "old_collection_ratio_to_its_raw": _ratio(table["collection"]["old"], _median(raw["old"])) if raw["old"] else None,
        },
        "collection_path": {side: runs[side][0]["branches"].get("collection") for side in SIDES} if raw["new"] else None,
    }


def _worker_argv(measures: Sequence[str], sizes: Sizes, scratch: Path, threads: int | None) -> list[str]:
    argv = [str(WORKER), "--measures", ",".join(measures), "--sizes", json.dumps(asdict(sizes)), "--scratch", str(scratch)]
    return argv + (["--threads", str(threads)] if threads is not None else [])


def run_benchmark(args: argparse.Namespace, trees: dict[str, Path], scratch: Path) -> dict[str, list[dict]]:
    """Every repeat of every tree's worker, interleaved; the workers' outputs by side."""

    def run(side: str, repeat: int) -> dict:
        start = time.perf_counter()
        output = run_json_child(
            _worker_argv(args.measures, args.sizes, scratch / side, args.threads), trees[side], timeout=WORKER_TIMEOUT_S
        )
        if "spf_rl_file" not in output:
            raise RuntimeError(f"the {side} worker did not report where it imported spf_rl from.")
        imported = Path(output["spf_rl_file"]).resolve()
        if not imported.is_relative_to(Path(trees[side]).resolve()):
            raise RuntimeError(f"the {side} worker imported spf_rl from {imported}, not from its tree {trees[side]}.")
        figures = ", ".join(f"{name} {m['value']:.1f} {m['unit']}" for name, m in output["measures"].items())
        logger.info("repeat %d/%d %s (%.0f s): %s", repeat + 1, args.repeats, side, time.perf_counter() - start, figures)
        return {**output, "wall_seconds": time.perf_counter() - start}

    return interleaved_runs(run, args.repeats)


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
        scratch = args.scratch or Path(temporary)
        runs = run_benchmark(args, {"old": worktree, "new": ROOT}, scratch)
    machine, note = load.finish()
    result = {
        "baseline_commit": args.baseline_sha,
        "quick": args.quick,
        **summarise(runs, args.measures),
        "setup": {
            "measures": args.measures,
            "repeats": args.repeats,
            "order": "interleaved: old, new, old, new, ...",
            "sizes": asdict(args.sizes),
            "torch_threads": {side: runs[side][0]["torch_threads"] for side in SIDES},
            "baseline_worktree": str(args.baseline_dir),
            "branches": {side: runs[side][0]["branches"] for side in SIDES},
            "learner": "each tree's ModelConfig() SPF policy, random weights (torch.manual_seed(sizes.seed))",
        },
        "machine": machine,
        "notes": [note] if note else [],
        "wall_seconds": time.perf_counter() - start,
        "command": "python benchmarks/bench_pipeline.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "runs": runs,
    }
    args.output.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(args.output, result, default=str)
    for name, target in result["targets"].items():
        logger.info("target %s >= %.1f: measured %s, holds %s", name, target["target"], target["measured"], target["holds"])
    logger.info("wrote %s", args.output)
    return result


if __name__ == "__main__":
    main()
