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
``optim.amp`` the loss is computed under bf16 autocast. With ``optim.pointer_coef`` the
loss also holds the policy's pointer to the agent's place on the route
(:func:`pointer_loss`; episodes of a route style carry that label, ``route_step``).
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
import torch.nn.functional as F
from tensordict import TensorDict
from torchrl.modules import set_recurrent_mode
from torchrl.record.loggers import get_logger

from envs.atomic_io import atomic_write_json
from envs.checks import check_positive_ints
from envs.episode_spec import EpisodeSpec, check_sizes_match
from spf_rl.data import MEMORY_MISMATCHED_KEY, ROUTE_STEP_KEY, DatasetConfig, EpisodeDataset
from spf_rl.device import DEFAULT_DEVICE, autocast, check_device, module_device
from spf_rl.evaluation import TEST_SEED, VAL_SEED, EvalConfig, episode_store_root, evaluate_policy
from spf_rl.modules.policy import SPFPolicy
from spf_rl.modules.registry import ModelConfig, build_policy, spf_config
from spf_rl.modules.replay_gate import replay_score
from spf_rl.modules.td_utils import ANCHOR_CONFIDENCE_KEY, ANCHOR_KEY
from spf_rl.modules.views import episodes_to_sequence, model_memory_bytes
from spf_rl.records_cache import TEST_EPISODES_FILE, records_key, write_records
from spf_rl.train.distributed import ShardedSampler, barrier, init_distributed
from spf_rl.train.pointer_guard import RESTARTS_KEY, PointerGuard, restart_run
from spf_rl.train.run import OptimConfig, TrainingRun, run_on_device, run_results, start_run, trim_csv_logs

logger = logging.getLogger(__name__)


def default_val_config() -> EvalConfig:
    """Validation that picks the checkpoint: 300 episodes of the ``val`` split, seed 1
    (fewer pick noisily: the standard error of a success rate on 100 episodes is about 0.05)."""
    return EvalConfig(EpisodeSpec(split="val", max_steps=50, seed=VAL_SEED), num_episodes=300, store_root=episode_store_root())


#: The preset of the main job (``python recipes/bc.py`` with no preset, ``scripts/main.sh``):
#: ``recipes/configs/bc_main.yaml``. :class:`BCConfig`'s defaults are the paper's recipe (``bc_paper``).
MAIN_JOB_PRESET = "bc_main"


def default_test_config() -> EvalConfig:
    """The final test of the best checkpoint: 500 episodes of the ``test`` split, seed 2."""
    return EvalConfig(EpisodeSpec(split="test", max_steps=50, seed=TEST_SEED), num_episodes=500, store_root=episode_store_root())


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
        model: the policy (:class:`~spf_rl.modules.registry.ModelConfig`).
        optim: the optimiser (:class:`OptimConfig`).
        val: validation rollouts; the best validated epoch is kept as ``best.pt``.
        val_every: validate after every ``val_every``-th epoch and after the last one.
        test: final evaluation of the best checkpoint.
        keep_epochs: also keep every epoch's weights (``epochs/epoch-001.pt``, ...), for
            studies of checkpoint picking (``recipes/picking_study.py``).

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
    val: EvalConfig = field(default_factory=default_val_config)
    test: EvalConfig = field(default_factory=default_test_config)
    val_every: int = 3
    keep_epochs: bool = False

    def __post_init__(self) -> None:
        check_device(self.device)
        check_positive_ints(self, ("val_every",))
        check_pointer_labels(self.optim, self.data.episodes.route_style, "data.route_style")
        check_no_replay_gate_loss(self.optim)
        check_sizes_match(self.data.episodes, "data", val=self.val.episodes, test=self.test.episodes)

    def validates_after(self, epoch: int) -> bool:
        """Whether epoch ``epoch`` (from 1) is validated: every ``val_every``-th one and the last."""
        return epoch % self.val_every == 0 or epoch == self.optim.epochs

    def resolved_data_dir(self) -> Path:
        """``data_dir``, or the dataset's default directory (:meth:`~spf_rl.data.DatasetConfig.default_dir`)."""
        return Path(self.data_dir) if self.data_dir else self.data.default_dir()


def check_no_replay_gate_loss(optim: OptimConfig) -> None:
    """Raise ``ValueError`` if ``optim.replay_gate_coef`` > 0 for a run whose network (built from a
    :class:`~spf_rl.modules.registry.ModelConfig`) has no replay gate: only DAgger grows one.

    Examples:
        >>> check_no_replay_gate_loss(OptimConfig(replay_gate_coef=0.5))
        Traceback (most recent call last):
        ...
        ValueError: optim.replay_gate_coef > 0 needs a network with a replay gate, which only DAgger grows (recipes/dagger.py replay_gate=true); set optim.replay_gate_coef=0.
    """
    if optim.replay_gate_coef > 0:
        raise ValueError(
            "optim.replay_gate_coef > 0 needs a network with a replay gate, which only DAgger grows "
            "(recipes/dagger.py replay_gate=true); set optim.replay_gate_coef=0."
        )


def check_pointer_labels(optim: OptimConfig, route_style: str | None, name: str) -> None:
    """Raise ``ValueError`` if ``optim.pointer_coef`` > 0 on episodes without pointer labels
    (only episodes of a route style, labelled by the route expert, carry ``route_step``).

    Examples:
        >>> check_pointer_labels(OptimConfig(pointer_coef=0.1), None, "data.route_style")
        Traceback (most recent call last):
        ...
        ValueError: optim.pointer_coef > 0 needs episodes of a route style (their route_step labels the pointer): set data.route_style (e.g. 'planner=1,tour=1,driven=1'), or optim.pointer_coef=0.
    """
    if optim.pointer_coef > 0 and route_style is None:
        raise ValueError(
            f"optim.pointer_coef > 0 needs episodes of a route style (their {ROUTE_STEP_KEY} labels the pointer): "
            f"set {name} (e.g. 'planner=1,tour=1,driven=1'), or optim.pointer_coef=0."
        )


def bc_loss(
    policy: SPFPolicy,
    batch: TensorDict,
    amp: bool = False,
    pointer_coef: float = 0.0,
    parts: dict[str, float] | None = None,
    replay_gate_coef: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Cross-entropy between the policy's logits and the expert's actions on valid steps,
    plus ``pointer_coef`` times the :func:`pointer_loss` and ``replay_gate_coef`` times the
    :func:`replay_gate_loss`.

    The batch moves to the device of the policy's weights first.

    Args:
        policy: the policy (sequence mode is switched on here).
        batch: stored episodes (:mod:`spf_rl.data` layout), on any device; with
            ``pointer_coef`` > 0 their steps must hold ``route_step``.
        amp: run the forward pass under bf16 autocast (the cross-entropy is float32).
        pointer_coef: weight of the pointer loss (0: the cross-entropy alone).
        parts: if given, receives the loss's parts as numbers: ``"cross_entropy"`` and, with
            ``pointer_coef`` > 0, ``"pointer"`` (the pointer loss before its weight), with
            ``replay_gate_coef`` > 0 ``"replay_gate"``, so that a training loop can log them apart.
        replay_gate_coef: weight of the replay gate's loss (0: none; > 0 needs a policy with a
            replay gate).

    Returns:
        (loss, accuracy of the arg-max action).
    """
    if pointer_coef > 0 and ROUTE_STEP_KEY not in batch.get("steps").keys():
        raise ValueError(
            f"pointer_coef > 0 needs {ROUTE_STEP_KEY!r} in the episodes' steps (datasets and DAgger rounds of a "
            "route style store it); these episodes have none."
        )
    gate = replay_gate_of(policy)
    if replay_gate_coef > 0 and gate is None:
        raise ValueError("optim.replay_gate_coef > 0 needs a policy with a replay gate (SPFConfig.replay_gate); set it to 0.")
    device = module_device(policy)
    sequence = episodes_to_sequence(batch, device)
    with set_recurrent_mode(True), autocast(device, amp):
        # padded steps (after each episode's end) are not encoded: they are not in the loss
        sequence = policy(sequence, valid=sequence.get("mask"))
    mask = sequence.get("mask")
    logits = sequence.get("logits")[mask].float()
    labels = sequence.get("expert_action")[mask]
    loss = F.cross_entropy(logits, labels)
    accuracy = (logits.argmax(-1) == labels).float().mean()
    if parts is not None:
        parts["cross_entropy"] = loss.item()
    if pointer_coef > 0:
        pointer = pointer_loss(sequence, getattr(getattr(unwrapped(policy), "config", None), "anchor_radius", None))
        loss = loss + pointer_coef * pointer
        if parts is not None:
            parts["pointer"] = pointer.item()
    if replay_gate_coef > 0:
        gate_loss = replay_gate_loss(sequence, gate)
        loss = loss + replay_gate_coef * gate_loss
        if parts is not None:
            parts["replay_gate"] = gate_loss.item()
    return loss, accuracy


def unwrapped(policy: torch.nn.Module) -> torch.nn.Module:
    """The policy itself: the wrapped one under data-parallel training (its config and layers are there)."""
    return policy.module if isinstance(policy, torch.nn.parallel.DistributedDataParallel) else policy


def replay_gate_of(policy) -> torch.nn.Linear | None:
    """The policy's replay gate layer (:mod:`spf_rl.modules.replay_gate`; the wrapped policy's under
    data-parallel training), ``None`` where it has none."""
    return getattr(getattr(unwrapped(policy), "cell", None), "replay_gate", None)


def replay_gate_loss(sequence: TensorDict, gate: torch.nn.Linear) -> torch.Tensor:
    """Binary cross-entropy of the replay gate's opening on the valid steps against whether the episode's
    memory shows another route (:data:`~spf_rl.data.MEMORY_MISMATCHED_KEY`; episodes without the key
    show their own): the gate learns to fall back on blind replay where the frames it carries are not
    the route's, and to stay shut where they are. The imitation loss alone moves it slowly: shut, its
    gradient is small and of either sign from step to step.

    Args:
        sequence: the policy's output on a ``[B, T]`` sequence with ``mask``, ``features`` (the cell's
            new hidden state) and ``anchor_confidence``.
        gate: the policy's gate layer (:func:`replay_gate_of`).

    Examples:
        >>> from spf_rl.modules.replay_gate import replay_gate_layer
        >>> sequence = TensorDict({"features": torch.zeros(1, 2, 3), "anchor_confidence": torch.zeros(1, 2, 1),
        ...     "mask": torch.tensor([[True, True]]), "memory_mismatched": torch.tensor([[True, True]])}, [1, 2])
        >>> round(replay_gate_loss(sequence, replay_gate_layer(3)).item(), 3)  # shut where it should open: -log(sigmoid(-4))
        4.018
    """
    mask = sequence.get("mask")
    score = replay_score(sequence.get("features")[mask].float(), sequence.get(ANCHOR_CONFIDENCE_KEY)[mask].float().reshape(-1, 1), gate)
    if MEMORY_MISMATCHED_KEY in sequence.keys():
        target = sequence.get(MEMORY_MISMATCHED_KEY)[mask].reshape(-1, 1).to(score.dtype)
    else:
        target = torch.zeros_like(score)
    return F.binary_cross_entropy_with_logits(score, target)


def pointer_loss(sequence: TensorDict, anchor_radius: float | None = None) -> torch.Tensor:
    """Huber loss (threshold 1 step) between the pointer each valid step used (``eta_used``) and
    the agent's place on the route then (``route_step``, at most each demonstration's last step).

    The pointer counts demonstration steps (RPF's rule, or the paper's), so it should stand
    where the agent is: the pointer trace (:mod:`spf_rl.eval.pointer_trace`) shows the
    routes model failing once its pointer runs ahead of the agent, out of the attention
    window. The label is the route expert's (:meth:`~envs.route_expert.RouteExpert.route_step`).

    Args:
        sequence: the policy's output on a ``[B, T]`` sequence with ``mask``, ``eta_used``,
            ``route_step`` and, for demonstrations of several lengths, ``demo_steps``.
        anchor_radius: the policy's ``anchor_radius``: with it, the :func:`anchor_loss` of the
            policy's ``anchor`` is added (``None``: the pointer alone).

    Examples:
        >>> sequence = TensorDict({"eta_used": torch.tensor([[[0.0], [3.0], [9.0]]]),
        ...     "route_step": torch.tensor([[[0], [1], [5]]]), "mask": torch.tensor([[True, True, False]]),
        ...     "demo_steps": torch.tensor([[[4], [4], [4]]])}, [1, 3])
        >>> pointer_loss(sequence)  # errors 0 and 2 steps: (0 + 1.5) / 2
        tensor(0.7500)
    """
    if "eta_used" not in sequence.keys():
        raise ValueError("the pointer loss needs a policy with a pointer (it writes eta_used); this one has none.")
    mask = sequence.get("mask")
    eta = sequence.get("eta_used")[mask].float().reshape(-1)
    target = sequence.get(ROUTE_STEP_KEY)[mask].reshape(-1)
    if "demo_steps" in sequence.keys():  # the route's end pose counts as its last step
        target = torch.minimum(target, sequence.get("demo_steps")[mask].reshape(-1) - 1)
    target = target.to(eta.dtype)
    loss = F.smooth_l1_loss(eta, target)
    if anchor_radius is not None and ANCHOR_KEY in sequence.keys():
        loss = loss + anchor_loss(sequence, eta, target, anchor_radius)
    return loss


def anchor_loss(sequence: TensorDict, eta: torch.Tensor, target: torch.Tensor, radius: float) -> torch.Tensor:
    """For a policy that re-anchors its pointer (:mod:`spf_rl.modules.anchor`): the Huber loss between
    its anchor and the agent's place (``target``, as :func:`pointer_loss` reads it) on the valid steps
    where that place lies within ``radius`` of the pointer (``eta``: the anchor's search band) and the memory
    holds the route's own frames (not :data:`~spf_rl.data.MEMORY_MISMATCHED_KEY`); 0 where no
    step qualifies. It teaches the frame-to-slot match directly, before the gate opens.

    Examples:
        >>> sequence = TensorDict({"anchor": torch.tensor([[[2.0], [9.0]]]), "mask": torch.tensor([[True, True]]),
        ...     "memory_mismatched": torch.tensor([[False, False]])}, [1, 2])
        >>> anchor_loss(sequence, torch.tensor([2.0, 30.0]), torch.tensor([1.0, 4.0]), 8.0)  # step 2: outside the band
        tensor(0.5000)
    """
    mask = sequence.get("mask")
    place = sequence.get(ANCHOR_KEY)[mask].float().reshape(-1)
    counted = (target - eta).abs() <= radius
    if MEMORY_MISMATCHED_KEY in sequence.keys():
        counted = counted & ~sequence.get(MEMORY_MISMATCHED_KEY)[mask].reshape(-1)
    if not bool(counted.any()):
        return place.sum() * 0.0
    return F.smooth_l1_loss(place[counted], target[counted])


def train_bc(config: BCConfig) -> dict:
    """Run (or resume) a behaviour-cloning run and return its results dict (also written to ``results.json``).

    Under ``torchrun --nproc_per_node N`` the run is data-parallel (:mod:`spf_rl.train.distributed`):
    rank 0 returns the results and writes every file; the other ranks return their rank and history.

    Raises:
        ValueError: an unknown ``config.device``, or a run in ``output_dir`` with other settings (before any work).
    """
    return run_on_device(_train_bc, config)


def _train_bc(config: BCConfig, device: torch.device) -> dict:
    start_time = time.time()
    ranks, device = init_distributed(device)
    output = start_run(config, ranks=ranks)
    dataset = EpisodeDataset.build(config.resolved_data_dir(), config.data, config.num_workers, config.progress)
    logger.info("dataset: %s", dataset.statistics())

    model_type = config.model.name
    policy_config = spf_config(config.model, config.data.episodes.demo_length, config.data.episodes.image_size)
    policy = build_policy(model_type, policy_config).to(device)
    logger.info("training on %s%s", device, " with bf16 autocast" if config.optim.amp else "")
    batches_per_epoch = -(-len(dataset) // config.optim.batch_size)

    def new_run() -> TrainingRun:
        return TrainingRun(
            output, model_type, policy_config, policy, config.optim, batches_per_epoch * config.optim.epochs,
            config.keep_epochs, loss_fn=bc_loss, ranks=ranks,
        )

    run = new_run()
    epoch = run.resume(state_keys=(RESTARTS_KEY,))
    if config.logger and ranks.is_main:
        trim_csv_logs(output / "logs", run.step)

    run_logger = get_logger(config.logger, logger_name=str(output / "logs"), experiment_name="bc") if config.logger and ranks.is_main else None
    val_config = config.val
    guard = PointerGuard.of(policy, dataset)
    while epoch < config.optim.epochs:
        sampler = ShardedSampler(ranks) if ranks.distributed else None
        buffer = dataset.replay_buffer(config.optim.batch_size, seed=config.seed * 1000 + epoch, sampler=sampler)
        batches = (buffer.sample() for _ in range(batches_per_epoch))
        losses, accuracies, train_seconds = run.train_epoch(
            batches, batches_per_epoch, f"epoch {epoch + 1}/{config.optim.epochs}", config.progress and ranks.is_main, run_logger
        )
        validate = config.validates_after(epoch + 1) and ranks.is_main
        val = evaluate_policy(policy, val_config, progress=False)[0] if validate else None
        pace = guard.pace(policy, ranks) if guard is not None else None  # one decision for every rank
        if PointerGuard.collapsed(pace) and (restarted := restart_run(run, new_run, config.seed, epoch + 1, pace)):
            run, epoch = restarted, 0  # the collapsed epoch is not kept: last.pt is the restart's
            if config.logger and ranks.is_main:  # the collapsed attempt's rows go, and a fresh logger writes on
                trim_csv_logs(output / "logs", 0)
                run_logger = get_logger(config.logger, logger_name=str(output / "logs"), experiment_name="bc")
            barrier(ranks)
            continue
        record = run.end_epoch(epoch, losses, accuracies, train_seconds, val, run_logger, pointer_pace=pace)
        logger.info("epoch %d: %s", epoch + 1, record)
        barrier(ranks)  # the other ranks wait for rank 0's validation and checkpoints
        epoch += 1
    history, best = run.history, run.best
    if run_logger is not None and hasattr(run_logger, "experiment"):
        run_logger = None
    if not ranks.is_main:
        return {"rank": ranks.rank, "history": history}

    run.load_best()
    test_config = config.test
    test, records = evaluate_policy(policy, test_config, progress=config.progress)
    results = {
        "model": model_type,
        "sparsity": policy_config.effective_sparsity,
        "memory_frames": policy_config.memory_length,
        "memory_bytes": model_memory_bytes(model_type, config.data.episodes.demo_length, config.model.sparsity, config.data.episodes.image_size),
        "test": test,
        "best_epoch": best["epoch"],
        "val_best": best,
        "history": history,
        "dataset": dataset.statistics(),
        RESTARTS_KEY: run.state.get(RESTARTS_KEY, []),
        **run_results(config, time.time() - start_time),
    }
    atomic_write_json(output / "results.json", results, default=str)
    write_records(output / TEST_EPISODES_FILE, records_key(test_config, policy), records, checkpoint=str(run.best_path))
    from spf_rl.viz import plot_if_available, plot_training_curves

    plot_if_available(plot_training_curves, history, output / "training_curves.png", title=f"BC {model_type}")
    return results
