"""The configuration of a PPO fine-tuning run (:func:`~spf_rl.train.ppo.train_ppo`)."""
from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

from envs.demo_store import DemoStore, DemoStoreConfig
from envs.episode_spec import EpisodeSpec, check_sizes_match
from envs.homing import FOLLOW
from envs.version import ENV_VERSION
from spf_rl.device import DEFAULT_DEVICE, check_device
from spf_rl.evaluation import TEST_SEED, VAL_SEED, EvalConfig, episode_store_root
from spf_rl.hub import DEFAULT_START_CHECKPOINT
from spf_rl.modules import SPFConfig
from spf_rl.train.collection import CollectionEnvConfig, CollectorConfig

logger = logging.getLogger(__name__)

#: Seed of the demonstrations PPO's training episodes draw from (``PPOConfig.store_demos``).
TRAIN_STORE_SEED = 0

__all__ = ["TRAIN_STORE_SEED", "PPOConfig", "checked_env_config", "training_demo_store"]


#: Settings a resumed PPO run may change (beyond how it executes): more frames, threads, where the demo store lives,
#: the collector (its layout is checked against ``last.pt`` separately).
PPO_RESUME_FREE = ("total_frames", "num_threads", "store_root", "collector")


@dataclass
class PPOConfig:
    """A PPO fine-tuning run.

    Args:
        checkpoint: the starting (BC) checkpoint: a path, or a shipped name
            (:func:`spf_rl.list_checkpoints`).
        output_dir: checkpoints, logs, results and figures.
        seed: seed of the collector's episodes, action sampling and minibatches.
        device: where the policy, value head and their optimisers run, and where the
            collector's policy acts: ``"auto"`` (CUDA if available, else the CPU),
            ``"cpu"``, ``"cuda"`` or ``"cuda:N"``. Envs and rendering stay on the CPU.
        amp: bf16 autocast for collection, values and the loss (mixed precision; see
            :mod:`spf_rl.train.ppo_loss`). Validation and test stay float32.
        frames_per_batch: frames per collected batch (over all agents); a multiple
            of ``collector.total_agents``. Each of the ``N = total_agents`` rows of a
            batch holds ``T = frames_per_batch / N`` steps; ``T >= env.max_steps``
            makes every row's first episode complete.
        total_frames: frames of the run; ``total_frames // frames_per_batch`` PPO
            iterations.
        ppo_epochs: passes over each batch.
        minibatch_rows: whole ``[T]`` rows of the ``[N, T]`` batch per gradient step.
        lr: Adam learning rate of the policy.
        critic_lr: Adam learning rate of the value head.
        max_grad_norm: gradient-norm clip (policy and value head separately).
        clip_epsilon: PPO ratio clip, ``> 0``.
        gamma: discount, in ``(0, 1]``.
        lmbda: GAE lambda, in ``[0, 1]``.
        entropy_coef: entropy bonus coefficient.
        critic_coef: value-loss coefficient.
        kl_coef: coefficient of ``KL(pi || pi_start)`` to the frozen starting policy.
        bc_coef: coefficient of the cross-entropy to the env's ``expert_action``.
        normalize_advantage: standardise advantages per minibatch.
        critic_warmup_iters: first iterations that fit only the value head.
        value_hidden: hidden units of the value head's MLP.
        critic_trunk_grad: let the value loss's gradient into the policy's trunk
            (``False``: the head reads the features detached).
        val_every: validate every this many iterations (and after the last).
        store_demos: the training episodes draw their demonstrations at random from a
            store of this many ``env`` demonstrations (:class:`~envs.demo_store.DemoStore`,
            seed :data:`TRAIN_STORE_SEED`), rendered once; the envs emit ``demo_id`` and
            the policy looks the frames up. ``None``: every reset samples and renders a
            new demonstration.
        store_root: where that store is kept (shared by runs of the same episodes);
            ``None``: inside ``output_dir``.
        num_threads: torch intra-op threads during the run (restored after; ``0``:
            leave torch's setting). Collection, rendering and the updates share one
            process; on the 2-core machine one thread was about 5x faster than
            torch's default of two while other jobs were running (two threads spin
            waiting for each other).
        logger: torchrl logger backend (``"csv"``, ``"tensorboard"``, ...); ``""`` or
            ``None`` (``logger=`` on the command line) for none.
        progress: progress bars.
        collector: how episodes are collected (:class:`~spf_rl.train.collection.CollectorConfig`).
        env: the training episodes (:class:`~spf_rl.train.collection.CollectionEnvConfig`);
            ``demo_length`` and ``image_size`` must match the checkpoint.
        val: validation rollouts (their ``demo_length``, ``max_steps`` and
            ``image_size`` are taken from ``env``).
        test: final evaluation of the start and of the best checkpoint (sizes
            from ``env`` too).

    Examples:
        >>> cfg = PPOConfig(frames_per_batch=1250, total_frames=12500)
        >>> cfg.num_iterations, cfg.rows_per_batch, cfg.steps_per_row
        (10, 25, 50)
        >>> PPOConfig(clip_epsilon=0.0)
        Traceback (most recent call last):
        ...
        ValueError: clip_epsilon must be > 0, got 0.0.
    """

    checkpoint: str = DEFAULT_START_CHECKPOINT
    output_dir: str = "runs/ppo"
    seed: int = 0
    device: str = DEFAULT_DEVICE
    amp: bool = False
    frames_per_batch: int = 1250
    total_frames: int = 50000
    ppo_epochs: int = 3
    minibatch_rows: int = 5
    lr: float = 1e-4
    critic_lr: float = 1e-3
    max_grad_norm: float = 0.5
    clip_epsilon: float = 0.2
    gamma: float = 0.99
    lmbda: float = 0.95
    entropy_coef: float = 0.001
    critic_coef: float = 0.5
    kl_coef: float = 0.0
    bc_coef: float = 0.0
    normalize_advantage: bool = True
    critic_warmup_iters: int = 2
    value_hidden: int = 64
    critic_trunk_grad: bool = False
    val_every: int = 4
    store_demos: int | None = 2000
    store_root: str | None = field(default_factory=episode_store_root)
    num_threads: int = 1
    logger: str | None = "csv"
    progress: bool = True
    collector: CollectorConfig = field(default_factory=lambda: CollectorConfig(num_agents=25))
    env: CollectionEnvConfig = field(default_factory=lambda: CollectionEnvConfig(with_expert=False))
    val: EvalConfig = field(
        default_factory=lambda: EvalConfig(EpisodeSpec(split="val", max_steps=50, seed=VAL_SEED), num_episodes=100, store_root=episode_store_root())
    )
    test: EvalConfig = field(
        default_factory=lambda: EvalConfig(EpisodeSpec(split="test", max_steps=50, seed=TEST_SEED), num_episodes=500, store_root=episode_store_root())
    )

    def __post_init__(self) -> None:
        check_device(self.device)
        check_sizes_match(self.env.episodes, "env", val=self.val.episodes, test=self.test.episodes)

        def positive_int(name: str) -> None:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive int, got {value!r}.")

        for name in ("frames_per_batch", "total_frames", "ppo_epochs", "minibatch_rows", "value_hidden", "val_every"):
            positive_int(name)
        if self.store_demos is not None:
            positive_int("store_demos")
        if isinstance(self.num_threads, bool) or not isinstance(self.num_threads, int) or self.num_threads < 0:
            raise ValueError(f"num_threads must be an int >= 0 (0: torch's default), got {self.num_threads!r}.")
        if isinstance(self.critic_warmup_iters, bool) or not isinstance(self.critic_warmup_iters, int) or self.critic_warmup_iters < 0:
            raise ValueError(f"critic_warmup_iters must be an int >= 0, got {self.critic_warmup_iters!r}.")
        for name in ("lr", "critic_lr", "max_grad_norm", "clip_epsilon"):
            value = getattr(self, name)
            if not value > 0 or not math.isfinite(value):
                raise ValueError(f"{name} must be > 0, got {value!r}.")
        for name in ("entropy_coef", "critic_coef", "kl_coef", "bc_coef"):
            value = getattr(self, name)
            if not value >= 0 or not math.isfinite(value):
                raise ValueError(f"{name} must be >= 0, got {value!r}.")
        if not 0 < self.gamma <= 1:
            raise ValueError(f"gamma must be in (0, 1], got {self.gamma!r}.")
        if not 0 <= self.lmbda <= 1:
            raise ValueError(f"lmbda must be in [0, 1], got {self.lmbda!r}.")
        rows = self.rows_per_batch
        if self.frames_per_batch % rows:
            raise ValueError(
                f"frames_per_batch must be a multiple of collector.num_collectors * collector.num_agents = {rows} "
                f"(one [T] row per agent), got {self.frames_per_batch}."
            )
        if self.minibatch_rows > rows:
            raise ValueError(
                f"minibatch_rows must be <= the rows of a batch (collector.num_collectors * num_agents = {rows}), "
                f"got {self.minibatch_rows}."
            )
        if self.total_frames < self.frames_per_batch:
            raise ValueError(
                f"total_frames must be >= frames_per_batch = {self.frames_per_batch} (one iteration), got {self.total_frames}."
            )

    @property
    def rows_per_batch(self) -> int:
        """Rows ``N`` of a collected batch: one per agent."""
        return self.collector.total_agents

    @property
    def steps_per_row(self) -> int:
        """Steps ``T`` of each row of a collected batch."""
        return self.frames_per_batch // self.rows_per_batch

    @property
    def num_iterations(self) -> int:
        """PPO iterations (collected batches) of the run."""
        return self.total_frames // self.frames_per_batch


def checked_env_config(config: PPOConfig, policy_config: SPFConfig) -> CollectionEnvConfig:
    """The run's training env config, checked against the checkpoint's sizes.

    ``env.with_expert`` is switched on when ``bc_coef > 0`` (the loss reads the expert's labels).

    Raises:
        ValueError: ``env.demo_length`` or ``env.image_size`` differ from the checkpoint's.

    Examples:
        >>> checked_env_config(PPOConfig(bc_coef=0.1), SPFConfig(demo_length=30)).with_expert
        True
    """
    env, spec = config.env, config.env.episodes
    if spec.demo_length != policy_config.demo_length:
        raise ValueError(
            f"env.demo_length must equal the checkpoint's demo_length {policy_config.demo_length}, got {spec.demo_length}."
        )
    if (spec.image_size, spec.image_size) != tuple(policy_config.image_size):
        raise ValueError(
            f"env.image_size must equal the checkpoint's image size {tuple(policy_config.image_size)}, got {spec.image_size}."
        )
    if config.bc_coef > 0 and not env.with_expert:
        logger.info("bc_coef > 0: the env emits expert_action (env.with_expert=True)")
        env = dataclasses.replace(env, with_expert=True)
    return env


def training_demo_store(config: PPOConfig, env: CollectionEnvConfig) -> DemoStore | None:
    """The store PPO's training episodes draw their demonstrations from (built on first
    use, under ``config.store_root``), or ``None`` without ``config.store_demos``.

    Its directory name holds the episodes' split, sizes, seed, count and env version, so
    runs of the same episodes share it and one of an older env is never reopened.
    """
    if config.store_demos is None:
        return None
    spec = env.episodes.replace(seed=TRAIN_STORE_SEED, task=FOLLOW, route_style=None, route_lengths=None)
    store_config = DemoStoreConfig(episodes=spec, num_demos=config.store_demos)
    houses = "" if spec.num_houses is None else f"-{spec.num_houses}houses"
    name = (
        f"{spec.split}{houses}-{FOLLOW}-n{spec.demo_length}-{spec.image_size}px-seed{TRAIN_STORE_SEED}"
        f"-{config.store_demos}demos-env{ENV_VERSION}"
    )
    root = Path(config.store_root) if config.store_root is not None else Path(config.output_dir) / "demos"
    return DemoStore.build(root / name, store_config, progress=config.progress)
