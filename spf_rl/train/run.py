"""The machinery every training run shares: optimiser settings, the resumable run
(:class:`TrainingRun`: optimiser, schedule, ``last.pt`` and ``best.pt``), where a run
keeps every epoch's weights, and starting a run on its device.

Behaviour cloning (:mod:`spf_rl.train.bc`), the mixed-length run
(:mod:`spf_rl.train.lengths`) and DAgger's training rounds build on it.
"""
from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Callable, Collection
from dataclasses import dataclass
from pathlib import Path

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
    """

    lr: float = 1e-3
    weight_decay: float = 0.0
    batch_size: int = 16
    epochs: int = 12
    max_grad_norm: float = 1.0
    cosine_schedule: bool = True
    amp: bool = False
    pointer_coef: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.pointer_coef) and self.pointer_coef >= 0.0):
            raise ValueError(f"optim.pointer_coef must be a finite number >= 0, got {self.pointer_coef!r}.")


class TrainingRun:
    """The optimiser, schedule, resume state and checkpoints of a BC run (shared by :func:`train_bc`
    and the mixed-length run of :mod:`spf_rl.train.lengths`).

    ``<output>/last.pt`` holds everything needed to resume (written after every epoch);
    ``<output>/best.pt`` the weights of the best validation epoch (success, then SPL).

    Args:
        output: the run directory.
        model_type: the policy's model type (checked when resuming).
        policy_config: the policy's :class:`~spf_rl.modules.SPFConfig`, saved with it.
        policy: the policy being trained.
        optim: the optimiser settings.
        total_steps: gradient steps of the whole run (the cosine schedule's length).
        keep_epochs: also write every epoch's weights to ``epochs/epoch-NNN.pt``.
        loss_fn: ``loss_fn(policy, batch, amp=..., pointer_coef=..., parts=...) -> (loss, accuracy)``
            of a batch, filling the dict ``parts`` with the loss's parts
            (:func:`spf_rl.train.bc.bc_loss` for behaviour cloning); with ``optim.pointer_coef`` > 0,
            its ``"pointer"`` part is logged as ``train/pointer_loss`` and the epoch's mean is
            ``train_pointer_loss`` in the epoch's record.
        ranks: this process's place in a data-parallel run (:mod:`spf_rl.train.distributed`):
            with more than one rank the policy is wrapped in DistributedDataParallel, each
            batch is this rank's shard, the logged loss and accuracy are the whole batch's,
            and only rank 0 writes checkpoints.
    """

    def __init__(
        self,
        output: Path,
        model_type: str,
        policy_config,
        policy: SPFPolicy,
        optim: OptimConfig,
        total_steps: int,
        keep_epochs: bool = False,
        *,
        loss_fn: Callable[..., tuple[torch.Tensor, torch.Tensor]],
        ranks: Ranks = Ranks(),
    ) -> None:
        self.loss_fn, self.ranks = loss_fn, ranks
        self.module = policy
        if ranks.distributed:
            device = next(policy.parameters()).device
            self.module = DistributedDataParallel(policy, device_ids=[device] if device.type == "cuda" else None)
        self.model_type, self.policy_config, self.policy, self.optim = model_type, policy_config, policy, optim
        self.optimizer = torch.optim.Adam(policy.parameters(), lr=optim.lr, weight_decay=optim.weight_decay)
        self.scheduler = (
            torch.optim.lr_scheduler.CosineAnnealingLR(self.optimizer, T_max=total_steps)
            if optim.cosine_schedule
            else torch.optim.lr_scheduler.LambdaLR(self.optimizer, lambda _: 1.0)
        )
        self.last_path, self.best_path = output / "last.pt", output / "best.pt"
        self.epochs_dir = output / EPOCHS_DIR if keep_epochs else None
        self.history: list[dict] = []
        self.best = {"success": -1.0, "spl": -1.0, "epoch": -1}
        self.step = 0
        self.pointer_losses: list[float] = []  # the pointer loss of each step of the current epoch

    def resume(self) -> int:
        """Load ``last.pt`` if it exists; returns the number of finished epochs."""
        if not self.last_path.exists():
            return 0
        payload = load_checkpoint(self.last_path, expected_model_type=self.model_type)
        self.policy.load_state_dict(payload["model"])
        self.optimizer.load_state_dict(payload["optimizer"])
        if "scheduler" in payload:
            self.scheduler.load_state_dict(payload["scheduler"])
        self.history, self.best = payload["history"], payload["best"]
        self.step = self.history[-1]["step"] if self.history else 0
        torch.set_rng_state(payload["torch_rng"])
        logger.info("resuming %s after epoch %d", self.last_path.parent, payload["epoch"])
        return payload["epoch"]

    def train_epoch(
        self, batches, num_batches: int, desc: str, progress: bool, run_logger=None, policy_of=None
    ) -> tuple[list, list, float]:
        """One gradient step per batch (cross-entropy, clipped gradients); returns (losses, accuracies, seconds).

        ``policy_of(batch)``, if given, is the module that computes a batch's loss (a view of
        the policy sharing its parameters, e.g. for another demonstration length).
        """
        if policy_of is not None and self.ranks.distributed:
            raise ValueError("policy_of (a view of the policy per batch) does not run data-parallel; start one process.")
        self.policy.train()
        losses, accuracies, start = [], [], time.time()
        self.pointer_losses = []
        bar = tqdm(batches, total=num_batches, desc=desc, disable=not progress)
        device = next(self.policy.parameters()).device
        for batch in bar:
            policy = self.module if policy_of is None else policy_of(batch).train()
            parts: dict[str, float] = {}
            loss, accuracy = self.loss_fn(
                policy, batch, amp=self.optim.amp, pointer_coef=self.optim.pointer_coef, parts=parts
            )
            self.optimizer.zero_grad(set_to_none=True)
            loss_value, accuracy_value = backward_on_shard(loss, accuracy, batch, self.ranks, device)
            if "pointer" in parts:
                self.pointer_losses.append(batch_mean(parts["pointer"], batch, self.ranks, device))
            torch.nn.utils.clip_grad_norm_(self.policy.parameters(), self.optim.max_grad_norm)
            self.optimizer.step()
            self.scheduler.step()
            self.step += 1
            losses.append(loss_value)
            accuracies.append(accuracy_value)
            bar.set_postfix(loss=f"{losses[-1]:.3f}", acc=f"{accuracies[-1]:.2f}")
            if run_logger is not None:
                run_logger.log_scalar("train/loss", losses[-1], step=self.step)
                if "pointer" in parts:
                    run_logger.log_scalar("train/pointer_loss", self.pointer_losses[-1], step=self.step)
        return losses, accuracies, time.time() - start

    def end_epoch(
        self, epoch: int, losses: list, accuracies: list, train_seconds: float, val: dict | None, run_logger=None
    ) -> dict:
        """Record epoch ``epoch`` (from 0), keep ``best.pt`` if ``val`` is the best so far, write ``last.pt``.

        ``val`` is ``None`` for an epoch that was not validated (its record says so with
        ``None`` scores; it cannot become ``best.pt``).
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
        if self.pointer_losses:
            record["train_pointer_loss"] = sum(self.pointer_losses) / len(self.pointer_losses)
        self.history.append(record)
        if run_logger is not None:
            for key in ("train_accuracy", "train_pointer_loss", "val_success", "val_spl"):
                if record.get(key) is not None:
                    run_logger.log_scalar(f"epoch/{key}", record[key], step=self.step)
        if not self.ranks.is_main:
            return record
        state = {"model": self.policy.state_dict(), "epoch": epoch + 1}
        if val is not None and (val["success"], val["spl"]) > (self.best["success"], self.best["spl"]):
            self.best = {"success": val["success"], "spl": val["spl"], "epoch": epoch + 1}
            save_checkpoint(self.best_path, self.model_type, self.policy_config, {**state, "val": val})
        if self.epochs_dir is not None:
            save_checkpoint(epoch_checkpoint(self.epochs_dir.parent, epoch + 1), self.model_type, self.policy_config, {**state, "val": val})
        extra = {"optimizer": self.optimizer.state_dict(), "scheduler": self.scheduler.state_dict()}
        save_checkpoint(
            self.last_path,
            self.model_type,
            self.policy_config,
            {**state, **extra, "history": self.history, "best": self.best, "torch_rng": torch.get_rng_state()},
        )
        return record

    def load_best(self) -> None:
        """Load the weights of ``best.pt`` into the policy."""
        self.policy.load_state_dict(load_checkpoint(self.best_path, expected_model_type=self.model_type)["model"])


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
