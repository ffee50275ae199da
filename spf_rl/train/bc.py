"""Behaviour cloning of the SPF policy (and baselines) on expert-labelled follow episodes.

The loop: build (or reuse) the episode dataset, train with cross-entropy between
the policy's logits and the expert's action at every valid step of whole
episodes (the policy runs in sequence mode), validate by rolling the policy out
on the ``val`` split after each epoch, keep the best checkpoint, and finally
evaluate the best checkpoint on the ``test`` split.

Everything needed to resume is in ``<output_dir>/last.pt`` (written atomically
after every epoch): an interrupted run started again with the same config
continues after the last finished epoch.

The policy and its optimiser run on ``BCConfig.device`` (``"auto"``: CUDA if
available, see :mod:`spf_rl.device`); each batch moves there
(:func:`episodes_to_sequence`), the rollouts' envs stay on the CPU. With
``optim.amp`` the loss is computed under bf16 autocast.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
import torch.nn.functional as F
from tensordict import TensorDict
from torchrl.modules import set_recurrent_mode
from torchrl.record.loggers import get_logger
from tqdm.auto import tqdm

from spf_rl.checkpoint import load_checkpoint, save_checkpoint
from spf_rl.data import DatasetConfig, EpisodeDataset
from spf_rl.device import DEFAULT_DEVICE, autocast, check_device, exact_float32, module_device, resolve_device, to_device
from spf_rl.modules.memory import memory_bytes
from spf_rl.modules.policy import SPFPolicy
from spf_rl.train.evaluation import EvalConfig, evaluate_policy
from spf_rl.train.models import ModelConfig, build_policy, spf_config

logger = logging.getLogger(__name__)


@dataclass
class OptimConfig:
    """Optimiser settings.

    Args:
        lr: Adam learning rate.
        weight_decay: Adam weight decay.
        batch_size: episodes per gradient step.
        epochs: passes over the dataset.
        max_grad_norm: gradient-norm clip.
        cosine_schedule: decay the learning rate to 0 over the run (cosine), which
            steadies the final checkpoints.
        amp: compute the loss under bf16 autocast (mixed precision; see
            :mod:`spf_rl.device`). Off by default; on the CPU allowed but usually slower.
    """

    lr: float = 1e-3
    weight_decay: float = 0.0
    batch_size: int = 16
    epochs: int = 6
    max_grad_norm: float = 1.0
    cosine_schedule: bool = True
    amp: bool = False


@dataclass
class BCConfig:
    """A behaviour-cloning run.

    Args:
        seed: seed of initialisation, batching and (through the sub-configs) data.
        output_dir: checkpoints, logs, results and figures.
        device: where the policy trains and acts: ``"auto"`` (CUDA if available, else
            the CPU), ``"cpu"``, ``"cuda"`` or ``"cuda:N"``; envs stay on the CPU.
        data_dir: the dataset directory (default ``data/<split>-<episodes>-<noise>-s<seed>``).
        num_workers: processes generating the dataset.
        logger: torchrl logger backend (``"csv"``, ``"tensorboard"``, ...) or ``""`` for none.
        progress: progress bars.
        data: the dataset (:class:`~spf_rl.data.DatasetConfig`).
        model: the policy (:class:`~spf_rl.train.models.ModelConfig`).
        optim: the optimiser (:class:`OptimConfig`).
        val: validation rollouts after each epoch.
        test: final evaluation of the best checkpoint.

    Examples:
        >>> BCConfig(device="gpu")
        Traceback (most recent call last):
        ...
        ValueError: device must be one of 'auto', 'cpu', 'cuda' or 'cuda:N' (N = 0, 1, ...), got 'gpu'.
    """

    seed: int = 0
    output_dir: str = "runs/bc"
    device: str = DEFAULT_DEVICE
    data_dir: str | None = None
    num_workers: int = 2
    logger: str = "csv"
    progress: bool = True
    data: DatasetConfig = field(default_factory=DatasetConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    val: EvalConfig = field(default_factory=lambda: EvalConfig(split="val", num_episodes=100, seed=1))
    test: EvalConfig = field(default_factory=lambda: EvalConfig(split="test", num_episodes=500, seed=2))

    def __post_init__(self) -> None:
        check_device(self.device)

    def resolved_data_dir(self) -> Path:
        if self.data_dir:
            return Path(self.data_dir)
        d = self.data
        return Path("data") / f"{d.split}-{d.num_episodes}ep-{d.noise}-rand{d.random_action_prob}-n{d.demo_length}-{d.image_size}px-s{d.seed}"


def episodes_to_sequence(batch: TensorDict, device: torch.device | str | None = None) -> TensorDict:
    """Turn a batch of stored episodes ``[B]`` into the policy's sequence input ``[B, T]`` on ``device``.

    Demonstration frames and actions are stored once per episode; they move to
    ``device`` once and are then broadcast over time as views (no copy). ``T`` is cut
    to the longest episode (read on the batch's own device, before the move).

    Args:
        batch: stored episodes (:mod:`spf_rl.data` layout).
        device: where the sequence goes (``None``: where the batch is).

    Examples:
        >>> from tensordict import TensorDict
        >>> mask = torch.tensor([[True, True, False], [True, False, False]])
        >>> steps = TensorDict({"pixels": torch.zeros(2, 3, 8, 8, 3, dtype=torch.uint8), "mask": mask,
        ...     "is_init": torch.zeros(2, 3, 1, dtype=torch.bool), "expert_action": torch.zeros(2, 3, dtype=torch.long)}, [2, 3])
        >>> batch = TensorDict({"steps": steps, "demo_frames": torch.zeros(2, 4, 8, 8, 3, dtype=torch.uint8),
        ...     "demo_actions": torch.zeros(2, 4, dtype=torch.long)}, [2])
        >>> sequence = episodes_to_sequence(batch, device="meta")
        >>> sequence.batch_size, sequence["demo_frames"].shape, sequence["pixels"].device
        (torch.Size([2, 2]), torch.Size([2, 2, 4, 8, 8, 3]), device(type='meta'))
    """
    steps = batch.get("steps")
    length = int(steps.get("mask").sum(-1).max())
    steps = to_device(steps[:, :length], device)
    b, t = steps.batch_size
    demo_frames = batch.get("demo_frames")
    demo_actions = batch.get("demo_actions")
    if device is not None:
        demo_frames, demo_actions = demo_frames.to(device), demo_actions.to(device)
    return TensorDict(
        {
            "pixels": steps.get("pixels"),
            "is_init": steps.get("is_init"),
            "demo_frames": demo_frames.unsqueeze(1).expand(b, t, *demo_frames.shape[1:]),
            "demo_actions": demo_actions.unsqueeze(1).expand(b, t, *demo_actions.shape[1:]),
            "expert_action": steps.get("expert_action"),
            "mask": steps.get("mask"),
        },
        batch_size=[b, t],
        device=device,
    )


def bc_loss(policy: SPFPolicy, batch: TensorDict, amp: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Cross-entropy between the policy's logits and the expert's actions on valid steps.

    The batch moves to the device of the policy's weights first.

    Args:
        policy: the policy (sequence mode is switched on here).
        batch: stored episodes (:mod:`spf_rl.data` layout), on any device.
        amp: run the forward pass under bf16 autocast (the cross-entropy is float32).

    Returns:
        (loss, accuracy of the arg-max action).
    """
    device = module_device(policy)
    sequence = episodes_to_sequence(batch, device)
    with set_recurrent_mode(True), autocast(device, amp):
        sequence = policy(sequence)
    mask = sequence.get("mask")
    logits = sequence.get("logits")[mask].float()
    labels = sequence.get("expert_action")[mask]
    loss = F.cross_entropy(logits, labels)
    accuracy = (logits.argmax(-1) == labels).float().mean()
    return loss, accuracy


def model_memory_bytes(model_type: str, demo_length: int, sparsity: float, image_size: int) -> int:
    """Bytes the agent carries for one demonstration: memory frames (uint8) plus all actions.

    ``"spf_random"`` at ``sparsity`` carries what ``"spf"`` does: only the frames its
    mask keeps, although its network holds a slot for every frame.
    """
    frame_shape = (3, image_size, image_size)
    if model_type == "action_only":
        return demo_length  # one byte per action, no frames
    return memory_bytes(demo_length, 1.0 if model_type in ("rpf", "rpf_original") else sparsity, frame_shape)


def train_bc(config: BCConfig) -> dict:
    """Run (or resume) a behaviour-cloning run and return its results dict (also written to ``results.json``).

    Raises:
        ValueError: ``config.device`` names a device this machine does not have (before any work).
    """
    device = resolve_device(config.device)
    with exact_float32(device, enabled=not config.optim.amp):
        return _train_bc(config, device)


def _train_bc(config: BCConfig, device: torch.device) -> dict:
    start_time = time.time()
    output = Path(config.output_dir)
    output.mkdir(parents=True, exist_ok=True)
    (output / "config.json").write_text(json.dumps(asdict(config), indent=2, default=str))
    torch.manual_seed(config.seed)
    dataset = EpisodeDataset.build(config.resolved_data_dir(), config.data, config.num_workers, config.progress)
    logger.info("dataset: %s", dataset.statistics())

    model_type = config.model.name
    policy_config = spf_config(config.model, config.data.demo_length, config.data.image_size)
    policy = build_policy(model_type, policy_config).to(device)
    logger.info("training on %s%s", device, " with bf16 autocast" if config.optim.amp else "")
    optimizer = torch.optim.Adam(policy.parameters(), lr=config.optim.lr, weight_decay=config.optim.weight_decay)
    batches_per_epoch = -(-len(dataset) // config.optim.batch_size)
    total_steps = batches_per_epoch * config.optim.epochs
    scheduler = (
        torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=total_steps)
        if config.optim.cosine_schedule
        else torch.optim.lr_scheduler.LambdaLR(optimizer, lambda _: 1.0)
    )
    history: list[dict] = []
    best = {"success": -1.0, "spl": -1.0, "epoch": -1}
    start_epoch = 0
    last_path, best_path = output / "last.pt", output / "best.pt"
    if last_path.exists():
        payload = load_checkpoint(last_path, expected_model_type=model_type)
        policy.load_state_dict(payload["model"])
        optimizer.load_state_dict(payload["optimizer"])
        if "scheduler" in payload:
            scheduler.load_state_dict(payload["scheduler"])
        start_epoch, history, best = payload["epoch"], payload["history"], payload["best"]
        torch.set_rng_state(payload["torch_rng"])
        logger.info("resuming %s after epoch %d", output, start_epoch)

    run_logger = get_logger(config.logger, logger_name=str(output / "logs"), experiment_name="bc") if config.logger else None
    val_config = dataclasses.replace(
        config.val, demo_length=config.data.demo_length, max_steps=config.data.max_steps, image_size=config.data.image_size
    )
    step = start_epoch * batches_per_epoch
    for epoch in range(start_epoch, config.optim.epochs):
        policy.train()
        buffer = dataset.replay_buffer(config.optim.batch_size, seed=config.seed * 1000 + epoch)
        losses, accuracies, epoch_start = [], [], time.time()
        bar = tqdm(range(batches_per_epoch), desc=f"epoch {epoch + 1}/{config.optim.epochs}", disable=not config.progress)
        for _ in bar:
            batch = buffer.sample()
            loss, accuracy = bc_loss(policy, batch, amp=config.optim.amp)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(policy.parameters(), config.optim.max_grad_norm)
            optimizer.step()
            scheduler.step()
            step += 1
            losses.append(loss.item())
            accuracies.append(accuracy.item())
            bar.set_postfix(loss=f"{losses[-1]:.3f}", acc=f"{accuracies[-1]:.2f}")
            if run_logger is not None:
                run_logger.log_scalar("train/loss", losses[-1], step=step)
        train_seconds = time.time() - epoch_start
        val, _ = evaluate_policy(policy, val_config, progress=False)
        record = {
            "epoch": epoch + 1,
            "step": step,
            "train_loss": sum(losses) / len(losses),
            "train_accuracy": sum(accuracies) / len(accuracies),
            "val_success": val["success"],
            "val_spl": val["spl"],
            "train_seconds": train_seconds,
        }
        history.append(record)
        logger.info("epoch %d: %s", epoch + 1, record)
        if run_logger is not None:
            for key in ("train_accuracy", "val_success", "val_spl"):
                run_logger.log_scalar(f"epoch/{key}", record[key], step=step)
        if (val["success"], val["spl"]) > (best["success"], best["spl"]):
            best = {"success": val["success"], "spl": val["spl"], "epoch": epoch + 1}
            save_checkpoint(best_path, model_type, policy_config, {"model": policy.state_dict(), "epoch": epoch + 1, "val": val})
        save_checkpoint(
            last_path,
            model_type,
            policy_config,
            {
                "model": policy.state_dict(),
                "optimizer": optimizer.state_dict(),
                "scheduler": scheduler.state_dict(),
                "epoch": epoch + 1,
                "history": history,
                "best": best,
                "torch_rng": torch.get_rng_state(),
            },
        )
    if run_logger is not None and hasattr(run_logger, "experiment"):
        run_logger = None

    payload = load_checkpoint(best_path, expected_model_type=model_type)
    policy.load_state_dict(payload["model"])
    test_config = dataclasses.replace(
        config.test, demo_length=config.data.demo_length, max_steps=config.data.max_steps, image_size=config.data.image_size
    )
    test, records = evaluate_policy(policy, test_config, progress=config.progress)
    results = {
        "model": model_type,
        "sparsity": policy_config.effective_sparsity,
        "memory_frames": policy_config.memory_length,
        "memory_bytes": model_memory_bytes(model_type, config.data.demo_length, config.model.sparsity, config.data.image_size),
        "test": test,
        "best_epoch": best["epoch"],
        "val_best": best,
        "history": history,
        "dataset": dataset.statistics(),
        "seed": config.seed,
        "wall_seconds_this_run": time.time() - start_time,
        "config": asdict(config),
    }
    _atomic_json(output / "results.json", results)
    _atomic_json(output / "test_episodes.json", {"episodes": records})
    from spf_rl.viz import plot_if_available, plot_training_curves

    plot_if_available(plot_training_curves, history, output / "training_curves.png", title=f"BC {model_type}")
    return results


def _atomic_json(path: Path, payload: dict) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(payload, indent=2, default=str))
    os.replace(tmp, path)
