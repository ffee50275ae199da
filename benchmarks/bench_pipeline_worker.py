"""One child process of ``benchmarks/bench_pipeline.py``: run some measures, print one JSON line.

The driver runs this script with ``PYTHONPATH`` set to the tree it measures: the
working tree for every measure, and the baseline's ``git worktree`` for
``training`` only. ``training`` therefore calls only what the baseline has
(``EpisodeDataset.build`` and ``replay_buffer``, ``ModelConfig`` / ``spf_config`` /
``build_policy``, ``OptimConfig``, ``TrainingRun.train_epoch`` with ``bc_loss``): each tree
trains with its own training step at its own defaults.

Measures (each returns ``{"value": x, "unit": ..., ...}``):

* ``raw``: the raw render loop, one process (``bench_env_paths.bench_raw``): frames/s;
* ``matmul``: a dense fp32 ``torch.mm`` of :data:`MATMUL_SIZE` at this process's torch
  thread count (the training's): FLOP/s;
* ``dataset_generation``, ``dagger_collection``, ``evaluation``: frames rendered per
  second by the pipeline, counted from what it returns (:func:`frames_rendered`);
* ``training``: expert-labelled (``mask``-ed) steps/s through the tree's training step,
  and the FLOPs of the timed steps counted from the model
  (``torch.utils.flop_counter.FlopCounterMode`` over forward and backward, untimed); and
  the seconds of those steps' FLOP-carrying kernels replayed alone
  (:mod:`kernel_ceiling`: the ceiling of the step's FLOP/s with the same kernels).

Usage (the driver does this)::

    PYTHONPATH=<tree> python benchmarks/bench_pipeline_worker.py --measures training \\
        --sizes '{"train_steps": 4}' --scratch /tmp/scratch
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

from bench_pipeline import MEASURES, UNITS, Sizes

logger = logging.getLogger("bench_pipeline_worker")

#: Side of the square fp32 matrices of the matmul reference.
MATMUL_SIZE = 2048
#: Timed matmuls (the median kept), after one untimed.
MATMUL_REPEATS = 5


def frames_rendered(demo_frames: int, episode_steps: list[int]) -> int:
    """Frames a pipeline rendered: the demonstrations' frames, then each episode's observation
    at reset and after each of its steps.

    Examples:
        >>> frames_rendered(2 * 30, [10, 20])
        92
    """
    return demo_frames + sum(steps + 1 for steps in episode_steps)


def _given(**values) -> dict:
    """The values that are set (``None``: the tree's own default)."""
    return {name: value for name, value in values.items() if value is not None}


def _episode_sizes(sizes: Sizes) -> dict:
    return dict(demo_length=sizes.demo_length, max_steps=sizes.max_steps, image_size=sizes.image_size)


def build_learner(sizes: Sizes):
    """The tree's default SPF model (``ModelConfig()``) with random weights, for the episodes' sizes."""
    import torch

    from spf_rl.modules.registry import ModelConfig, build_policy, spf_config

    torch.manual_seed(sizes.seed)
    model = ModelConfig()
    return build_policy(model.name, spf_config(model, sizes.demo_length, sizes.image_size))


def _dataset_config(sizes: Sizes):
    from envs.episode_spec import EpisodeSpec
    from spf_rl.data import DatasetConfig

    episodes = EpisodeSpec(split="train", num_houses=sizes.num_houses, noise="paper", seed=sizes.seed, **_episode_sizes(sizes))
    return dataclasses.replace(DatasetConfig(), num_episodes=sizes.dataset_episodes, episodes=episodes)


def measure_raw(sizes: Sizes, scratch: Path) -> dict:
    """Frames/s of the raw render loop (pose update, render, uint8 tensor), one process."""
    from bench_env_paths import WARMUP_FRAMES, bench_raw

    from envs.scenes import split_seeds

    house = split_seeds("train", sizes.num_houses)[0]
    raw = bench_raw(house, sizes.image_size, sizes.raw_chunks, sizes.raw_chunk_frames, WARMUP_FRAMES, sizes.seed)
    return {"value": raw["fps"], **raw}


def measure_matmul(sizes: Sizes, scratch: Path) -> dict:
    """FLOP/s of a dense fp32 ``torch.mm`` of :data:`MATMUL_SIZE` at this process's thread count."""
    import torch

    generator = torch.Generator().manual_seed(sizes.seed)
    a, b = (torch.randn(MATMUL_SIZE, MATMUL_SIZE, generator=generator) for _ in range(2))
    torch.mm(a, b)
    seconds = []
    for _ in range(MATMUL_REPEATS):
        start = time.perf_counter()
        torch.mm(a, b)
        seconds.append(time.perf_counter() - start)
    flops = 2 * MATMUL_SIZE**3
    return {"value": flops / statistics.median(seconds), "size": MATMUL_SIZE, "threads": torch.get_num_threads()}


def measure_dataset_generation(sizes: Sizes, scratch: Path) -> dict:
    """Frames/s of ``EpisodeDataset.build`` into a fresh directory, ``sizes.workers`` processes
    (its demonstration store included)."""
    from spf_rl.data import EpisodeDataset

    config = _dataset_config(sizes)
    parent = Path(tempfile.mkdtemp(dir=scratch))
    start = time.perf_counter()
    dataset = EpisodeDataset.build(parent / "dataset", config, sizes.workers, progress=False)
    seconds = time.perf_counter() - start
    lengths = [int(length) for length in dataset.episodes["length"]]
    statistics_ = dataset.statistics()
    del dataset
    shutil.rmtree(parent)
    frames = frames_rendered(sizes.dataset_episodes * sizes.demo_length, lengths)
    return {"value": frames / seconds, "frames": frames, "seconds": seconds, **statistics_}


def measure_dagger_collection(sizes: Sizes, scratch: Path) -> dict:
    """Frames/s of one DAgger round's collection with the learner driving (``beta = 0``): its
    demonstrations rendered into the round's store, then its episodes played."""
    from spf_rl.train import dagger, dagger_rounds

    default = dagger.DAggerConfig()
    config = dataclasses.replace(
        default, episodes_per_round=sizes.dagger_episodes, progress=False, output_dir=str(scratch / "dagger"),
        seed=sizes.seed, device="cpu",
        env=dataclasses.replace(default.env, **_collection_env_values(sizes)),
        val=_sized(default.val, sizes),
        test=_sized(default.test, sizes),
        collector=dataclasses.replace(
            default.collector, **_given(num_collectors=sizes.collectors, num_agents=sizes.num_agents)
        ),
    )
    env = config.env
    round_config = dagger_rounds.RoundConfig(
        round_index=1, beta=0.0, num_episodes=config.episodes_per_round, episodes=env.episodes.replace(seed=sizes.seed),
    )
    round_dir = Path(tempfile.mkdtemp(dir=scratch)) / "round-01"
    policy = build_learner(sizes)
    start = time.perf_counter()
    episodes = dagger._collect_round(policy, config, round_config, round_dir)
    seconds = time.perf_counter() - start
    shutil.rmtree(round_dir.parent)
    lengths = [int(length) for length in episodes["length"]]
    frames = frames_rendered(len(lengths) * sizes.demo_length, lengths)
    return {
        "value": frames / seconds, "frames": frames, "episodes": len(lengths), "seconds": seconds,
        "num_collectors": config.collector.num_collectors, "num_agents": config.collector.num_agents,
    }


def measure_evaluation(sizes: Sizes, scratch: Path) -> dict:
    """Frames/s of ``evaluate_policy`` of the learner (greedy) on the test split, as ``EvalConfig()``
    runs it (its default collectors): its demonstrations rendered, then its episodes."""
    from envs.episode_spec import EpisodeSpec
    from spf_rl.evaluation import EvalConfig, evaluate_policy

    episodes = EpisodeSpec(split="test", noise="paper", seed=sizes.seed, num_houses=sizes.num_houses, **_episode_sizes(sizes))
    config = dataclasses.replace(
        EvalConfig(), episodes=episodes, num_episodes=sizes.eval_episodes, **_given(num_agents=sizes.eval_agents),
    )
    policy = build_learner(sizes)
    start = time.perf_counter()
    summary, records = evaluate_policy(policy, config)
    seconds = time.perf_counter() - start
    frames = frames_rendered(len(records) * sizes.demo_length, [record["steps"] for record in records])
    return {"value": frames / seconds, "frames": frames, "episodes": len(records), "seconds": seconds, "num_agents": config.num_agents}


def measure_training(sizes: Sizes, scratch: Path) -> dict:
    """Expert-labelled steps/s through the tree's BC training step (``TrainingRun.train_epoch`` with
    ``bc_loss``: loss, backward, clip, Adam, schedule) at the default batch (``OptimConfig()``), on a
    dataset built (untimed, once per scratch directory) from ``sizes``; and the FLOPs of those steps."""
    import torch
    from kernel_ceiling import KernelRecorder, replay_kernels
    from torch.utils.flop_counter import FlopCounterMode

    from spf_rl.data import EpisodeDataset
    from spf_rl.modules.registry import ModelConfig, spf_config
    from spf_rl.train.bc import bc_loss
    from spf_rl.train.run import OptimConfig, TrainingRun

    dataset = EpisodeDataset.build(scratch / "bc_data", _dataset_config(sizes), sizes.workers, progress=False)
    optim = OptimConfig()
    policy = build_learner(sizes)
    model = ModelConfig()
    total = sizes.train_warmup_steps + sizes.train_steps
    buffer = dataset.replay_buffer(optim.batch_size, seed=sizes.seed)
    batches = [buffer.sample() for _ in range(total)]
    output = Path(tempfile.mkdtemp(dir=scratch))
    run = TrainingRun(
        output, model.name, spf_config(model, sizes.demo_length, sizes.image_size), policy, optim, total, loss_fn=bc_loss
    )
    run.train_epoch(batches[: sizes.train_warmup_steps], sizes.train_warmup_steps, "warm-up", False)
    timed = batches[sizes.train_warmup_steps :]
    start = time.perf_counter()
    run.train_epoch(timed, len(timed), "timed", False)
    seconds = time.perf_counter() - start
    shutil.rmtree(output)
    labelled = sum(int(batch["steps", "mask"].sum()) for batch in timed)
    counter, recorder = FlopCounterMode(display=False), KernelRecorder()
    with counter, recorder:  # the same batches' forward and backward, counted and recorded (not timed)
        for batch in timed:
            loss, _ = bc_loss(policy, batch, amp=optim.amp)
            loss.backward()
    policy.zero_grad(set_to_none=True)
    flops = counter.get_total_flops()
    kernels = replay_kernels(recorder.calls, seed=sizes.seed)
    return {
        "value": labelled / seconds,
        "labelled_steps": labelled,
        "gradient_steps": len(timed),
        "batch_size": optim.batch_size,
        "seconds": seconds,
        "flops": flops,
        "flops_per_s": flops / seconds,
        "kernel_flops": kernels["flops"],
        "kernel_seconds": kernels["seconds"],
        "kernel_calls": kernels["calls"],
        "kernel_distinct_calls": kernels["distinct"],
        "threads": torch.get_num_threads(),
    }


def _sized(evaluation, sizes: Sizes):
    """An evaluation config of the benchmark's episode sizes (as its training episodes)."""
    return dataclasses.replace(evaluation, episodes=evaluation.episodes.replace(**_episode_sizes(sizes)))


def _collection_env_values(sizes: Sizes) -> dict:
    from envs.episode_spec import EpisodeSpec

    return dict(episodes=EpisodeSpec(split="train", noise="paper", num_houses=sizes.num_houses, **_episode_sizes(sizes)), with_expert=True)


MEASURE_FUNCTIONS: dict[str, Callable[[Sizes, Path], dict]] = {
    "raw": measure_raw,
    "matmul": measure_matmul,
    "dataset_generation": measure_dataset_generation,
    "dagger_collection": measure_dagger_collection,
    "evaluation": measure_evaluation,
    "training": measure_training,
}


def run_measures(names: list[str], sizes: Sizes, scratch: Path) -> dict:
    """Run ``names`` in order in this process; the worker's output (one JSON object)."""
    import torch

    import envs  # noqa: F401  (selects the headless GL back-end before any renderer)

    scratch.mkdir(parents=True, exist_ok=True)
    measures = {}
    for name in names:
        logger.info("measuring %s", name)
        measures[name] = {**MEASURE_FUNCTIONS[name](sizes, scratch), "unit": UNITS[name]}
        logger.info("%s: %.4g %s", name, measures[name]["value"], UNITS[name])
    return {"measures": measures, "torch_threads": torch.get_num_threads(), "spf_rl_file": sys.modules["spf_rl"].__file__}


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--measures", required=True, help=f"comma-separated, of {', '.join(MEASURES)}")
    parser.add_argument("--sizes", default="{}", help="JSON object of Sizes fields (the rest: defaults)")
    parser.add_argument("--scratch", type=Path, required=True, help="this tree's scratch directory (kept across repeats)")
    args = parser.parse_args(argv)
    names = [name for name in args.measures.split(",") if name]
    unknown = sorted(set(names) - set(MEASURES))
    if unknown:
        parser.error(f"--measures: unknown {unknown}; choose from {list(MEASURES)}")
    sizes = dataclasses.replace(Sizes(), **json.loads(args.sizes))
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    output = run_measures(names, sizes, args.scratch)
    print(json.dumps(output), flush=True)  # the one line the driver reads
    return output


if __name__ == "__main__":
    main()
