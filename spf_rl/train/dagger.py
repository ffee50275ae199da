"""DAgger from a behaviour-cloning checkpoint.

Round ``r = 1..R``: play ``episodes_per_round`` numbered episodes of the round's seed
(their demonstrations rendered once into an episode store, looked up by the learner)
with a mixture of the learner and the expert (per step the expert's action with
probability ``beta_r = beta0 * beta_decay ** (r - 1)``, else the learner's greedy
action) through a TorchRL collector, label every visited state with the expert (the
env's ``expert_action``), store the round's episodes on disk, and retrain the learner with the BC loss for a fixed number of
gradient steps on a sliding window of the latest ``window_rounds`` rounds plus the
BC dataset (by default). Round 0 is the starting BC model.

The default is the improvement phase of the first author's code (``Hwiyeon/RPF``,
``RPF_DAgger/DAgger.py``): the learner drives every step (``beta0 = 0``), and
training sees a sliding window of recent learner episodes. The expert-driven
control (``beta0 = 1, beta_decay = 1``: the same steps on expert-visited states)
tells what the learner's own states add (``recipes/configs/dagger_control.yaml``).
Every round is scored on the ``val`` split (and on ``test`` when
``test_every_round``); the results go to ``results.json`` and ``dagger.png``.

Resuming: the round's episodes (``rounds/round-XX``, a
:class:`~spf_rl.train.dagger_rounds.RoundStore`) and ``last.pt`` (atomic) are the durable state; an
interrupted run started again with the same config reads the stored rounds
and continues with the next round. Collection is deterministic and does not depend
on the collector layout: the round's numbered episodes, the mixing coin (a Philox
draw of the episode seed and step) and the greedy learner fix every visited state.
So the run also keeps the learners that collected its window of rounds
(``learners/learner-XX.pt``, :func:`~spf_rl.train.dagger_rounds.learner_path`, about the size
of the policy each); where a window round's episodes are missing (the run moved to another
machine with ``last.pt`` and ``learners/`` but not the gigabytes of ``rounds/``), resuming
collects them again. Those two are the whole resume state: a resumed run does not read the
starting checkpoint.

The learner and its optimiser run on ``DAggerConfig.device`` (see
:mod:`spf_rl.device`): the collector gets it as ``policy_device`` with the envs on
the CPU and stores the round's episodes on the CPU (they go to disk); training
batches move to the device in :func:`~spf_rl.train.bc.bc_loss`. ``optim.amp``
computes the retraining loss under bf16 autocast; collection and scoring stay float32.
"""
from __future__ import annotations

import json
import logging
import shutil
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.record.loggers import get_logger

from envs.atomic_io import atomic_write_json
from envs.demo_store import DemoStore
from envs.episode_spec import check_sizes_match
from envs.episodes import STEPS_PER_BATCH, gather_episode_steps
from envs.scripted import behaviour_coins
from spf_rl.checkpoint import load_checkpoint, save_checkpoint
from spf_rl.data import DatasetConfig, EpisodeDataset, demos_root, episode_keys, step_keys
from spf_rl.device import DEFAULT_DEVICE, check_device, exact_float32, module_device, torch_threads_kept
from spf_rl.evaluation import EvalConfig, FramesFromStore, evaluate_policy, summarize_episodes
from spf_rl.hub import DEFAULT_START_CHECKPOINT, checked_checkpoint, shipped_file_sha256
from spf_rl.modules.config import SPFConfig
from spf_rl.modules.policy import SPFPolicy
from spf_rl.modules.registry import build_policy
from spf_rl.records_cache import TEST_EPISODES_FILE, read_records, records_key, write_records
from spf_rl.train.bc import bc_loss, check_pointer_labels, default_test_config, default_val_config
from spf_rl.train.collection import CollectionEnvConfig, CollectorConfig, collection_device, make_collector
from spf_rl.train.dagger_rounds import (
    RoundConfig,
    RoundStore,
    learner_path,
    round_demo_config,
    round_directory,
    source_rows,
    training_sources,
)
from spf_rl.train.distributed import Ranks, barrier, init_distributed, shard_indices
from spf_rl.train.pointer_guard import COLLAPSE_PACE, PointerGuard
from spf_rl.train.run import OptimConfig, TrainingRun, run_results, trim_csv_logs
from spf_rl.train.run_config import DAGGER_RESUME_FREE, write_run_config
from spf_rl.viz import plot_if_available, pyplot, write_figure

logger = logging.getLogger(__name__)

#: Mixed into the episode seed so the mixing coin is independent of the actuation noise.
MIXING_STREAM_SALT = 0x5DA66E4
#: Mixed into a retraining step's seed (:func:`retraining_seed`): a stream of its own.
RETRAINING_STREAM = 0x7E7A1
DAGGER_VAL_SEED = 3  # not the BC val seed (1), on which the starting checkpoint was picked


def default_dagger_val_config() -> EvalConfig:
    """BC's validation size and split on fresh episodes: the start (round 0) was picked as
    the best of its BC run on seed 1's episodes, a maximum of noisy scores that would favour it there."""
    val = default_val_config()
    return replace(val, episodes=val.episodes.replace(seed=DAGGER_VAL_SEED))


class ExpertMixturePolicy(TensorDictModuleBase):
    """DAgger's behaviour policy: the learner, or the expert with probability ``beta``.

    The learner runs at every step (so its recurrent state follows the episode);
    ``"action"`` is then the expert's ``"expert_action"`` where a coin with
    probability ``beta`` comes up, else the learner's arg-max action. The coin
    of a step is a Philox draw of ``(episode_seed, step_count)``, so the same
    episodes give the same actions in any process and batch layout.

    Args:
        learner: module writing ``"logits"`` (e.g. :class:`~spf_rl.modules.SPFPolicy`).
        beta: probability of the expert's action, in ``[0, 1]``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule
        >>> learner = TensorDictModule(lambda p: torch.zeros(p.shape[0], 3), ["pixels"], ["logits"])
        >>> td = TensorDict({"pixels": torch.zeros(4, 1), "expert_action": torch.full((4,), 2),
        ...     "episode_seed": torch.arange(4)[:, None], "step_count": torch.zeros(4, 1, dtype=torch.long)}, [4])
        >>> ExpertMixturePolicy(learner, beta=1.0)(td)["action"].tolist()
        [2, 2, 2, 2]
        >>> ExpertMixturePolicy(learner, beta=0.0)(td)["action"].tolist()
        [0, 0, 0, 0]
    """

    def __init__(self, learner: TensorDictModuleBase, beta: float) -> None:
        super().__init__()
        if not 0.0 <= float(beta) <= 1.0:
            raise ValueError(f"beta must be in [0, 1], got {beta!r}.")
        self.learner = learner
        self.beta = float(beta)
        self.in_keys = list(dict.fromkeys([*learner.in_keys, "expert_action", "episode_seed", "step_count"]))
        self.out_keys = list(dict.fromkeys([*learner.out_keys, "action"]))

    def make_tensordict_primer(self):
        """The learner's primer (its recurrent state), if it has one."""
        return self.learner.make_tensordict_primer()

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict = self.learner(tensordict)
        action = tensordict.get("logits").argmax(-1)
        if self.beta > 0.0:
            expert = tensordict.get("expert_action").reshape(action.shape).to(action.dtype)
            coin = behaviour_coins(tensordict, MIXING_STREAM_SALT, 1)[:, 0].reshape(action.shape).to(action.device)
            action = torch.where(coin < self.beta, expert, action)
        tensordict.set("action", action)
        return tensordict


@dataclass
class DAggerConfig:
    """A DAgger run.

    Args:
        checkpoint: the BC checkpoint to start from: a path, or a shipped name
            (:func:`spf_rl.list_checkpoints`).
        output_dir: checkpoints, round data, logs, results and figures.
        seed: seed of collection and batching.
        device: where the learner trains and acts: ``"auto"`` (CUDA if available, else
            the CPU), ``"cpu"``, ``"cuda"`` or ``"cuda:N"``; envs stay on the CPU.
        rounds: DAgger rounds after the starting model.
        round_seed_offset: round ``r``'s episodes are drawn with the seed ``(seed, r +
            round_seed_offset)``. 0 by default; a run that continues an earlier run's kept
            weights sets it to that run's ``rounds``, so that its rounds draw routes the
            earlier rounds did not.
        anchor_radius: grow an anchor of this radius (:mod:`spf_rl.modules.anchor`) onto a starting
            checkpoint that has none: its layers drawn from ``seed``, its gate nearly shut, every other
            weight loaded as it was. ``None`` (default): the checkpoint's own network.
        normalize_frames: set the starting network's ``normalize_frames`` (``SPFConfig``: every frame
            standardised per channel before the encoder; no new weights) to this. ``None`` (default):
            the checkpoint's own.
        replay_gate: grow a replay gate (:mod:`spf_rl.modules.replay_gate`: the actions and the
            pointer moved toward blind replay where the memory disagrees with the view) onto a starting
            checkpoint that has none: its layer nearly shut. Needs an anchor (the checkpoint's or
            ``anchor_radius``). ``None`` or false (default): the checkpoint's own network.
        episodes_per_round: learner episodes collected per round.
        beta0: expert probability in round 1.
        beta_decay: ``beta`` is multiplied by this each round.
        aggregate_bc_data: train on the BC dataset ``bc_data`` (built if missing) beside
            the window of rounds; otherwise only DAgger's episodes are trained on.
        bc_data: the BC dataset (default: the one ``recipes/bc.py`` builds).
        bc_data_dir: its directory (``None``: the BC recipe's default naming).
        epochs_per_round: passes over the training episodes after each round (used when
            ``steps_per_round`` is ``None``).
        steps_per_round: gradient steps after each round (``None``: ``epochs_per_round``
            passes over the training episodes). 500 by default.
        window_rounds: train on the episodes of the latest this many rounds (plus the BC
            data); ``None``: every round so far. 4 by default (about 1,000 learner episodes).
        rounds_share: the share of every retraining batch drawn from the window of rounds, the rest
            from the BC data (each part without replacement, pass after pass; needs
            ``aggregate_bc_data``), so that the learner's own episodes weigh as much as the run asks
            whatever the BC data's size. ``None`` (default): every episode of the pool equally likely
            (the window is then about a fifth of a batch beside 4,000 BC episodes).
        test_every_round: also score every round on the test split (else only
            the start and the final best model).
        num_workers: processes building the BC dataset, if it is missing.
        logger: torchrl logger backend or ``""``.
        progress: progress bars.
        env: the collection episodes (split, noise, sizes).
        collector: collection backend and layout.
        optim: optimiser (``epochs`` is ignored: see ``epochs_per_round``; ``amp``:
            bf16 autocast for the retraining loss).
        val: validation after every round, round 0 included (default: 300 episodes of the
            ``val`` split at seed 3, fresh to the BC run that picked the start on seed 1).
        test: test evaluation.
    """

    checkpoint: str = DEFAULT_START_CHECKPOINT
    output_dir: str = "runs/dagger"
    seed: int = 0
    device: str = DEFAULT_DEVICE
    rounds: int = 10
    round_seed_offset: int = 0
    anchor_radius: int | None = None
    normalize_frames: bool | None = None
    replay_gate: bool | None = None
    episodes_per_round: int = 256
    beta0: float = 0.0
    beta_decay: float = 0.5
    aggregate_bc_data: bool = True
    bc_data: DatasetConfig = field(default_factory=DatasetConfig)
    bc_data_dir: str | None = None
    epochs_per_round: int = 1
    steps_per_round: int | None = 500
    window_rounds: int | None = 4
    rounds_share: float | None = None
    test_every_round: bool = True
    num_workers: int = 2
    logger: str = "csv"
    progress: bool = True
    env: CollectionEnvConfig = field(default_factory=CollectionEnvConfig)
    collector: CollectorConfig = field(default_factory=CollectorConfig)
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(lr=3e-4, cosine_schedule=False))
    val: EvalConfig = field(default_factory=default_dagger_val_config)
    test: EvalConfig = field(default_factory=default_test_config)

    def __post_init__(self) -> None:
        check_device(self.device)
        for name in ("rounds", "round_seed_offset", "episodes_per_round", "epochs_per_round"):
            value, least = getattr(self, name), 0 if name in ("rounds", "round_seed_offset") else 1
            if isinstance(value, bool) or not isinstance(value, int) or value < least:
                raise ValueError(f"{name} must be a {'non-negative' if least == 0 else 'positive'} int, got {value!r}.")
        for name in ("steps_per_round", "window_rounds", "anchor_radius"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
                raise ValueError(f"{name} must be a positive int or None, got {value!r}.")
        if self.normalize_frames is not None and not isinstance(self.normalize_frames, bool):
            raise ValueError(f"normalize_frames must be true, false or None (the checkpoint's own), got {self.normalize_frames!r}.")
        if self.replay_gate is not None and not isinstance(self.replay_gate, bool):
            raise ValueError(f"replay_gate must be true, false or None (the checkpoint's own), got {self.replay_gate!r}.")
        if self.optim.replay_gate_coef > 0 and self.replay_gate is False:
            raise ValueError("optim.replay_gate_coef > 0 needs the replay gate: set replay_gate=true (or leave it unset for a gated checkpoint).")
        if self.rounds_share is not None:
            if isinstance(self.rounds_share, bool) or not isinstance(self.rounds_share, (int, float)) or not 0.0 < self.rounds_share < 1.0:
                raise ValueError(f"rounds_share must be in (0, 1) or None (every episode equally likely), got {self.rounds_share!r}.")
            if not self.aggregate_bc_data:
                raise ValueError("rounds_share needs aggregate_bc_data: true (it shares each batch between the BC data and the rounds).")
            if self.optim.batch_size < 2:
                raise ValueError(f"rounds_share needs optim.batch_size >= 2 (a row of each part), got {self.optim.batch_size}.")
        for name in ("beta0", "beta_decay"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)!r}.")
        check_pointer_labels(self.optim, self.env.episodes.route_style, "env.route_style")
        check_sizes_match(self.env.episodes, "env", val=self.val.episodes, test=self.test.episodes)
        if self.aggregate_bc_data:
            check_pointer_labels(self.optim, self.bc_data.episodes.route_style, "bc_data.route_style")

    def beta(self, round_index: int) -> float:
        """Expert probability of round ``round_index`` (1-based)."""
        return self.beta0 * self.beta_decay ** (round_index - 1)


def behaviour_statistics(episodes: TensorDictBase) -> dict:
    """Count, success rate and mean length of a round's behaviour episodes (whole episodes,
    each played once from its start, so their success rate measures the behaviour policy).

    Examples:
        >>> from tensordict import TensorDict
        >>> episodes = TensorDict({"success": torch.tensor([True, False]), "length": torch.tensor([3, 50])}, [2])
        >>> behaviour_statistics(episodes)
        {'episodes': 2, 'behaviour_success': 0.5, 'mean_length': 26.5}
    """
    return {
        "episodes": int(episodes.shape[0]),
        "behaviour_success": float(episodes["success"].float().mean()),
        "mean_length": float(episodes["length"].float().mean()),
    }


def episode_seed_of_round(config: DAggerConfig, round_index: int) -> int:
    """The seed of the episodes round ``round_index`` collects: from ``(config.seed, round_index +
    config.round_seed_offset)``.

    Examples:
        >>> first, more = DAggerConfig(), DAggerConfig(round_seed_offset=10)
        >>> episode_seed_of_round(more, 1) == episode_seed_of_round(first, 11) != episode_seed_of_round(first, 1)
        True
    """
    return int(np.random.SeedSequence([config.seed, round_index + config.round_seed_offset]).generate_state(1)[0] % (2**31))


def start_policy(
    model_type: str,
    policy_config: SPFConfig,
    weights: dict,
    anchor_radius: int | None,
    seed: int,
    normalize_frames: bool | None = None,
    replay_gate: bool | None = None,
) -> tuple[SPFConfig, SPFPolicy]:
    """The policy DAgger starts from: ``weights`` in the checkpoint's network, or that network grown
    what it lacks: with ``anchor_radius``, an anchor; with ``replay_gate`` true, a replay gate (their
    layers drawn from ``seed``, every other weight loaded as it was); with ``normalize_frames`` (not
    ``None``), its encoder set to standardise frames or not.

    Raises:
        ValueError: the checkpoint has an anchor of another radius, or a replay gate that
            ``replay_gate`` false would drop, or its weights do not fit.

    Examples:
        >>> from spf_rl.modules import SPFConfig
        >>> from spf_rl.modules.registry import build_policy
        >>> config = SPFConfig(demo_length=6, feature_dim=8, hidden_size=8, image_size=(16, 16), pointer_update="rpf")
        >>> grown_config, grown = start_policy("spf", config, build_policy("spf", config).state_dict(), 4, seed=0)
        >>> grown_config.anchor_radius, grown.anchors
        (4, True)
        >>> normalized_config, normalized = start_policy("spf", config, build_policy("spf", config).state_dict(), None, 0, True)
        >>> normalized_config.normalize_frames, normalized.encoder.module.normalize
        (True, True)
        >>> gated_config, gated = start_policy("spf", grown_config, grown.state_dict(), None, 0, replay_gate=True)
        >>> gated_config.replay_gate, gated.cell.replay_gate is not None
        (True, True)
    """
    if normalize_frames is not None and normalize_frames != policy_config.normalize_frames:
        policy_config = replace(policy_config, normalize_frames=normalize_frames)
        logger.info("the starting policy's encoder %s frames", "standardises" if normalize_frames else "no longer standardises")
    if replay_gate is False and policy_config.replay_gate:
        raise ValueError("replay_gate=false but the checkpoint's policy has a replay gate; leave replay_gate unset (null).")
    grow_anchor = anchor_radius is not None and policy_config.anchor_radius != anchor_radius
    grow_gate = bool(replay_gate) and not policy_config.replay_gate
    if grow_anchor and policy_config.anchor_radius is not None:
        raise ValueError(f"anchor_radius={anchor_radius} but the checkpoint's policy already anchors with radius {policy_config.anchor_radius}.")
    if not (grow_anchor or grow_gate):
        policy = build_policy(model_type, policy_config)
        policy.load_state_dict(weights)
        return policy_config, policy
    grown_config = replace(
        policy_config,
        anchor_radius=anchor_radius if grow_anchor else policy_config.anchor_radius,
        replay_gate=policy_config.replay_gate or grow_gate,
    )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        policy = build_policy(model_type, grown_config)
    missing, unexpected = policy.load_state_dict(weights, strict=False)
    new_parts = (("anchor",) if grow_anchor else ()) + (("replay_gate",) if grow_gate else ())
    foreign = [key for key in missing if not any(part in key for part in new_parts)]
    if unexpected or foreign:
        raise ValueError(f"the checkpoint's weights do not fit its network grown {' and '.join(new_parts)} (missing {foreign}, unexpected {unexpected}).")
    if grow_anchor:
        logger.info("grew an anchor of radius %d onto the starting policy", anchor_radius)
    if grow_gate:
        logger.info("grew a replay gate onto the starting policy")
    logger.info("%d new tensors", len(missing))
    return grown_config, policy


def train_dagger(config: DAggerConfig) -> dict:
    """Run (or resume) DAgger and return its results (also written to ``results.json``).

    Raises:
        ValueError: ``config.device`` names a device this machine does not have, or ``output_dir``
            holds a run started with other settings (before any work).
    """
    device = collection_device(config.device, config.collector)
    with exact_float32(device, enabled=not config.optim.amp):
        return _train_dagger(config, device)


def _train_dagger(config: DAggerConfig, device: torch.device) -> dict:
    start_time = time.time()
    ranks, device = init_distributed(device)
    output = Path(config.output_dir)
    if ranks.is_main:
        write_run_config(output, config, free=DAGGER_RESUME_FREE)
        (output / "rounds").mkdir(parents=True, exist_ok=True)
    barrier(ranks)
    last_path, best_path = output / "last.pt", output / "best.pt"
    # a resumed run needs only its own state (last.pt, learners/), not the starting checkpoint
    start_path = None if last_path.exists() else checked_checkpoint(config.checkpoint)
    payload = load_checkpoint(last_path if start_path is None else start_path, known_file_sha256=shipped_file_sha256())
    model_type, policy_config = payload["model_type"], payload["model_config"]
    env = config.env
    if (policy_config.demo_length, policy_config.image_size) != (env.episodes.demo_length, (env.episodes.image_size,) * 2):
        raise ValueError(
            f"env.demo_length / env.image_size ({env.episodes.demo_length}, {env.episodes.image_size}) must match the checkpoint's "
            f"({policy_config.demo_length}, {policy_config.image_size})."
        )
    policy_config, policy = start_policy(
        model_type, policy_config, payload["model"], config.anchor_radius, config.seed, config.normalize_frames, config.replay_gate
    )
    if config.optim.replay_gate_coef > 0 and not policy_config.replay_gate:
        raise ValueError("optim.replay_gate_coef > 0 needs a policy with a replay gate: set replay_gate=true, or optim.replay_gate_coef=0.")
    policy = policy.to(device)
    logger.info("DAgger on %s%s", device, " with bf16 autocast for retraining" if config.optim.amp else "")
    run = TrainingRun(output, model_type, policy_config, policy, config.optim, loss_fn=bc_loss, ranks=ranks, unit="round")
    val_config, test_config = config.val, config.test
    done_rounds = run.resume()
    history = run.history

    bc_data = None
    if config.aggregate_bc_data:
        bc_dir = config.bc_data_dir or config.bc_data.default_dir()
        bc_data = EpisodeDataset.build(bc_dir, config.bc_data, config.num_workers, config.progress)

    if config.logger and ranks.is_main:  # rounds logged but not in last.pt are logged again
        trim_csv_logs(output / "logs", done_rounds if history else -1)
    run_logger = (
        get_logger(config.logger, logger_name=str(output / "logs"), experiment_name="dagger")
        if config.logger and ranks.is_main
        else None
    )

    # the (key, per-episode test records) of rounds tested in this process
    tested: dict[int, tuple[dict, list[dict]]] = {}

    def keep_test_records(round_index: int) -> None:
        """The new best round's test records, if it was tested, as ``test_episodes.json`` (of ``best.pt``)."""
        if round_index in tested:
            key, records = tested[round_index]
            write_records(output / TEST_EPISODES_FILE, key, records, round=round_index, checkpoint=str(best_path))

    def start_test() -> tuple[dict, list[dict]]:
        """Round 0's test: the start checkpoint's test records beside it (its BC run's ``test_episodes.json``)
        where they are of the same weights on the same episodes, else played now."""
        reused = read_records(start_path.parent / TEST_EPISODES_FILE, records_key(test_config, policy))
        if reused is None:
            return evaluate_policy(policy, test_config, progress=config.progress)
        logger.info("round 0: the test of %s on these episodes is in %s: reused", start_path, start_path.parent / TEST_EPISODES_FILE)
        return summarize_episodes(reused), reused

    def score(round_index: int, extra: dict) -> tuple[dict, dict]:
        """The round's record and its validation summary."""
        val, _ = evaluate_policy(policy, val_config)
        record = {"round": round_index, **extra, "val_success": val["success"], "val_spl": val["spl"]}
        if config.test_every_round or round_index in (0, config.rounds):
            if round_index == 0:
                summary, records = start_test()
            else:
                summary, records = evaluate_policy(policy, test_config, progress=config.progress)
            record.update(_test_fields(summary))
            tested[round_index] = records_key(test_config, policy), records
        logger.info("round %d: %s", round_index, record)
        if run_logger is not None:
            for key, value in record.items():
                if isinstance(value, float):
                    run_logger.log_scalar(f"round/{key}", value, step=round_index)
        return record, val

    def end_round(round_index: int, record: dict, val: dict) -> None:
        """The round's record, ``best.pt`` and its test records if it is the best so far, ``last.pt``, its learner."""
        if run.end_period(round_index, record, val):
            keep_test_records(round_index)
        save_checkpoint(learner_path(output, round_index), model_type, policy_config, {"model": policy.state_dict()})
        if config.window_rounds is not None:  # a resume after this round collects at most its window again
            for old in range(round_index - config.window_rounds):
                learner_path(output, old).unlink(missing_ok=True)

    def round_config_of(round_index: int) -> RoundConfig:
        round_seed = episode_seed_of_round(config, round_index)
        return RoundConfig(
            round_index=round_index, beta=config.beta(round_index), num_episodes=config.episodes_per_round,
            episodes=env.episodes.replace(seed=round_seed),
        )

    def collect_missing_window(done: int) -> None:
        """Collect again the window's rounds whose episodes are missing, each with its own learner."""
        first = 1 if config.window_rounds is None else max(1, done - config.window_rounds + 1)
        for round_index in range(first, done + 1):
            round_dir, learner = round_directory(output, round_index), learner_path(output, round_index - 1)
            if (round_dir / "meta.json").exists() or not learner.exists():
                continue  # stored; or not recoverable (training_sources says so)
            logger.info("collecting round %d again with %s (its stored episodes are missing)", round_index, learner)
            collector_policy = build_policy(model_type, policy_config).to(device)
            collector_policy.load_state_dict(load_checkpoint(learner, expected_model_type=model_type)["model"])
            shutil.rmtree(round_dir, ignore_errors=True)  # an incomplete store
            shutil.rmtree(demos_root(round_dir), ignore_errors=True)
            round_config = round_config_of(round_index)
            RoundStore.write(round_dir, round_config, _collect_round(collector_policy, config, round_config, round_dir))

    if done_rounds > 0 and ranks.is_main:
        if not learner_path(output, done_rounds).exists():  # last.pt's learner (a run begun before learners/)
            save_checkpoint(learner_path(output, done_rounds), model_type, policy_config, {"model": policy.state_dict()})
        if done_rounds < config.rounds:  # a run resumed with no round left to train (rounds=N lowered) collects nothing
            collect_missing_window(done_rounds)
    if done_rounds == 0 and not history and ranks.is_main:
        bc_count = len(bc_data) if bc_data is not None else 0
        end_round(0, *score(0, {"beta": None, "training_episodes": bc_count}))
    barrier(ranks)

    for round_index in range(done_rounds + 1, config.rounds + 1):
        beta = config.beta(round_index)
        round_dir = round_directory(output, round_index)
        round_config = round_config_of(round_index)
        if ranks.is_main and not (round_dir / "meta.json").exists():  # rank 0 collects, the others read its store
            RoundStore.write(round_dir, round_config, _collect_round(policy, config, round_config, round_dir))
        barrier(ranks)
        # stored before an interruption too (collection is deterministic): reused
        round_store = RoundStore.read(round_dir, round_config.collection())
        episodes = round_store.episodes
        collected = {"beta": beta, **behaviour_statistics(episodes)}
        sources = training_sources(bc_data, output, round_index, config.window_rounds)
        collected["training_episodes"] = sum(len(source) for source in sources)
        collected.update(_train_round(run, sources, config, round_index, ranks))
        # the pointer-collapse guard (every rank: the same weights, the same pace), on the round's own episodes
        guard = PointerGuard.of(policy, round_store)
        pace = guard.pace(policy, ranks) if guard is not None else None
        if pace is not None:
            collected["pointer_pace"] = pace
        collapsed = PointerGuard.collapsed(pace)
        if ranks.is_main:
            record, val = score(round_index, collected)
            if collapsed:  # never the best; the next round starts from the best round's weights
                logger.warning("round %d: pointer collapse (pace %.3f < %g): set aside, back to round %d's weights",
                               round_index, pace, COLLAPSE_PACE, run.best["round"])
                record["pointer_collapsed"], val = True, None
                run.restore_best()
            end_round(round_index, record, val)
        else:
            if collapsed:
                run.restore_best()
            run.end_period(round_index, {"round": round_index, **collected}, None)
        barrier(ranks)  # the other ranks wait for rank 0's validation and checkpoints

    if not ranks.is_main:
        return {"rank": ranks.rank, "history": history}

    best = next(record for record in history if record["round"] == run.best["round"])
    if "test_success" not in best or _test_episodes_round(output) != best["round"]:  # the shipped checkpoint's own test
        shipped = load_checkpoint(best_path, expected_model_type=model_type)
        if shipped["round"] != best["round"]:
            raise RuntimeError(
                f"{best_path} holds round {shipped['round']}, but the history's best round is {best['round']} "
                "(a run interrupted between its checkpoints); rerun that round or delete the run."
            )
        policy.load_state_dict(shipped["model"])
        summary, records = evaluate_policy(policy, test_config, progress=config.progress)
        write_records(output / TEST_EPISODES_FILE, records_key(test_config, policy), records, round=best["round"],
                      checkpoint=str(best_path))
        best = {**best, **_test_fields(summary)}
        logger.info("best round %d (best.pt): %s", best["round"], best)
    results = {
        "model": model_type,
        "start_checkpoint": config.checkpoint,
        "start": history[0],
        "final": history[-1],
        "best": best,
        "best_round_by_val": best["round"],
        "history": history,
        **run_results(config, time.time() - start_time),
    }
    atomic_write_json(output / "results.json", results, default=str)
    plot_if_available(plot_rounds, history, output / "dagger.png", title=f"DAgger from {Path(config.checkpoint).name}")
    return results


def _test_episodes_round(output: Path) -> int | None:
    """The round whose test records ``test_episodes.json`` holds (``None``: there is none)."""
    path = output / TEST_EPISODES_FILE
    return json.loads(path.read_text()).get("round") if path.exists() else None


def _test_fields(summary: dict) -> dict:
    """The test fields of a round's record, from an evaluation summary."""
    return {f"test_{key}": summary[key] for key in ("success", "spl", "success_ci", "spl_ci")}


def retraining_seed(config: DAggerConfig, round_index: int, step: int) -> int:
    """The seed of the random draws in gradient step ``step`` of round ``round_index`` (a
    random-sparsity model's per-episode sparsities): from ``(config.seed, round_index +
    config.round_seed_offset, step)`` alone, so that a resumed run, or one whose data were built
    in the same process, draws what an uninterrupted run draws.

    Examples:
        >>> config = DAggerConfig()
        >>> retraining_seed(config, 1, 0) == retraining_seed(config, 1, 0) != retraining_seed(config, 1, 1)
        True
    """
    entropy = [config.seed, round_index + config.round_seed_offset, step, RETRAINING_STREAM]
    return int(np.random.SeedSequence(entropy).generate_state(1)[0])


def _collect_round(policy: TensorDictModuleBase, config: DAggerConfig, round_config: RoundConfig, round_dir: Path) -> TensorDict:
    """The round's episodes: numbered episodes ``0 .. E - 1`` of its seed, their demonstrations
    rendered first into ``round-XX-demos``, played by the beta-mixture through the run's
    collectors (:func:`~spf_rl.train.collection.make_collector` with the store), each kept whole."""
    demos = DemoStore.build(demos_root(round_dir), round_demo_config(round_config), progress=False)
    policy.eval()
    behaviour = ExpertMixturePolicy(FramesFromStore(policy, demos, round_config.episodes.frames_id_key), round_config.beta)
    with torch_threads_kept():  # a multi-process collector changes them (retraining must not see it)
        return _play_round(policy, behaviour, config, round_config, demos)


def _play_round(
    policy: TensorDictModuleBase, behaviour: TensorDictModuleBase, config: DAggerConfig, round_config: RoundConfig, demos: DemoStore
) -> TensorDict:
    """``behaviour`` plays the round's numbered episodes through the run's collectors; ``policy`` back in training mode after."""
    env, layout = config.env, config.collector
    collector = make_collector(
        behaviour,
        env,
        layout,
        frames_per_batch=layout.total_agents * STEPS_PER_BATCH,
        seed=round_config.seed,
        device=module_device(policy),
        storing_device="cpu",  # the round's episodes go to disk
        demo_store=demos.root,
    )
    try:
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            return gather_episode_steps(
                collector, 0, round_config.num_episodes, step_keys(round_config.episodes.route_style), env.episodes.step_limit,
                episode_keys=episode_keys(round_config.episodes), progress=config.progress,
            )
    finally:
        collector.shutdown()
        policy.train()


def retraining_order(sizes: torch.Tensor, steps: int, batch_size: int, generator: torch.Generator,
                     rounds_share: float | None = None) -> torch.Tensor:
    """The rows of each retraining batch, ``[steps, batch_size]``, over the training sources laid end to end
    (``sizes``: their episode counts, the BC data's first).

    ``rounds_share`` ``None``: every row equally likely, drawn without replacement, pass after pass over
    all of them. Otherwise ``round(rounds_share * batch_size)`` rows of every batch (at least one, and at
    least one of the BC data) come from the sources after the first, the rest from the first, each part
    without replacement pass after pass over its own rows, in an order shuffled within the batch.

    Examples:
        >>> order = retraining_order(torch.tensor([90, 10]), steps=20, batch_size=10, generator=torch.Generator().manual_seed(0))
        >>> order.shape, round(float((order >= 90).float().mean()), 2)  # the rounds: a tenth of the rows
        (torch.Size([20, 10]), 0.1)
        >>> shared = retraining_order(torch.tensor([90, 10]), 20, 10, torch.Generator().manual_seed(0), rounds_share=0.5)
        >>> (shared >= 90).sum(1).tolist() == [5] * 20  # half of every batch
        True
    """
    def passes_over(count: int, per_batch: int) -> torch.Tensor:
        """``steps * per_batch`` of ``count`` rows: passes without replacement, one after another."""
        needed = -(-steps * per_batch // count)
        return torch.cat([torch.randperm(count, generator=generator) for _ in range(needed)])[: steps * per_batch]

    total = int(sizes.sum())
    if rounds_share is None:
        return passes_over(total, batch_size).reshape(steps, batch_size)
    first = int(sizes[0])
    from_rounds = min(max(round(rounds_share * batch_size), 1), batch_size - 1)
    bc = passes_over(first, batch_size - from_rounds).reshape(steps, -1)
    rounds = (passes_over(total - first, from_rounds) + first).reshape(steps, -1)
    rows = torch.cat([bc, rounds], 1)
    shuffle = torch.stack([torch.randperm(batch_size, generator=generator) for _ in range(steps)])
    return torch.gather(rows, 1, shuffle)


def _train_round(
    run: TrainingRun,
    sources: list[EpisodeDataset | RoundStore],
    config: DAggerConfig,
    round_index: int,
    ranks: Ranks = Ranks(),
) -> dict[str, float | int]:
    """Retrain on ``sources`` (:meth:`~spf_rl.train.run.TrainingRun.train_epoch`): ``steps_per_round`` steps
    (or ``epochs_per_round`` passes) of batches drawn without replacement, pass after pass, in an order fixed
    by the seed and round; each step's random draws from :func:`retraining_seed`.

    In a data-parallel run each rank trains on its shard of every batch (:mod:`spf_rl.train.distributed`).

    Returns:
        ``train_loss`` (the mean over whole batches), ``gradient_steps`` and, with
        ``optim.pointer_coef`` > 0, ``train_pointer_loss`` (the pointer loss's mean, before its weight), and
        with ``optim.replay_gate_coef`` > 0 ``train_replay_gate_loss`` (:meth:`~spf_rl.train.run.TrainingRun.loss_part_means`).
    """
    sizes = torch.tensor([len(source) for source in sources])
    offsets = torch.cumsum(sizes, 0)
    total, batch_size = int(offsets[-1]), config.optim.batch_size
    steps = config.steps_per_round or config.epochs_per_round * -(-total // batch_size)
    generator = torch.Generator().manual_seed(config.seed * 100_003 + round_index * 101)
    rounds_share = config.rounds_share if len(sources) > 1 else None  # the BC data and at least one round
    order = retraining_order(sizes, steps, batch_size, generator, rounds_share)
    if rounds_share is not None:
        logger.info("round %d retraining: %d of every batch of %d from the rounds (rounds_share %g)", round_index,
                    int((order[0] >= int(sizes[0])).sum()), batch_size, rounds_share)

    def batches():
        for step in range(steps):
            rows = shard_indices(order[step], ranks)
            source_of_row = torch.searchsorted(offsets, rows, right=True)
            yield torch.cat([
                source_rows(sources[k], rows[source_of_row == k] - (offsets[k] - sizes[k]))
                for k in source_of_row.unique().tolist()
            ], 0)

    losses, _, _ = run.train_epoch(
        batches(), steps, f"round {round_index} retraining", config.progress,
        seed_of_step=lambda step: retraining_seed(config, round_index, step),
    )
    return {"train_loss": float(sum(losses) / len(losses)), "gradient_steps": steps, **run.loss_part_means()}


def plot_rounds(history: list[dict], path: Path, title: str = "DAgger") -> None:
    """Success and SPL per round (val, and test where measured)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    rounds = [r["round"] for r in history]
    for split, style in (("val", "-"), ("test", "--")):
        for metric, marker in (("success", "o"), ("spl", "s")):
            points = [(r["round"], r[f"{split}_{metric}"]) for r in history if f"{split}_{metric}" in r]
            if points:
                ax.plot(*zip(*points), style, marker=marker, label=f"{split} {metric}")
    ax.set_xticks(rounds)
    ax.set_xlabel("DAgger round (0 = BC start)")
    ax.set_ylim(0, 1)
    ax.set_title(title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    write_figure(fig, path, dpi=120)


__all__ = ["DAggerConfig", "ExpertMixturePolicy", "behaviour_statistics", "episode_seed_of_round", "plot_rounds", "retraining_seed", "train_dagger"]
