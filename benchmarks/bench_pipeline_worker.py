"""One tree's side of ``benchmarks/bench_pipeline.py``: run the pipeline measures, print one JSON line.

The driver runs this script twice per repeat, with ``PYTHONPATH`` set to the
baseline's worktree and to the working tree, so the same code measures both.
It therefore calls only what both trees have: at the baseline ``5b5e344`` and in
the working tree (checked when this was written):

* ``spf_rl.data``: ``DatasetConfig``, ``EpisodeDataset.build(root, config,
  num_workers, progress)``, ``EpisodeDataset.replay_buffer``;
* ``spf_rl.modules.registry`` (``spf_rl.train.models`` at the baseline): ``ModelConfig``,
  ``spf_config``, ``build_policy``;
* ``spf_rl.train.bc``: ``bc_loss(policy, batch)``; ``spf_rl.train.run`` (``spf_rl.train.bc`` at
  the baseline): ``OptimConfig``;
* ``spf_rl.train.dagger``: ``DAggerConfig``, ``ExpertMixturePolicy`` and
  ``_collect_round`` (one round's collection, as ``train_dagger`` runs it: at the
  baseline ``(policy, config, beta, seed)``, ``make_collector`` + ``collect_episodes``;
  where ``spf_rl.train.dagger_rounds.round_demo_config`` exists,
  ``(policy, config, round_config, round_dir)``: the round's episode store, then
  ``make_collector`` with it + ``gather_episode_steps``);
* ``spf_rl.train.collection``: ``CollectionEnvConfig``, ``CollectorConfig``,
  ``make_collector``;
* ``spf_rl.train.evaluation``: ``EvalConfig``, ``evaluate_policy``;
* from the working tree's ``benchmarks/bench_env_paths.py`` (not the tree's own):
  the raw render loop ``bench_raw`` and the collector timing loop
  ``bench_collector``, which import only ``envs`` names present in both trees.

Every config starts from the tree's own defaults (``dataclasses.replace`` of
``DatasetConfig()``, ``DAggerConfig()``, ``EvalConfig()``), with only the sizes of
:class:`Sizes` set, so each pipeline runs as it does by default. Where the trees
may differ the worker branches on what exists and says so in its output
(``branches``): for ``collection``, a tree whose ``make_collector`` takes
``demo_store`` collects from a demo store with ``demo_id`` only and the frames looked
up on the policy side (``FramesFromStore``), as PPO does; otherwise the default env
renders the demonstrations at each reset. Config fields
for worker processes that only a tree's ``EvalConfig`` has (``num_workers``,
``num_collectors``) are set to ``Sizes.workers`` and listed.

The learner is the tree's default SPF model (``ModelConfig()``) with random weights
(``torch.manual_seed(seed)``), acting greedily (``ExpertMixturePolicy`` with
``beta = 0``, as DAgger's learner-driven rounds).

Usage (the driver does this)::

    PYTHONPATH=<tree> python benchmarks/bench_pipeline_worker.py --measures evaluation \\
        --sizes '{"eval_episodes": 8}' --scratch /tmp/scratch
"""
from __future__ import annotations

import argparse
import dataclasses
import inspect
import json
import logging
import shutil
import sys
import tempfile
import time
from dataclasses import fields
from functools import partial
from pathlib import Path
from typing import Any, Callable

from bench_pipeline import MEASURES, UNITS, Sizes

logger = logging.getLogger("bench_pipeline_worker")

#: Config fields for worker processes that a tree's ``EvalConfig`` may have; set to ``Sizes.workers`` where they exist.
WORKER_FIELDS = ("num_workers", "num_collectors")


def configured(default: Any, values: dict, optional: dict, applied: list[str]) -> Any:
    """``default`` (a tree's config dataclass) with ``values`` set, and those of ``optional``
    that are fields of it (their names go to ``applied``)."""
    names = {f.name for f in fields(default)}
    present = {key: value for key, value in optional.items() if key in names}
    applied.extend(f"{type(default).__name__}.{key}={value!r}" for key, value in present.items())
    return dataclasses.replace(default, **values, **present)


def _episode_sizes(sizes: Sizes) -> dict:
    return dict(demo_length=sizes.demo_length, max_steps=sizes.max_steps, image_size=sizes.image_size)


def build_learner(sizes: Sizes):
    """The tree's default SPF model (``ModelConfig()``) with random weights, for the episodes' sizes."""
    import torch

    try:
        from spf_rl.modules.registry import ModelConfig, build_policy, spf_config
    except ImportError:  # the baseline tree, where the registry was spf_rl.train.models
        from spf_rl.train.models import ModelConfig, build_policy, spf_config

    torch.manual_seed(sizes.seed)
    model = ModelConfig()
    return build_policy(model.name, spf_config(model, sizes.demo_length, sizes.image_size))


def _dataset_config(sizes: Sizes, applied: list[str]):
    from spf_rl.data import DatasetConfig

    values = dict(
        num_episodes=sizes.dataset_episodes, split="train", num_houses=sizes.num_houses, noise="paper",
        seed=sizes.seed, **_episode_sizes(sizes),
    )
    return configured(DatasetConfig(), values, {}, applied)


def measure_dataset_generation(sizes: Sizes, scratch: Path, branches: dict) -> dict:
    """Episodes/s of ``EpisodeDataset.build`` into a fresh directory (worker processes included).

    The first build of this tree's scratch is kept as ``bc_training``'s dataset.
    """
    from spf_rl.data import EpisodeDataset

    applied: list[str] = []
    config = _dataset_config(sizes, applied)
    keep = scratch / "bc_data"
    parent = Path(tempfile.mkdtemp(dir=scratch))
    root = parent / "dataset"
    start = time.perf_counter()
    dataset = EpisodeDataset.build(root, config, sizes.workers, progress=False)
    seconds = time.perf_counter() - start
    statistics = dataset.statistics()
    del dataset
    if not keep.exists():
        root.rename(keep)
    shutil.rmtree(parent)
    branches["dataset_generation"] = applied
    return {"value": sizes.dataset_episodes / seconds, "episodes": sizes.dataset_episodes, "seconds": seconds, **statistics}


def measure_dagger_collection(sizes: Sizes, scratch: Path, branches: dict) -> dict:
    """Episodes/s of one DAgger round's collection with the learner driving (``beta = 0``)."""
    from spf_rl.train import dagger

    applied: list[str] = []
    default = dagger.DAggerConfig()
    values = dict(
        episodes_per_round=sizes.dagger_episodes, progress=False, output_dir=str(scratch / "dagger"), seed=sizes.seed,
        env=dataclasses.replace(default.env, **_collection_env_values(sizes)),
        collector=dataclasses.replace(default.collector, num_collectors=sizes.collectors, num_agents=sizes.num_agents),
    )
    config = configured(default, values, {"device": "cpu"}, applied)
    policy = build_learner(sizes)
    try:
        from spf_rl.train import dagger_rounds
    except ImportError:  # the baseline tree: rounds are batches from a reset, in spf_rl.train.dagger
        dagger_rounds = None

    start = time.perf_counter()
    if hasattr(dagger_rounds, "round_demo_config"):  # rounds of numbered episodes on an episode store
        env = config.env
        round_config = dagger_rounds.RoundConfig(
            round_index=1, seed=sizes.seed, beta=0.0, num_episodes=config.episodes_per_round, demo_length=env.demo_length,
            max_steps=env.max_steps, image_size=env.image_size, split=env.split, num_houses=env.num_houses, noise=env.noise,
        )
        episodes = dagger._collect_round(policy, config, round_config, scratch / "dagger" / "round-01")
        applied.append("round on an episode store (its demonstrations rendered in the timing)")
    else:
        episodes = dagger._collect_round(policy, config, 0.0, sizes.seed)
    seconds = time.perf_counter() - start
    count = int(episodes.shape[0])
    branches["dagger_collection"] = applied
    return {
        "value": count / seconds,
        "episodes": count,
        "seconds": seconds,
        "mean_length": float(episodes["length"].float().mean()),
    }


def _evaluation_config(sizes: Sizes, optional: dict, applied: list[str]):
    from spf_rl.train.evaluation import EvalConfig

    values = dict(
        split="test", num_episodes=sizes.eval_episodes, noise="paper", seed=sizes.seed, num_agents=sizes.eval_agents,
        num_houses=sizes.num_houses, **_episode_sizes(sizes),
    )
    return configured(EvalConfig(), values, {**dict.fromkeys(WORKER_FIELDS, sizes.workers), **optional}, applied)


def _timed_evaluation(config, sizes: Sizes) -> dict:
    from spf_rl.train.evaluation import evaluate_policy

    policy = build_learner(sizes)
    start = time.perf_counter()
    summary, records = evaluate_policy(policy, config)
    seconds = time.perf_counter() - start
    return {
        "value": len(records) / seconds,
        "episodes": len(records),
        "seconds": seconds,
        "mean_steps": sum(record["steps"] for record in records) / len(records),
        "success": summary["success"],
    }


def measure_evaluation(sizes: Sizes, scratch: Path, branches: dict) -> dict:
    """Episodes/s of ``evaluate_policy`` (the learner, greedy) on the test split, as the
    tree's ``EvalConfig()`` runs it."""
    applied: list[str] = []
    config = _evaluation_config(sizes, {}, applied)
    branches["evaluation"] = applied
    return _timed_evaluation(config, sizes)


def measure_evaluation_repeat(sizes: Sizes, scratch: Path, branches: dict) -> dict:
    """Episodes/s of a second ``evaluate_policy`` of the same episodes, as every validation
    of a training run after the first: in a tree whose ``EvalConfig`` has ``store_root``,
    from the episode store the first (untimed) evaluation kept in the scratch directory."""
    applied: list[str] = []
    root = scratch / "episode_stores"
    shutil.rmtree(root, ignore_errors=True)
    config = _evaluation_config(sizes, {"store_root": str(root)}, applied)
    branches["evaluation_repeat"] = applied
    _timed_evaluation(config, sizes)  # the first evaluation (builds the store where there is one)
    return _timed_evaluation(config, sizes)


def measure_bc_training(sizes: Sizes, scratch: Path, branches: dict) -> dict:
    """Expert-labelled (``mask``-ed) steps/s through ``bc_loss`` + backward + clip + Adam step,
    at the tree's default batch size (``OptimConfig().batch_size``), on the dataset built by
    ``dataset_generation`` (built here, untimed, if that measure did not run)."""
    import torch

    from spf_rl.data import EpisodeDataset
    from spf_rl.train.bc import bc_loss
    try:
        from spf_rl.train.run import OptimConfig
    except ImportError:  # the baseline tree, where OptimConfig was in spf_rl.train.bc
        from spf_rl.train.bc import OptimConfig

    applied: list[str] = []
    root = scratch / "bc_data"
    dataset = EpisodeDataset.build(root, _dataset_config(sizes, applied), sizes.workers, progress=False)
    optim = OptimConfig()
    policy = build_learner(sizes)
    policy.train()
    optimizer = torch.optim.Adam(policy.parameters(), lr=optim.lr, weight_decay=optim.weight_decay)
    buffer = dataset.replay_buffer(optim.batch_size, seed=sizes.seed)

    def step() -> int:
        batch = buffer.sample()
        loss, _ = bc_loss(policy, batch)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), optim.max_grad_norm)
        optimizer.step()
        return int(batch["steps", "mask"].sum())

    for _ in range(sizes.bc_warmup_steps):
        step()
    start = time.perf_counter()
    labelled = sum(step() for _ in range(sizes.bc_steps))
    seconds = time.perf_counter() - start
    branches["bc_training"] = applied
    return {
        "value": labelled / seconds,
        "labelled_steps": labelled,
        "gradient_steps": sizes.bc_steps,
        "batch_size": optim.batch_size,
        "seconds": seconds,
    }


def measure_collection(sizes: Sizes, scratch: Path, branches: dict) -> dict:
    """Frames/s of collection as the pipelines run it (the learner in ``make_collector``, with the
    expert's labels and ``paper`` noise), and the raw render loop's frames/s in the same process."""
    import torch
    from bench_env_paths import WARMUP_FRAMES, bench_collector, bench_raw
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from envs.scenes import split_seeds
    from spf_rl.train.collection import make_collector
    from spf_rl.train.dagger import DAggerConfig, ExpertMixturePolicy

    applied: list[str] = []
    env = dataclasses.replace(DAggerConfig().env, **_collection_env_values(sizes))
    layout = dataclasses.replace(DAggerConfig().collector, num_collectors=sizes.collectors, num_agents=sizes.num_agents)
    learner = build_learner(sizes).eval()
    frames_per_batch = layout.total_agents * sizes.max_steps
    if "demo_store" in inspect.signature(make_collector).parameters:  # envs drawing from a store, frames looked up
        from envs.demo_store import DemoStore, DemoStoreConfig
        from spf_rl.train.evaluation import FramesFromStore

        store_config = DemoStoreConfig(
            num_demos=sizes.store_demos, split="train", num_houses=sizes.num_houses,
            demo_length=sizes.demo_length, image_size=sizes.image_size, seed=sizes.seed,
        )
        store = DemoStore.build(scratch / "demo_store", store_config, progress=False)  # untimed
        policy = ExpertMixturePolicy(FramesFromStore(learner, store), 0.0)
        factory = partial(make_collector, policy, env, layout, frames_per_batch=frames_per_batch, seed=sizes.seed,
                          demo_store=store.root)
        applied.append("demo store (make_collector(demo_store=), demo_id only, policy-side lookup: FramesFromStore)")
    else:
        policy = ExpertMixturePolicy(learner, 0.0)
        factory = partial(make_collector, policy, env, layout, frames_per_batch=frames_per_batch, seed=sizes.seed)
        applied.append("default env (demonstrations rendered at each reset; make_collector has no demo_store)")
    house = split_seeds("train", sizes.num_houses)[0]
    raw = bench_raw(house, sizes.image_size, sizes.raw_chunks, sizes.raw_chunk_frames, WARMUP_FRAMES, sizes.seed)
    with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
        result = bench_collector(factory, 0, sizes.collection_batches, 1)
    branches["collection"] = applied
    return {"value": result["fps"], **result, "raw_fps": raw["fps"], "raw": raw}


def _collection_env_values(sizes: Sizes) -> dict:
    return dict(split="train", noise="paper", num_houses=sizes.num_houses, with_expert=True, **_episode_sizes(sizes))


MEASURE_FUNCTIONS: dict[str, Callable[[Sizes, Path, dict], dict]] = {
    "dataset_generation": measure_dataset_generation,
    "dagger_collection": measure_dagger_collection,
    "evaluation": measure_evaluation,
    "evaluation_repeat": measure_evaluation_repeat,
    "bc_training": measure_bc_training,
    "collection": measure_collection,
}


def run_measures(names: list[str], sizes: Sizes, scratch: Path, threads: int | None = None) -> dict:
    """Run ``names`` in order in this process; the worker's output (one JSON object)."""
    import torch

    import envs  # noqa: F401  (selects the headless GL back-end before any renderer)

    if threads is not None:
        torch.set_num_threads(threads)
    scratch.mkdir(parents=True, exist_ok=True)
    branches: dict[str, list[str]] = {}
    measures = {}
    for name in names:
        logger.info("measuring %s", name)
        measures[name] = {**MEASURE_FUNCTIONS[name](sizes, scratch, branches), "unit": UNITS[name]}
        logger.info("%s: %.2f %s", name, measures[name]["value"], UNITS[name])
    return {
        "measures": measures,
        "branches": branches,
        "torch_threads": torch.get_num_threads(),
        "spf_rl_file": sys.modules["spf_rl"].__file__,
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--measures", required=True, help=f"comma-separated, of {', '.join(MEASURES)}")
    parser.add_argument("--sizes", default="{}", help="JSON object of Sizes fields (the rest: defaults)")
    parser.add_argument("--scratch", type=Path, required=True, help="this tree's scratch directory (kept across repeats)")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    args = parser.parse_args(argv)
    names = [name for name in args.measures.split(",") if name]
    unknown = sorted(set(names) - set(MEASURES))
    if unknown:
        parser.error(f"--measures: unknown {unknown}; choose from {list(MEASURES)}")
    sizes = dataclasses.replace(Sizes(), **json.loads(args.sizes))
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    output = run_measures(names, sizes, args.scratch, args.threads)
    print(json.dumps(output), flush=True)  # the one line the driver reads
    return output


if __name__ == "__main__":
    main()
