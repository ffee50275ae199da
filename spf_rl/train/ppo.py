"""Recurrent PPO fine-tuning of a behaviour-cloned path-following policy: the run loop.

Starting from a BC checkpoint, the policy (:class:`~spf_rl.modules.SPFPolicy`,
wrapped by :func:`~spf_rl.modules.make_actor` into a
:class:`~torchrl.modules.ProbabilisticActor` over the 3 actions) is trained on
the environment's dense reward (geodesic progress, success bonus, step cost;
see :mod:`envs.nav_env`) with the loss of :mod:`spf_rl.train.ppo_loss` (TorchRL's
:class:`~torchrl.objectives.ClipPPOLoss` and :class:`~torchrl.objectives.value.GAE`,
a value head on the policy's GRU features, optional pulls toward the start). The
run is configured by :class:`~spf_rl.train.ppo_config.PPOConfig`.

* **Collection.** :func:`~spf_rl.train.collection.make_collector` (local
  in-process / multi-process, or Ray) with ``reset_at_each_iter=True``: every
  batch ``[N, T]`` (``N = collector.total_agents`` rows, ``T = frames_per_batch / N``)
  starts ``N`` fresh episodes at ``t = 0``, so each row is one agent's stream of
  whole episodes (plus one cut by the batch end, bootstrapped by the critic) and
  the recurrent state at ``t = 0`` is the zero reset state. The weights are pushed
  to the collector (:meth:`update_policy_weights_`) before every batch. Demonstrations
  come from a store rendered once (``store_demos``): the envs emit ``demo_id``, and the
  actor (:class:`~spf_rl.evaluation.FramesFromStore`) and the update look the frames up.
* **Device.** The policy, value head, frozen reference and optimisers live on
  ``config.device``; the collector acts there (``policy_device``) with the envs on
  the CPU and stores the batch on the device, where GAE and the updates run.
* **Train/eval mode.** The policy is kept in ``eval()`` mode throughout, also in
  the PPO update (gradients flow as usual). The networks have no dropout or
  batch-norm, but ``"spf_random"`` models pick their memory mask by
  ``policy.training``: in eval mode collection (step mode) and the loss
  (sequence mode) both read the memory at the model's evaluation sparsity, so the
  recomputed log-probabilities match the collected ones. PPO therefore fine-tunes
  a ``"spf_random"`` model at that one sparsity.

Every ``val_every`` iterations the policy is scored greedily on the ``val``
split; the best checkpoint by (val success, val SPL), the start policy included
as iteration 0, is kept in ``best.pt`` (same ``model_type`` as the start, so
``recipes/evaluate.py`` reads it) and evaluated on the ``test`` split at the end.
``results.json`` compares start and after; ``ppo.png`` plots the val curve.

Resuming: ``<output_dir>/last.pt`` (written atomically after every iteration)
holds the policy, value head, optimisers, iteration, history and RNG state; a run
started again with the same config continues after the last finished iteration
(the start evaluations are not repeated). A resumed run seeds its new collector
from ``(seed, iteration)``, so it plays other episodes than an uninterrupted run
would have from that point on.
"""
from __future__ import annotations

import copy
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path

import torch
from tensordict import TensorDictBase
from torchrl.modules import set_recurrent_mode
from torchrl.objectives.value import GAE
from torchrl.record.loggers import get_logger
from tqdm.auto import tqdm

from envs.atomic_io import atomic_write_json
from spf_rl.checkpoint import load_checkpoint
from spf_rl.device import autocast, exact_float32
from spf_rl.evaluation import FramesFromStore, evaluate_policy, frames_lookup
from spf_rl.hub import checked_checkpoint, shipped_file_sha256
from spf_rl.modules.registry import build_policy
from spf_rl.train.collection import collection_device, make_collector
from spf_rl.train.ppo_config import PPO_RESUME_FREE, PPOConfig, checked_env_config, training_demo_store
from spf_rl.train.ppo_loss import (
    AMP_RATIO_SYNC_TOLERANCE,
    EXPERT_KEY,
    RATIO_SYNC_TOLERANCE,
    REF_LOGITS_KEY,
    VALUE_KEY,
    Autocast,
    SPFPPOLoss,
    compute_values,
    episode_statistics,
    make_ppo_modules,
)
from spf_rl.train.run import OptimConfig, TrainingRun, run_results
from spf_rl.train.run_config import write_run_config
from spf_rl.viz import plot_if_available, pyplot, write_figure

logger = logging.getLogger(__name__)

#: Salt of the per-iteration minibatch permutation seed.
_PERMUTATION_SALT = 1_000_003
#: Salt of the collector seed of a run (re)started at an iteration.
_COLLECTOR_SALT = 7919


def train_ppo(config: PPOConfig, callback: Callable[[dict], None] | None = None) -> dict:
    """Run (or resume) a PPO fine-tuning run; return its results (also in ``results.json``).

    Args:
        config: the run.
        callback: called with each iteration's record after ``last.pt`` is written
            (e.g. to stop a run early by raising).

    Returns:
        dict with ``start`` and ``after`` (val and test summaries with CIs),
        ``best_iteration``, ``history`` (one record per iteration), ``val_history``,
        ``frames`` and ``config``.

    Raises:
        ValueError: the env's sizes do not match the checkpoint's, ``output_dir`` holds a run started
            with other settings, or another ``frames_per_batch`` / collector layout than ``last.pt``.

    Examples:
        >>> results = train_ppo(PPOConfig(output_dir="runs/ppo-example"))  # doctest: +SKIP
        >>> results["after"]["test"]["success"]  # doctest: +SKIP
        0.52
    """
    threads = torch.get_num_threads()
    if config.num_threads:
        torch.set_num_threads(config.num_threads)
    try:
        run = _PPORun(config)
        with exact_float32(run.device, enabled=not config.amp):
            return run.run(callback)
    finally:
        torch.set_num_threads(threads)


class _PPORun:
    """The state of one run: modules, optimisers, progress, and the files it writes."""

    def __init__(self, config: PPOConfig) -> None:
        self.config = config
        self.device = collection_device(config.device, config.collector)  # first: a missing GPU fails here
        self.output = Path(config.output_dir)
        write_run_config(self.output, config, free=PPO_RESUME_FREE)  # a resume under other settings fails here
        self.last_path, self.best_path = self.output / "last.pt", self.output / "best.pt"

        payload = load_checkpoint(checked_checkpoint(config.checkpoint), known_file_sha256=shipped_file_sha256())
        self.model_type, self.policy_config = payload["model_type"], payload["model_config"]
        self.env_config = checked_env_config(config, self.policy_config)
        self.val_config, self.test_config = config.val, config.test

        torch.manual_seed(config.seed)
        self.policy = build_policy(self.model_type, self.policy_config)
        self.policy.load_state_dict(payload["model"])
        self.policy.eval()  # see the module docstring: kept in eval mode throughout
        self.actor, self.critic = make_ppo_modules(self.policy, config.value_hidden, config.critic_trunk_grad)
        self.actor.to(self.device)
        self.critic.to(self.device)
        logger.info("PPO on %s%s", self.device, " with bf16 autocast" if config.amp else "")
        self.reference = copy.deepcopy(self.policy).requires_grad_(False) if config.kl_coef > 0 else None
        self.loss_module = SPFPPOLoss(
            self.actor,
            self.critic,
            kl_coef=config.kl_coef,
            bc_coef=config.bc_coef,
            clip_epsilon=config.clip_epsilon,
            entropy_bonus=config.entropy_coef > 0,
            entropy_coeff=config.entropy_coef,
            critic_coeff=config.critic_coef,
            normalize_advantage=config.normalize_advantage,
            device=self.device,
        )
        self.demo_store = training_demo_store(config, self.env_config)  # frames looked up where segments start:
        self.frames_lookup = frames_lookup(self.policy, self.demo_store, self.env_config.episodes.frames_id_key)  # every row starts one
        self.advantage_module = GAE(gamma=config.gamma, lmbda=config.lmbda, value_network=None, average_gae=False)
        self.layout = {"frames_per_batch": config.frames_per_batch, "rows_per_batch": config.rows_per_batch}
        # the one training loop's state: two optimisers (no schedule), last.pt and best.pt with the value head
        self.loop = TrainingRun(
            self.output, self.model_type, self.policy_config, self.policy,
            OptimConfig(lr=config.lr, max_grad_norm=config.max_grad_norm, cosine_schedule=False, amp=config.amp),
            unit="iteration",
            optimizers={"policy_optimizer": (self.policy.parameters(), config.lr, 0.0),
                        "critic_optimizer": (self.critic.parameters(), config.critic_lr, 0.0)},
            modules={"value_head": self.critic.module},
        )
        self.history = self.loop.history
        self.iteration = 0
        self.start: dict = {}

    # ------------------------------------------------------------------ the run
    def run(self, callback: Callable[[dict], None] | None) -> dict:
        start_time = time.time()
        if self.last_path.exists():
            self._resume()
        else:
            self._evaluate_start()
        if self.iteration < self.config.num_iterations:
            self._train(callback)
        return self._finish(time.time() - start_time)

    def _resume(self) -> None:
        def same_layout(state: dict) -> None:
            if state.get("layout") != self.layout:
                raise ValueError(
                    f"{self.last_path} was written with {state.get('layout')}, this config has {self.layout}: "
                    f"frames_per_batch and the collector's agents must not change on resume (or use a new output_dir)."
                )

        self.iteration = self.loop.resume(check=same_layout, state_keys=("start", "layout"))
        self.history, self.start = self.loop.history, self.loop.state["start"]

    def _evaluate_start(self) -> None:
        logger.info("evaluating the start policy %s on val and test", self.config.checkpoint)
        val, _ = evaluate_policy(self.policy, self.val_config, progress=self.config.progress)
        test, _ = evaluate_policy(self.policy, self.test_config, progress=self.config.progress)
        self.start = {"val": val, "test": test}
        logger.info("start: val success %.3f, test success %.3f", val["success"], test["success"])
        self.loop.state = {"start": self.start, "layout": self.layout}
        self.loop.keep_if_best(0, val)
        self.loop.save_last(0)

    def _train(self, callback: Callable[[dict], None] | None) -> None:
        config = self.config
        num_iterations = config.num_iterations
        collector = make_collector(
            FramesFromStore(Autocast(self.actor) if config.amp else self.actor, self.demo_store, self.env_config.episodes.frames_id_key),
            self.env_config,
            config.collector,
            frames_per_batch=config.frames_per_batch,
            total_frames=(num_iterations - self.iteration) * config.frames_per_batch,
            seed=config.seed + _COLLECTOR_SALT * self.iteration,
            reset_at_each_iter=True,
            device=self.device,
            demo_store=None if self.demo_store is None else self.demo_store.root,
        )
        run_logger = (
            get_logger(config.logger, logger_name=str(self.output / "logs"), experiment_name="ppo") if config.logger else None
        )
        bar = tqdm(total=num_iterations, initial=self.iteration, desc="ppo", disable=not config.progress)
        try:
            collector.update_policy_weights_()
            collect_start = time.time()
            for batch in collector:
                collect_seconds = time.time() - collect_start
                update_start = time.time()
                # [N, T]; the Ray collector stacks its collectors' [A, T] batches to [C, A, T]
                batch = batch.reshape(-1, batch.shape[-1]) if batch.ndim != 2 else batch
                record = self._update(batch)
                self.iteration += 1
                record.update(
                    iteration=self.iteration,
                    frames=self.iteration * config.frames_per_batch,
                    collect_seconds=collect_seconds,
                    update_seconds=time.time() - update_start,
                )
                validate = self.iteration % config.val_every == 0 or self.iteration == num_iterations
                val = self._validate(record) if validate else None
                self.loop.end_period(self.iteration, record, val)  # history, best.pt, last.pt
                self._log(record, run_logger)
                bar.update(1)
                bar.set_postfix(reward=f"{record['reward_per_step']:.3f}", success=f"{record['success']:.2f}")
                if callback is not None:
                    callback(record)
                if self.iteration >= num_iterations:
                    break
                collector.update_policy_weights_()
                collect_start = time.time()
        finally:
            bar.close()
            collector.shutdown()

    def _update(self, batch: TensorDictBase) -> dict:
        """GAE, then ``ppo_epochs`` passes over whole-row minibatches; returns the iteration's metrics."""
        config, policy = self.config, self.policy
        batch = self.frames_lookup(batch) if self.frames_lookup is not None else batch
        record = episode_statistics(batch)
        compute_values(policy, self.critic, batch, amp=config.amp)
        with torch.no_grad():
            self.advantage_module(batch)
        keys = set(policy.in_keys) | {"action", "action_log_prob", "advantage", "value_target", VALUE_KEY, policy.features_key}
        if config.bc_coef > 0:
            keys.add(EXPERT_KEY)
        train_td = batch.select(*keys, strict=False)
        if self.reference is not None:
            ref_td = train_td.select(*self.reference.in_keys, strict=False).clone(False)
            with torch.no_grad(), set_recurrent_mode(True), autocast(self.device, config.amp):
                train_td.set(REF_LOGITS_KEY, self.reference(ref_td).get(self.reference.logits_key).float())
        warmup = self.iteration < config.critic_warmup_iters
        generator = torch.Generator().manual_seed(config.seed * _PERMUTATION_SALT + self.iteration)
        sums: dict[str, float] = {}
        count = skipped = 0
        log_ratio_first = None
        for _ in range(config.ppo_epochs):
            order = torch.randperm(train_td.shape[0], generator=generator)
            for rows in order.split(config.minibatch_rows):
                minibatch = train_td[rows]
                for optimizer in self.loop.optimizers.values():
                    optimizer.zero_grad(set_to_none=True)
                with autocast(self.device, config.amp):
                    if warmup:  # fit the new value head on the collected features; the policy is left as it is
                        loss_critic, _, explained = self.loss_module.loss_critic(minibatch)
                        total = loss_critic.float().mean()
                        metrics = {"loss_critic": total.detach()}
                        if explained is not None:
                            metrics["explained_variance"] = explained.detach()
                    else:
                        out = self.loss_module(minibatch)
                        total = sum(value.float() for key, value in out.items() if key.startswith("loss_"))
                        metrics = {key: value.detach() for key, value in out.items()}
                        if log_ratio_first is None:
                            log_ratio_first = float(metrics["max_abs_log_ratio"])
                total.backward()
                # clipped, then stepped unless a loss or gradient is not finite (one bad minibatch must not turn
                # the weights into NaN: its step is skipped and counted); in the warm-up the policy is left alone
                stepped = ("critic_optimizer",) if warmup else ("critic_optimizer", "policy_optimizer")
                if not self.loop.apply_gradients(stepped, total):
                    skipped += 1
                    logger.warning("iteration %d: non-finite loss or gradient, update skipped", self.iteration + 1)
                    continue
                for key, value in metrics.items():
                    if value.numel() == 1:
                        sums[key] = sums.get(key, 0.0) + float(value)
                count += 1
        record.update({key: value / max(count, 1) for key, value in sums.items()})
        record["skipped_updates"] = skipped
        record["critic_warmup"] = warmup
        if log_ratio_first is not None:
            record["log_ratio_first"] = log_ratio_first
            if log_ratio_first > (AMP_RATIO_SYNC_TOLERANCE if config.amp else RATIO_SYNC_TOLERANCE):
                logger.warning(
                    "iteration %d: the first minibatch's |log-ratio| is %.4f, not 0: the collector acted with "
                    "other weights than the learner's (weight sync), or the recurrent replay differs.",
                    self.iteration + 1,
                    log_ratio_first,
                )
        return record

    def _validate(self, record: dict) -> dict:
        """The policy's validation summary, its scores and time also in ``record``."""
        start = time.time()
        val, _ = evaluate_policy(self.policy, self.val_config, progress=False)
        record.update(val_success=val["success"], val_spl=val["spl"], val_seconds=time.time() - start)
        return val

    def _log(self, record: dict, run_logger) -> None:
        if run_logger is not None:
            for key, value in record.items():
                if key in ("iteration", "frames") or not isinstance(value, (int, float)) or not math.isfinite(value):
                    continue
                name = f"val/{key[4:]}" if key.startswith("val_") else f"train/{key}"
                run_logger.log_scalar(name, float(value), step=record["frames"])
        logger.info("iteration %d: %s", self.iteration, {k: round(v, 4) if isinstance(v, float) else v for k, v in record.items()})

    def _finish(self, seconds: float) -> dict:
        best = load_checkpoint(self.best_path, expected_model_type=self.model_type)
        if best["iteration"] == 0:
            after_test = self.start["test"]  # the start policy itself: same episodes, same greedy actions
        else:
            self.policy.load_state_dict(best["model"])
            after_test, _ = evaluate_policy(self.policy, self.test_config, progress=self.config.progress)
        start = self.start
        val_history = [{"iteration": 0, "frames": 0, "val_success": start["val"]["success"], "val_spl": start["val"]["spl"]}]
        val_history += [
            {key: record[key] for key in ("iteration", "frames", "val_success", "val_spl")}
            for record in self.history
            if "val_success" in record
        ]
        results = {
            "model": self.model_type,
            "start_checkpoint": self.config.checkpoint,
            "best_checkpoint": str(self.best_path),
            "start": start,
            "after": {"iteration": best["iteration"], "val": best["val"], "test": after_test},
            "test_success_change": after_test["success"] - start["test"]["success"],
            "test_spl_change": after_test["spl"] - start["test"]["spl"],
            "best_iteration": best["iteration"],
            "iterations": self.iteration,
            "frames": self.iteration * self.config.frames_per_batch,
            "val_history": val_history,
            "history": self.history,
            **run_results(self.config, seconds),
        }
        atomic_write_json(self.output / "results.json", results, default=str)
        plot_if_available(
            plot_ppo, val_history, start, self.output / "ppo.png", title=f"PPO from {Path(self.config.checkpoint).name}"
        )
        return results


def plot_ppo(val_history: list[dict], start: dict, path: str | Path, title: str = "PPO") -> Path:
    """Val success and SPL per iteration, with the start policy's values as lines.

    Args:
        val_history: records with ``iteration``, ``val_success``, ``val_spl``.
        start: ``{"val": summary, ...}`` of the start policy.
        path: the figure file.
        title: figure title.

    Returns:
        ``path``.
    """
    plt = pyplot()
    path = Path(path)
    fig, ax = plt.subplots(figsize=(6, 4))
    iterations = [r["iteration"] for r in val_history]
    for metric, color in (("success", "tab:blue"), ("spl", "tab:orange")):
        ax.plot(iterations, [r[f"val_{metric}"] for r in val_history], "-o", color=color, label=f"val {metric}")
        ax.axhline(start["val"][metric], color=color, linestyle=":", label=f"start val {metric}")
    ax.set_xlabel("PPO iteration (0 = start checkpoint)")
    ax.set_ylim(0, 1)
    ax.set_title(title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return write_figure(fig, path, dpi=120)
