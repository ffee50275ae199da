"""Routes of several lengths: one SPF model for demonstrations of n = 30, 50 and 100 steps.

SPF's weights do not depend on the demonstration length ``n``: the memory holds
``round(sparsity * n)`` frames encoded by the same encoder, and the pointer moves on
``[0, n - 1]`` with the same heads. :func:`policy_for_length` builds a policy's modules
for another ``n`` that share its parameters, so one set of weights is trained on, and
evaluated at, every length. Episodes of length ``n`` are sampled in houses large enough
for them (:func:`~envs.house_grid.default_grid_size_cells`) and end after
:func:`~envs.follow.default_max_steps` steps (``ceil(5/3 n)``).

* :class:`MixedLengthConfig` and :func:`train_bc_mixed`: behaviour cloning on one
  expert-labelled dataset per length (a batch holds episodes of one length; each epoch
  visits every batch of every dataset in a seeded random order), validated on the mean
  success over the lengths, tested at each length (``recipes/bc_lengths.py``);
* :func:`spf_rl.evaluation.evaluate_lengths`: success and SPL of a policy at each length, the rows of
  :func:`spf_rl.viz.plot_success_by_length` (``recipes/success_by_length.py``).
"""
from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict

from envs.atomic_io import atomic_write_json
from envs.checks import check_positive_int
from envs.follow import default_max_steps
from envs.house_grid import check_demo_length
from spf_rl.data import DatasetConfig, EpisodeDataset
from spf_rl.device import DEFAULT_DEVICE, check_device
from spf_rl.evaluation import EvalConfig, evaluate_lengths, length_eval_config
from spf_rl.modules.policy import SPFPolicy
from spf_rl.modules.registry import ModelConfig, build_policy, spf_config
from spf_rl.modules.views import model_memory_bytes, policy_for_length
from spf_rl.records_cache import length_test_episodes_file, records_key, write_records
from spf_rl.train.bc import bc_loss, check_no_replay_gate_loss, check_pointer_labels, default_test_config, default_val_config
from spf_rl.train.pointer_guard import RESTARTS_KEY, PointerGuard, restart_run
from spf_rl.train.run import OptimConfig, TrainingRun, run_on_device, run_results, start_run

logger = logging.getLogger(__name__)

#: The lengths of the issue's report (#13 part 4), steps.
DEFAULT_LENGTHS = (30, 50, 100)
#: Training episodes per length: about the same bytes of frames per length
#: (episodes x (n + max_steps) frames); 125 + 75 + 38 = 238 batches of 16 per epoch.
DEFAULT_EPISODES = (2000, 1200, 600)


@dataclass
class MixedLengthConfig:
    """Behaviour cloning of one model on demonstrations of several lengths.

    Args:
        seed: seed of initialisation, batching and (through the sub-configs) data.
        output_dir: checkpoints, results and figures.
        device: where the policy trains (``"auto"``, ``"cpu"``, ``"cuda"``, ``"cuda:N"``).
        data_root: directory of the per-length datasets (named by their configuration).
        num_workers: processes generating the datasets.
        progress: progress bars.
        lengths: the demonstration lengths, steps (the checkpoint is saved for the first).
        episodes: training episodes per length (same order as ``lengths``).
        data: the datasets' common settings (split, noise, random actions, frame size,
            chunk size, seed); ``num_episodes``, ``demo_length`` and ``max_steps`` come
            from ``episodes``, ``lengths`` and :func:`~envs.follow.default_max_steps`.
        model: the policy.
        optim: the optimiser (``epochs`` passes over all datasets).
        val: validation after each epoch, ``num_episodes`` per length (mean success, then SPL, picks the best).
        test: final evaluation of the best checkpoint, ``num_episodes`` per length.

    Examples:
        >>> MixedLengthConfig(lengths=[30, 50], episodes=[10])
        Traceback (most recent call last):
        ...
        ValueError: episodes must give one count per length (lengths=[30, 50]), got [10].
    """

    seed: int = 0
    output_dir: str = "runs/bc_lengths"
    device: str = DEFAULT_DEVICE
    data_root: str = "data/lengths"
    num_workers: int = 2
    progress: bool = True
    lengths: list[int] = field(default_factory=lambda: list(DEFAULT_LENGTHS))
    episodes: list[int] = field(default_factory=lambda: list(DEFAULT_EPISODES))
    data: DatasetConfig = field(default_factory=DatasetConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    val: EvalConfig = field(default_factory=default_val_config)
    test: EvalConfig = field(default_factory=default_test_config)

    def __post_init__(self) -> None:
        check_device(self.device)
        if not self.lengths or len(set(self.lengths)) != len(self.lengths):
            raise ValueError(f"lengths must be distinct demonstration lengths (steps), got {list(self.lengths)}.")
        for length in self.lengths:
            check_demo_length(length, "lengths[i]")
        if len(self.episodes) != len(self.lengths):
            raise ValueError(
                f"episodes must give one count per length (lengths={list(self.lengths)}), got {list(self.episodes)}."
            )
        for count in self.episodes:
            check_positive_int("episodes[i]", count)
        check_pointer_labels(self.optim, self.data.episodes.route_style, "data.route_style")
        check_no_replay_gate_loss(self.optim)

    def dataset_config(self, index: int) -> DatasetConfig:
        """The dataset of ``lengths[index]``."""
        length = self.lengths[index]
        episodes = self.data.episodes.replace(demo_length=length, max_steps=default_max_steps(length))
        return dataclasses.replace(self.data, num_episodes=self.episodes[index], episodes=episodes)

    def dataset_dir(self, index: int) -> Path:
        """The dataset of ``lengths[index]`` under ``data_root``, named as every dataset is
        (:meth:`~spf_rl.data.DatasetConfig.default_dir`)."""
        return Path(self.data_root) / self.dataset_config(index).default_dir().name


def epoch_schedule(batches_per_length: list[int], seed: int) -> np.ndarray:
    """The order of an epoch's batches: index ``i`` of a length appears ``batches_per_length[i]`` times, shuffled.

    Examples:
        >>> sorted(epoch_schedule([3, 1], seed=0).tolist())
        [0, 0, 0, 1]
    """
    order = np.repeat(np.arange(len(batches_per_length)), batches_per_length)
    return np.random.default_rng(seed).permutation(order)


def train_bc_mixed(config: MixedLengthConfig) -> dict:
    """Run (or resume) a mixed-length BC run; returns its results (also ``results.json``, and
    ``success_by_length.png`` when matplotlib is installed).

    Raises:
        ValueError: ``config.device`` names a device this machine does not have (before any work).
    """
    return run_on_device(_train_mixed, config)


def _train_mixed(config: MixedLengthConfig, device: torch.device) -> dict:
    start_time = time.time()
    output = start_run(config)
    datasets = [
        EpisodeDataset.build(config.dataset_dir(i), config.dataset_config(i), config.num_workers, config.progress)
        for i in range(len(config.lengths))
    ]
    model_type, image_size = config.model.name, config.data.episodes.image_size
    policy_config = spf_config(config.model, config.lengths[0], image_size)
    policy = build_policy(model_type, policy_config).to(device)
    views = {length: policy_for_length(policy, length) for length in config.lengths}
    batch_size = config.optim.batch_size
    batches = [-(-len(dataset) // batch_size) for dataset in datasets]

    def new_run() -> TrainingRun:
        return TrainingRun(
            output, model_type, policy_config, policy, config.optim, sum(batches) * config.optim.epochs, loss_fn=bc_loss
        )

    run = new_run()
    epoch = run.resume(state_keys=(RESTARTS_KEY,))

    def policy_of(batch: TensorDict) -> SPFPolicy:
        return views[batch.get("demo_actions").shape[-1]]

    first = views[config.lengths[0]]  # the guard watches the pointer on the first length's episodes
    guard = PointerGuard.of(first, datasets[0])
    while epoch < config.optim.epochs:
        seed = config.seed * 1000 + epoch
        buffers = [dataset.replay_buffer(batch_size, seed=seed * len(datasets) + i) for i, dataset in enumerate(datasets)]
        order = epoch_schedule(batches, seed)
        stream = (buffers[i].sample() for i in order.tolist())
        losses, accuracies, seconds = run.train_epoch(
            stream, len(order), f"epoch {epoch + 1}/{config.optim.epochs}", config.progress, policy_of=policy_of
        )
        rows, _ = evaluate_lengths(policy, config.lengths, config.val)
        val = mean_over_lengths(rows)
        pace = guard.pace(first) if guard is not None else None
        if PointerGuard.collapsed(pace) and (restarted := restart_run(run, new_run, config.seed, epoch + 1, pace)):
            run, epoch = restarted, 0  # the collapsed epoch is not kept: last.pt is the restart's
            continue
        record = run.end_epoch(epoch, losses, accuracies, seconds, val, pointer_pace=pace)
        logger.info("epoch %d: %s, val by length %s", epoch + 1, record, [round(r["success"], 3) for r in rows])
        epoch += 1

    run.load_best()
    rows, records = evaluate_lengths(policy, config.lengths, config.test, progress=config.progress)
    results = {
        "model": model_type,
        "sparsity": policy_config.effective_sparsity,
        "lengths": list(config.lengths),
        "test_by_length": rows,
        "test": mean_over_lengths(rows),
        "memory_bytes_by_length": {
            length: model_memory_bytes(model_type, length, config.model.sparsity, image_size) for length in config.lengths
        },
        "best_epoch": run.best["epoch"],
        "val_best": run.best,
        "history": run.history,
        "datasets": [dataset.statistics() for dataset in datasets],
        RESTARTS_KEY: run.state.get(RESTARTS_KEY, []),
        **run_results(config, time.time() - start_time),
    }
    atomic_write_json(output / "results.json", results, default=str)
    for length in config.lengths:  # one records file per length, keyed by that length's view of the weights
        test_config = length_eval_config(config.test, length, policy_config.image_size[0])
        write_records(output / length_test_episodes_file(length), records_key(test_config, policy_for_length(policy, length)),
                      records[length], checkpoint=str(run.best_path))
    from spf_rl.viz import plot_if_available, plot_success_by_length, plot_training_curves

    plot_if_available(plot_training_curves, run.history, output / "training_curves.png", title=f"BC {model_type}, mixed lengths")
    plot_if_available(plot_success_by_length, {f"{model_type} (mixed lengths)": rows}, output / "success_by_length.png")
    return results


def mean_over_lengths(rows: list[dict]) -> dict:
    """Mean success and SPL over the lengths (each length weighs the same), with the rows.

    Examples:
        >>> mean_over_lengths([{"demo_length": 30, "success": 1.0, "spl": 0.9}, {"demo_length": 50, "success": 0.5, "spl": 0.4}])["success"]
        0.75
    """
    return {
        "success": float(np.mean([row["success"] for row in rows])),
        "spl": float(np.mean([row["spl"] for row in rows])),
        "by_length": {row["demo_length"]: {"success": row["success"], "spl": row["spl"]} for row in rows},
    }


__all__ = [
    "DEFAULT_EPISODES",
    "DEFAULT_LENGTHS",
    "MixedLengthConfig",
    "epoch_schedule",
    "mean_over_lengths",
    "train_bc_mixed",
]
