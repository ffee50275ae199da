"""The machinery every training run shares: optimiser settings, the one training loop
(:class:`TrainingRun`: optimisers, schedule, the gradient step, ``last.pt`` and ``best.pt``, picking the
best period), where a run keeps every epoch's weights, the fields every ``results.json`` holds, and
starting a run on its device.

Behaviour cloning (:mod:`spf_rl.train.bc`), the mixed-length run (:mod:`spf_rl.train.lengths`), DAgger
(:mod:`spf_rl.train.dagger`) and PPO (:mod:`spf_rl.train.ppo`) build on it.
"""
from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable, Collection, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch.nn.parallel import DistributedDataParallel
from tqdm.auto import tqdm

from envs.atomic_io import atomic_write_text
from spf_rl.checkpoint import load_checkpoint, save_checkpoint
from spf_rl.device import exact_float32, machine_info, resolve_device
from spf_rl.modules.policy import SPFPolicy
from spf_rl.train.distributed import Ranks, backward_on_shard, barrier, batch_mean
from spf_rl.train.run_config import BC_RESUME_FREE, config_dict, write_run_config

logger = logging.getLogger(__name__)


@dataclass
class OptimConfig:
    """Optimiser settings.

    Args:
        lr: Adam learning rate.
        weight_decay: Adam weight decay.
        batch_size: episodes per gradient step.
        epochs: passes over the dataset (12 on the default 2,000 episodes at batch 16 =
            1,500 gradient steps, the main job's budget).
        max_grad_norm: gradient-norm clip.
        cosine_schedule: decay the learning rate to 0 over the run (cosine), which
            steadies the final checkpoints.
        amp: compute the loss under bf16 autocast (mixed precision; see
            :mod:`spf_rl.device`). Off by default; on the CPU faster only with native bf16 (docs/performance.md).
        pointer_coef: weight of the pointer loss beside the cross-entropy
            (:func:`~spf_rl.train.bc.bc_loss`): holds the pointer (RPF's rule, in demonstration
            steps) to the agent's place on the route, the episodes' ``route_step``. 0: off.
        replay_gate_coef: weight of the replay gate's loss beside the cross-entropy
            (:func:`~spf_rl.train.bc.replay_gate_loss`, for a policy with a replay gate): the gate
            is taught to open on the episodes whose memory shows another route. 0: off.
    """

    lr: float = 1e-3
    weight_decay: float = 0.0
    batch_size: int = 16
    epochs: int = 12
    max_grad_norm: float = 1.0
    cosine_schedule: bool = True
    amp: bool = False
    pointer_coef: float = 0.0
    replay_gate_coef: float = 0.0

    def __post_init__(self) -> None:
        for name in ("pointer_coef", "replay_gate_coef"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"optim.{name} must be a finite number >= 0, got {value!r}.")


class TrainingRun:
    """The one training loop's state, shared by behaviour cloning (:func:`~spf_rl.train.bc.train_bc`),
    the mixed-length run (:mod:`spf_rl.train.lengths`), DAgger's retraining
    (:func:`~spf_rl.train.dagger.train_dagger`) and PPO (:func:`~spf_rl.train.ppo.train_ppo`): its
    optimisers and learning-rate schedule, the gradient step, resuming from ``last.pt``, picking the best
    period by validation into ``best.pt``. Each algorithm brings its losses and its data.

    A run advances in periods, numbered by ``unit``: BC's epochs, DAgger's rounds, PPO's iterations.
    ``<output>/last.pt`` holds everything needed to resume (written after every period: the weights, every
    optimiser and the schedule, the history, the best period, torch's RNG state and the algorithm's own
    :attr:`state`); ``<output>/best.pt`` the weights of the best validated period (success, then SPL; the
    first of equals), with its validation scores.

    Args:
        output: the run directory.
        model_type: the policy's model type (checked when resuming).
        policy_config: the policy's :class:`~spf_rl.modules.SPFConfig`, saved with it.
        policy: the policy being trained.
        optim: the optimiser settings (``lr``, ``weight_decay``, ``max_grad_norm``, ``amp``,
            ``pointer_coef``, ``cosine_schedule``).
        total_steps: gradient steps of the whole run: the length of the cosine schedule (with
            ``optim.cosine_schedule``); ``None``: a constant learning rate.
        keep_epochs: also write every period's weights to ``epochs/epoch-NNN.pt``.
        loss_fn: ``loss_fn(policy, batch, amp=..., pointer_coef=..., parts=..., replay_gate_coef=...) -> (loss, accuracy)``
            of a batch, filling the dict ``parts`` with the loss's parts
            (:func:`spf_rl.train.bc.bc_loss` for behaviour cloning), for :meth:`train_epoch`; with
            ``optim.pointer_coef`` > 0, its ``"pointer"`` part is logged as ``train/pointer_loss`` and the
            epoch's mean is ``train_pointer_loss`` in the epoch's record (likewise ``"replay_gate"``,
            ``train_replay_gate_loss``, with ``optim.replay_gate_coef`` > 0).
        ranks: this process's place in a data-parallel run (:mod:`spf_rl.train.distributed`):
            with more than one rank the policy is wrapped in DistributedDataParallel, each
            batch is this rank's shard, the logged loss and accuracy are the whole batch's,
            and only rank 0 writes checkpoints.
        unit: what a period is: ``"epoch"``, ``"round"`` or ``"iteration"`` (the key the files number it by).
        optimizers: ``{name: (parameters, lr, weight_decay)}``, one Adam each, saved under ``name``
            (default: ``{"optimizer": (the policy's parameters, optim.lr, optim.weight_decay)}``); the
            schedule follows the first.
        modules: more modules saved and resumed beside the policy's weights, by name (PPO's value head).

    Examples:
        >>> import tempfile
        >>> from spf_rl.modules import SPFConfig, SPFPolicy
        >>> config = SPFConfig(demo_length=4, feature_dim=8, hidden_size=8, image_size=(16, 16))
        >>> run = TrainingRun(Path(tempfile.mkdtemp()), "spf", config, SPFPolicy(config), OptimConfig(), unit="round")
        >>> run.end_period(1, {"round": 1}, {"success": 0.5, "spl": 0.4}), run.end_period(2, {"round": 2}, {"success": 0.5, "spl": 0.3})
        (True, False)
        >>> run.best, sorted(load_checkpoint(run.last_path))[:4], load_checkpoint(run.best_path)["round"]
        ({'success': 0.5, 'spl': 0.4, 'round': 1}, ['best', 'format_version', 'history', 'model'], 1)
    """

    def __init__(
        self,
        output: Path,
        model_type: str,
        policy_config,
        policy: SPFPolicy,
        optim: OptimConfig,
        total_steps: int | None = None,
        keep_epochs: bool = False,
        *,
        loss_fn: Callable[..., tuple[torch.Tensor, torch.Tensor]] | None = None,
        ranks: Ranks = Ranks(),
        unit: str = "epoch",
        optimizers: dict[str, tuple[Iterable[torch.nn.Parameter], float, float]] | None = None,
        modules: dict[str, torch.nn.Module] | None = None,
    ) -> None:
        self.loss_fn, self.ranks, self.unit = loss_fn, ranks, unit
        self.module = policy
        if ranks.distributed:
            device = next(policy.parameters()).device
            self.module = DistributedDataParallel(policy, device_ids=[device] if device.type == "cuda" else None)
        self.model_type, self.policy_config, self.policy, self.optim = model_type, policy_config, policy, optim
        self.modules = dict(modules or {})
        specs = optimizers or {"optimizer": (policy.parameters(), optim.lr, optim.weight_decay)}
        self.parameters = {name: list(params) for name, (params, _, _) in specs.items()}
        self.optimizers = {
            name: torch.optim.Adam(self.parameters[name], lr=lr, weight_decay=weight_decay)
            for name, (_, lr, weight_decay) in specs.items()
        }
        self.optimizer = next(iter(self.optimizers.values()))
        self.scheduler = (
            torch.optim.lr_scheduler.CosineAnnealingLR(self.optimizer, T_max=total_steps)
            if optim.cosine_schedule and total_steps is not None
            else torch.optim.lr_scheduler.LambdaLR(self.optimizer, lambda _: 1.0)
        )
        self.last_path, self.best_path = output / "last.pt", output / "best.pt"
        self.epochs_dir = output / EPOCHS_DIR if keep_epochs else None
        self.history: list[dict] = []
        self.best = {"success": -1.0, "spl": -1.0, unit: -1}
        #: The algorithm's own entries of ``last.pt`` (PPO: the start's scores, the collector layout).
        self.state: dict[str, Any] = {}
        self.step = 0
        self.pointer_losses: list[float] = []  # the pointer loss of each step of the current epoch
        self.replay_gate_losses: list[float] = []  # and the replay gate's

    # ------------------------------------------------------------------ resuming
    def resume(self, check: Callable[[dict], None] | None = None, state_keys: Collection[str] = ()) -> int:
        """Load ``last.pt`` if it exists (first ``check(payload)``, which may refuse it); returns the number
        of finished periods. ``state_keys``: the algorithm's own entries, back into :attr:`state`."""
        if not self.last_path.exists():
            return 0
        payload = load_checkpoint(self.last_path, expected_model_type=self.model_type)
        if check is not None:
            check(payload)
        self.policy.load_state_dict(payload["model"])
        for name, module in self.modules.items():
            module.load_state_dict(payload[name])
        for name, optimizer in self.optimizers.items():
            optimizer.load_state_dict(payload[name])
        if "scheduler" in payload:
            self.scheduler.load_state_dict(payload["scheduler"])
        self.history = payload["history"]
        self.best = payload["best"] if "best" in payload else self._best_of(self.history)  # DAgger before the one loop
        self.step = self.history[-1].get("step", 0) if self.history else 0
        if "torch_rng" in payload:
            torch.set_rng_state(payload["torch_rng"])
        self.state = {key: payload[key] for key in state_keys if key in payload}
        logger.info("resuming %s after %s %d", self.last_path.parent, self.unit, payload[self.unit])
        return payload[self.unit]

    def _best_of(self, history: list[dict]) -> dict:
        """The best validated record of a history (the first of equals), as :attr:`best` holds it."""
        validated = [r for r in history if r.get("val_success") is not None and not r.get("pointer_collapsed")]
        if not validated:
            return {"success": -1.0, "spl": -1.0, self.unit: -1}
        best = max(validated, key=lambda r: (r["val_success"], r["val_spl"]))
        return {"success": best["val_success"], "spl": best["val_spl"], self.unit: best[self.unit]}

    # ------------------------------------------------------------------ gradient steps
    def apply_gradients(self, names: Sequence[str], loss: torch.Tensor) -> bool:
        """Clip the gradients of the named optimisers' parameters (``optim.max_grad_norm``, in that order)
        and step those optimisers, unless ``loss`` or a gradient norm is not finite: then nothing is
        stepped (one bad batch must not turn the weights into NaN) and ``False`` is returned."""
        norms = [torch.nn.utils.clip_grad_norm_(self.parameters[name], self.optim.max_grad_norm) for name in names]
        if not all(bool(torch.isfinite(value)) for value in (loss.detach(), *norms)):
            return False
        for name in names:
            self.optimizers[name].step()
        return True

    def gradient_step(self, loss: torch.Tensor, accuracy: torch.Tensor, batch) -> tuple[float, float]:
        """One supervised step on ``batch``: backward (this rank's shard), clip, step, advance the schedule;
        returns the whole batch's loss and accuracy. A non-finite step is skipped (logged)."""
        device = next(self.policy.parameters()).device
        self.optimizer.zero_grad(set_to_none=True)
        loss_value, accuracy_value = backward_on_shard(loss, accuracy, batch, self.ranks, device)
        # the whole batch's loss (every rank's the same) and the synchronised gradients: one decision for all ranks
        if not self.apply_gradients(tuple(self.optimizers)[:1], torch.tensor(loss_value)):
            logger.warning("%s step %d: non-finite loss or gradient, update skipped", self.unit, self.step + 1)
        self.scheduler.step()
        self.step += 1
        return loss_value, accuracy_value

    def train_epoch(
        self, batches, num_batches: int, desc: str, progress: bool, run_logger=None, policy_of=None,
        seed_of_step: Callable[[int], int] | None = None,
    ) -> tuple[list, list, float]:
        """One gradient step per batch (:attr:`loss_fn`, :meth:`gradient_step`); returns (losses, accuracies, seconds).

        ``policy_of(batch)``, if given, is the module that computes a batch's loss (a view of
        the policy sharing its parameters, e.g. for another demonstration length).
        ``seed_of_step(i)``, if given, seeds the random draws of step ``i``'s loss (a random-sparsity
        model's per-episode sparsities) from that alone, torch's RNG left as it was.
        """
        if policy_of is not None and self.ranks.distributed:
            raise ValueError("policy_of (a view of the policy per batch) does not run data-parallel; start one process.")
        self.module.train()
        losses, accuracies, start = [], [], time.time()
        self.pointer_losses, self.replay_gate_losses = [], []
        bar = tqdm(batches, total=num_batches, desc=desc, disable=not progress)
        device = next(self.policy.parameters()).device
        for index, batch in enumerate(bar):
            policy = self.module if policy_of is None else policy_of(batch).train()
            parts: dict[str, float] = {}
            with torch.random.fork_rng(devices=[], enabled=seed_of_step is not None):
                if seed_of_step is not None:
                    torch.manual_seed(seed_of_step(index))
                loss, accuracy = self.loss_fn(
                    policy, batch, amp=self.optim.amp, pointer_coef=self.optim.pointer_coef, parts=parts,
                    replay_gate_coef=self.optim.replay_gate_coef,
                )
            loss_value, accuracy_value = self.gradient_step(loss, accuracy, batch)
            if "pointer" in parts:
                self.pointer_losses.append(batch_mean(parts["pointer"], batch, self.ranks, device))
            if "replay_gate" in parts:
                self.replay_gate_losses.append(batch_mean(parts["replay_gate"], batch, self.ranks, device))
            losses.append(loss_value)
            accuracies.append(accuracy_value)
            bar.set_postfix(loss=f"{losses[-1]:.3f}", acc=f"{accuracies[-1]:.2f}")
            if run_logger is not None:
                run_logger.log_scalar("train/loss", losses[-1], step=self.step)
                if "pointer" in parts:
                    run_logger.log_scalar("train/pointer_loss", self.pointer_losses[-1], step=self.step)
        return losses, accuracies, time.time() - start

    def loss_part_means(self) -> dict[str, float]:
        """The means over the last :meth:`train_epoch` of the loss's parts it logged apart:
        ``train_pointer_loss`` and ``train_replay_gate_loss``, each where the loss had it."""
        parts = {"train_pointer_loss": self.pointer_losses, "train_replay_gate_loss": self.replay_gate_losses}
        return {name: float(sum(values) / len(values)) for name, values in parts.items() if values}

    # ------------------------------------------------------------------ periods and checkpoints
    def end_epoch(
        self, epoch: int, losses: list, accuracies: list, train_seconds: float, val: dict | None, run_logger=None,
        pointer_pace: float | None = None,
    ) -> dict:
        """Record epoch ``epoch`` (from 0) of a supervised run and end it (:meth:`end_period`); returns its record.

        ``val`` is ``None`` for an epoch that was not validated (its record says so with
        ``None`` scores; it cannot become ``best.pt``). ``pointer_pace``: the pointer's pace after the
        epoch (:mod:`spf_rl.train.pointer_guard`), logged and kept in the record where measured.
        """
        record = {
            "epoch": epoch + 1,
            "step": self.step,
            "train_loss": sum(losses) / len(losses),
            "train_accuracy": sum(accuracies) / len(accuracies),
            "val_success": None if val is None else val["success"],
            "val_spl": None if val is None else val["spl"],
            "train_seconds": train_seconds,
        }
        record.update(self.loss_part_means())
        if pointer_pace is not None:
            record["pointer_pace"] = pointer_pace
        if run_logger is not None:
            for key in ("train_accuracy", "train_pointer_loss", "train_replay_gate_loss", "pointer_pace", "val_success", "val_spl"):
                if record.get(key) is not None:
                    run_logger.log_scalar(f"epoch/{key}", record[key], step=self.step)
        self.end_period(epoch + 1, record, val)
        return record

    def end_period(self, index: int, record: dict, val: dict | None) -> bool:
        """Append ``record`` to the history; on rank 0, keep ``best.pt`` if ``val`` (``{"success", "spl", ...}``;
        ``None``: not validated) is the best so far, and write ``last.pt``. Returns whether it was the best."""
        self.history.append(record)
        if not self.ranks.is_main:
            return False
        best = self.keep_if_best(index, val)
        if self.epochs_dir is not None:
            save_checkpoint(epoch_checkpoint(self.epochs_dir.parent, index), self.model_type, self.policy_config,
                            {**self._weights(), self.unit: index, "val": val})
        self.save_last(index)
        return best

    def keep_if_best(self, index: int, val: dict | None) -> bool:
        """Write ``best.pt`` (the weights, ``unit``: ``index``, ``val``) if ``val`` beats the best so far."""
        if val is None or (val["success"], val["spl"]) <= (self.best["success"], self.best["spl"]):
            return False
        self.best = {"success": val["success"], "spl": val["spl"], self.unit: index}
        save_checkpoint(self.best_path, self.model_type, self.policy_config, {**self._weights(), self.unit: index, "val": val})
        return True

    def save_last(self, index: int) -> None:
        """Write ``last.pt``: everything a resumed run needs after period ``index`` (atomic)."""
        save_checkpoint(
            self.last_path,
            self.model_type,
            self.policy_config,
            {
                **self._weights(),
                self.unit: index,
                **{name: optimizer.state_dict() for name, optimizer in self.optimizers.items()},
                "scheduler": self.scheduler.state_dict(),
                "history": self.history,
                "best": self.best,
                "torch_rng": torch.get_rng_state(),
                **self.state,
            },
        )

    def _weights(self) -> dict:
        return {"model": self.policy.state_dict(), **{name: module.state_dict() for name, module in self.modules.items()}}

    def restore_best(self) -> None:
        """Back to ``best.pt``'s weights, with fresh optimiser moments (those of the weights set aside do not
        belong to them): the pointer-collapse guard's rule for DAgger (:mod:`spf_rl.train.pointer_guard`)."""
        self.load_best()
        for optimizer in self.optimizers.values():
            optimizer.state.clear()

    def load_best(self) -> dict:
        """Load the weights of ``best.pt`` into the policy (and its other modules); returns its payload."""
        payload = load_checkpoint(self.best_path, expected_model_type=self.model_type)
        self.policy.load_state_dict(payload["model"])
        for name, module in self.modules.items():
            module.load_state_dict(payload[name])
        return payload


#: Where a run with ``keep_epochs`` keeps every epoch's weights.
EPOCHS_DIR = "epochs"


def trim_csv_logs(log_dir: str | os.PathLike, last_step: int) -> int:
    """Drop the rows past ``last_step`` from every CSV scalar log under ``log_dir``; returns how many.

    TorchRL's :class:`~torchrl.record.loggers.CSVLogger` appends ``step,value`` rows. A run
    interrupted after logging steps that its ``last.pt`` does not hold logs them again when
    it resumes; trimming to the resumed step first keeps one row per step. Each file is
    rewritten atomically, and only if it has rows to drop.

    Examples:
        >>> import tempfile
        >>> log = Path(tempfile.mkdtemp()) / "scalars" / "train" / "loss.csv"
        >>> log.parent.mkdir(parents=True)
        >>> _ = log.write_text("250,0.9\\n500,0.8\\n750,0.7\\n")
        >>> trim_csv_logs(log.parents[2], last_step=500), log.read_text()
        (1, '250,0.9\\n500,0.8\\n')
    """
    dropped = 0
    for path in sorted(Path(log_dir).rglob("*.csv")):
        lines = path.read_text().splitlines(keepends=True)
        kept = [line for line in lines if not line.strip() or float(line.split(",", 1)[0]) <= last_step]
        if len(kept) < len(lines):
            dropped += len(lines) - len(kept)
            atomic_write_text(path, "".join(kept))
    if dropped:
        logger.info("dropped %d log rows past step %d from %s (logged after the last checkpoint)", dropped, last_step, log_dir)
    return dropped


def epoch_checkpoint(run_dir: str | os.PathLike, epoch: int) -> Path:
    """The path of epoch ``epoch``'s (from 1) weights in a run kept with ``keep_epochs``."""
    return Path(run_dir) / EPOCHS_DIR / f"epoch-{epoch:03d}.pt"


def run_results(config, seconds: float) -> dict:
    """The fields every run's ``results.json`` holds beside its own (BC, the lengths run, DAgger, PPO):
    ``seed``, ``wall_seconds_this_run`` (``seconds``: this process's part of the run, a resumed run's
    earlier parts not counted), ``machine_this_run`` (:func:`~spf_rl.device.machine_info`) and ``config``
    (flat, as ``config.json`` writes it).

    Examples:
        >>> from spf_rl.train.dagger import DAggerConfig
        >>> sorted(run_results(DAggerConfig(seed=3), 1.5))
        ['config', 'machine_this_run', 'seed', 'wall_seconds_this_run']
    """
    return {"seed": config.seed, "wall_seconds_this_run": seconds, "machine_this_run": machine_info(), "config": config_dict(config)}


def run_on_device(train, config) -> dict:
    """``train(config, device)`` on the config's device (resolved before any work), in full
    float32 unless ``config.optim.amp`` (:func:`~spf_rl.device.exact_float32`)."""
    device = resolve_device(config.device)
    with exact_float32(device, enabled=not config.optim.amp):
        return train(config, device)


def start_run(config, free: Collection[str] = BC_RESUME_FREE, ranks: Ranks = Ranks()) -> Path:
    """Create ``config.output_dir``, write its ``config.json`` (:func:`write_run_config`; the
    settings in ``free`` may change on resume), seed torch. In a data-parallel run rank 0
    writes, and the other ranks wait for it."""
    output = Path(config.output_dir)
    if ranks.is_main:
        write_run_config(output, config, free=free)
    barrier(ranks)
    torch.manual_seed(config.seed)
    return output
