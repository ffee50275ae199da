"""Recurrent PPO fine-tuning of a behaviour-cloned path-following policy.

Starting from a BC checkpoint, the policy (:class:`~spf_rl.modules.SPFPolicy`,
wrapped by :func:`~spf_rl.modules.make_actor` into a
:class:`~torchrl.modules.ProbabilisticActor` over the 3 actions) is trained on
the environment's dense reward (geodesic progress, success bonus, step cost;
see :mod:`envs.nav_env`) with TorchRL's :class:`~torchrl.objectives.ClipPPOLoss`
and :class:`~torchrl.objectives.value.GAE`:

* **Critic.** A small MLP value head (:class:`ValueHead`) on the policy's GRU
  output ``"features"`` (a shared trunk). By default it reads the features
  detached, so only the policy loss shapes the pretrained trunk
  (``critic_trunk_grad=True`` lets the critic's gradient in). The head starts
  untrained: for the first ``critic_warmup_iters`` iterations only the head is
  fitted and the policy is left as it is.
* **Collection.** :func:`~spf_rl.train.collection.make_collector` (local
  in-process / multi-process, or Ray) with ``reset_at_each_iter=True``: every
  batch ``[N, T]`` (``N = collector.total_agents`` rows, ``T = frames_per_batch / N``)
  starts ``N`` fresh episodes at ``t = 0``, so each row is one agent's stream of
  whole episodes (plus one cut by the batch end, bootstrapped by the critic) and
  the recurrent state at ``t = 0`` is the zero reset state. The weights are pushed
  to the collector (:meth:`update_policy_weights_`) before every batch.
* **Recurrence.** PPO minibatches are whole rows ``[B, T]``; the loss runs the
  policy in sequence mode (:func:`torchrl.modules.set_recurrent_mode`), which
  restarts from the stored state at ``t = 0`` and wherever ``is_init`` is true,
  so on the first epoch the recomputed log-probabilities equal the collected
  ``action_log_prob`` (:func:`recompute_log_prob`; the training loop records the
  largest ``|log-ratio|`` of the first minibatch as ``log_ratio_first``). Values for GAE
  are exact step-mode values: ``V(s_t)`` from the collected ``features`` and
  ``V(s_{t+1})`` from the next step's features (one step-mode call from the stored
  next state where the episode ended or the batch is cut).
* **Regularisation toward the start** (optional): ``kl_coef * KL(pi || pi_BC)``
  against the frozen starting policy (run in sequence mode on the batch), and
  ``bc_coef * CE(pi, expert_action)`` on the env's expert labels
  (``with_expert`` is switched on automatically).
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
import dataclasses
import logging
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import ProbabilisticActor, set_recurrent_mode
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE
from torchrl.record.loggers import get_logger
from tqdm.auto import tqdm

from spf_rl.checkpoint import load_checkpoint, save_checkpoint
from spf_rl.train.bc import _atomic_json
from spf_rl.modules.policy import SPFPolicy, make_actor
from spf_rl.train.collection import CollectionEnvConfig, CollectorConfig, make_collector
from spf_rl.train.evaluation import EvalConfig, evaluate_policy, with_episode_sizes
from spf_rl.train.models import build_policy
from spf_rl.viz import plot_if_available, pyplot

logger = logging.getLogger(__name__)

__all__ = [
    "PPOConfig",
    "SPFPPOLoss",
    "ValueHead",
    "compute_values",
    "episode_statistics",
    "make_ppo_modules",
    "plot_ppo",
    "recompute_log_prob",
    "train_ppo",
]

#: Key of the value head's output.
VALUE_KEY = "state_value"
#: Key of the frozen starting policy's logits (written per batch when ``kl_coef > 0``).
REF_LOGITS_KEY = "ref_logits"
#: Key of the expert's action emitted by the env with ``with_expert=True``.
EXPERT_KEY = "expert_action"
#: Keys the collector writes that the loss must recompute (never read stale).
_RECOMPUTED_KEYS = ("logits", "features", "eta_used", "memory_mask")
#: ``|log pi_theta - log pi_collected|`` of the first minibatch above which the
#: collector is reported as acting with other weights than the learner's.
RATIO_SYNC_TOLERANCE = 1e-3
#: Salt of the per-iteration minibatch permutation seed.
_PERMUTATION_SALT = 1_000_003
#: Salt of the collector seed of a run (re)started at an iteration.
_COLLECTOR_SALT = 7919


@dataclass
class PPOConfig:
    """A PPO fine-tuning run.

    Args:
        checkpoint: the starting (BC) checkpoint.
        output_dir: checkpoints, logs, results and figures.
        seed: seed of the collector's episodes, action sampling and minibatches.
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

    checkpoint: str = "checkpoints/spf-s0.8.pt"
    output_dir: str = "runs/ppo"
    seed: int = 0
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
    num_threads: int = 1
    logger: str | None = "csv"
    progress: bool = True
    collector: CollectorConfig = field(default_factory=lambda: CollectorConfig(num_agents=25))
    env: CollectionEnvConfig = field(
        default_factory=lambda: CollectionEnvConfig(split="train", noise="paper", with_expert=False)
    )
    val: EvalConfig = field(default_factory=lambda: EvalConfig(split="val", num_episodes=100, seed=1, noise="paper"))
    test: EvalConfig = field(default_factory=lambda: EvalConfig(split="test", num_episodes=500, seed=2, noise="paper"))

    def __post_init__(self) -> None:
        def positive_int(name: str) -> None:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive int, got {value!r}.")

        for name in ("frames_per_batch", "total_frames", "ppo_epochs", "minibatch_rows", "value_hidden", "val_every"):
            positive_int(name)
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


# ---------------------------------------------------------------------- modules
class ValueHead(nn.Module):
    """MLP state-value head on the policy's GRU output.

    Args:
        in_features: size of the features (the policy's ``hidden_size``).
        hidden: hidden units.
        detach_input: read the features detached (the value loss then does not
            train the shared trunk).

    Examples:
        >>> head = ValueHead(16, hidden=8)
        >>> head(torch.zeros(2, 5, 16)).shape
        torch.Size([2, 5, 1])
    """

    def __init__(self, in_features: int, hidden: int = 64, detach_input: bool = True) -> None:
        super().__init__()
        self.detach_input = detach_input
        self.net = nn.Sequential(nn.Linear(in_features, hidden), nn.Tanh(), nn.Linear(hidden, 1))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """``[*, in_features] -> [*, 1]``."""
        if self.detach_input:
            features = features.detach()
        return self.net(features)


def make_ppo_modules(
    policy: SPFPolicy, value_hidden: int = 64, critic_trunk_grad: bool = False
) -> tuple[ProbabilisticActor, TensorDictModule]:
    """The actor (sampling, writes ``action`` and ``action_log_prob``) and the critic
    (a :class:`ValueHead` reading ``"features"``, writing ``"state_value"``) of a policy.

    The critic holds only the head: it reads the ``"features"`` that the actor wrote
    into the same tensordict (inside :class:`SPFPPOLoss`, the actor runs first).
    The actor exposes the policy's ``make_tensordict_primer``, so that
    :func:`~spf_rl.train.collection.make_collector` registers its recurrent state.

    Args:
        policy: the SPF policy (the shared trunk).
        value_hidden: hidden units of the value head.
        critic_trunk_grad: let the value loss train the trunk.

    Examples:
        >>> from spf_rl.modules import SPFConfig, SPFPolicy
        >>> actor, critic = make_ppo_modules(SPFPolicy(SPFConfig(feature_dim=8, hidden_size=8)))
        >>> actor.out_keys[-2:], critic.out_keys
        (['action', 'action_log_prob'], ['state_value'])
    """
    actor = make_actor(policy, policy.config.num_actions)
    # make_collector adds the recurrent-state primer of a policy that has
    # make_tensordict_primer; a ProbabilisticActor does not forward its module's, and
    # without the primer the collector never carries the state (every step would
    # start from zeros), so expose the SPF policy's
    actor.make_tensordict_primer = policy.make_tensordict_primer
    head = ValueHead(policy.config.hidden_size, value_hidden, detach_input=not critic_trunk_grad)
    critic = TensorDictModule(head, in_keys=[policy.features_key], out_keys=[VALUE_KEY])
    return actor, critic


class SPFPPOLoss(ClipPPOLoss):
    """:class:`~torchrl.objectives.ClipPPOLoss` plus optional pulls toward the start.

    Adds to the clipped objective, entropy and value losses:

    * ``loss_kl = kl_coef * mean_t KL(pi_theta(.|s_t) || pi_ref(.|s_t))``, with the
      frozen reference policy's logits read from ``"ref_logits"`` (computed once per
      batch), and ``kl_ref`` (the unweighted KL) for logging;
    * ``loss_bc = bc_coef * mean_t CE(pi_theta(.|s_t), expert_action_t)`` and ``bc_ce``.

    Both use the distribution of the same sequence-mode forward as the PPO ratio.
    The keys the actor writes (``logits``, ``features``, ...) are dropped from the
    input first, so the critic reads this forward's features, never the
    collected ones.

    Args:
        actor_network: the actor (:func:`make_ppo_modules`).
        critic_network: the critic (:func:`make_ppo_modules`).

    Keyword Args:
        kl_coef: KL coefficient (0: off).
        bc_coef: expert cross-entropy coefficient (0: off).
        **kwargs: :class:`~torchrl.objectives.ClipPPOLoss` arguments
            (``clip_epsilon``, ``entropy_coeff``, ``critic_coeff``, ...).

    Examples:
        >>> from spf_rl.modules import SPFConfig, SPFPolicy
        >>> actor, critic = make_ppo_modules(SPFPolicy(SPFConfig(feature_dim=8, hidden_size=8)))
        >>> loss = SPFPPOLoss(actor, critic, kl_coef=0.1, clip_epsilon=0.2)
        >>> loss.kl_coef
        0.1
    """

    def __init__(self, actor_network, critic_network, *, kl_coef: float = 0.0, bc_coef: float = 0.0, **kwargs) -> None:
        kwargs.setdefault("functional", False)
        super().__init__(actor_network, critic_network, **kwargs)
        self.kl_coef = float(kl_coef)
        self.bc_coef = float(bc_coef)
        self._current = None

    def _log_weight(self, tensordict: TensorDictBase, adv_shape: torch.Size):
        log_weight, dist, kl_approx, log_is_weight = super()._log_weight(tensordict, adv_shape)
        self._current = (dist, log_weight.detach())
        return log_weight, dist, kl_approx, log_is_weight

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The PPO losses (``loss_objective``, ``loss_entropy``, ``loss_critic``) and,
        when their coefficients are set, ``loss_kl`` and ``loss_bc``; also
        ``max_abs_log_ratio``, the largest ``|log pi_theta - log pi_collected|`` of the
        minibatch (0 on the first minibatch when collection used these weights)."""
        tensordict = tensordict.exclude(*_RECOMPUTED_KEYS)
        self._current = None
        out = super().forward(tensordict)
        (dist, log_weight), self._current = self._current, None
        out.set("max_abs_log_ratio", log_weight.abs().max())
        if self.kl_coef or self.bc_coef:
            log_p = torch.log_softmax(dist.logits, -1)
            if self.kl_coef:
                ref = torch.log_softmax(tensordict.get(REF_LOGITS_KEY), -1)
                kl = (log_p.exp() * (log_p - ref)).sum(-1).mean()
                out.set("loss_kl", self.kl_coef * kl)
                out.set("kl_ref", kl.detach())
            if self.bc_coef:
                labels = tensordict.get(EXPERT_KEY)
                ce = F.nll_loss(log_p.reshape(-1, log_p.shape[-1]), labels.reshape(-1).long())
                out.set("loss_bc", self.bc_coef * ce)
                out.set("bc_ce", ce.detach())
        return out


# ---------------------------------------------------------------------- batch helpers
def recompute_log_prob(actor: ProbabilisticActor, batch: TensorDictBase) -> torch.Tensor:
    """Log-probability of the collected actions under ``actor``, in sequence mode.

    Runs the policy over the ``[N, T]`` batch as the PPO loss does (each row starts
    from its stored state at ``t = 0`` and at ``is_init``); with the weights that
    collected the batch it equals the collected ``action_log_prob``.

    Args:
        actor: the actor (:func:`make_ppo_modules`).
        batch: a collected ``[N, T]`` batch.

    Returns:
        ``[N, T]`` log-probabilities.
    """
    td = batch.exclude(*_RECOMPUTED_KEYS, "next").clone(False)
    with torch.no_grad(), set_recurrent_mode(True):
        dist = actor.get_dist(td)
    return dist.log_prob(batch.get("action"))


def compute_values(policy: SPFPolicy, critic: TensorDictModule, batch: TensorDictBase) -> TensorDictBase:
    """Write ``state_value`` and ``("next", "state_value")`` of a collected ``[N, T]`` batch.

    ``V(s_t)`` is the value head on the collected ``features`` (the GRU output of the
    step, computed by the current weights during collection). ``V(s_{t+1})`` is
    ``V(s_{t+1})`` of the row where the episode goes on within the batch, and
    elsewhere (episode ended, batch cut) one step-mode call from the stored next
    state on the next observation (the terminal or cut-off observation).

    Args:
        policy: the trunk.
        critic: the value head module.
        batch: the batch (modified in place).

    Returns:
        ``batch``.
    """
    features_key = policy.features_key
    with torch.no_grad():
        value = critic.module(batch.get(features_key))
        next_value = torch.roll(value, -1, dims=1)
        need = batch.get(("next", "done")).reshape(batch.shape).clone()
        need[:, -1] = True
        rows = batch.get("next").select(*policy.in_keys, strict=False)[need]
        rows = policy(rows)
        next_value[need] = critic.module(rows.get(features_key))
    batch.set(VALUE_KEY, value)
    batch.set(("next", VALUE_KEY), next_value)
    return batch


def episode_statistics(batch: TensorDictBase) -> dict:
    """Reward and outcome of the episodes a batch holds.

    ``success``, ``spl``, ``return`` and ``length`` are over the episodes that start
    at a row's ``t = 0`` and end within the batch (with ``T >= max_steps`` that is
    one whole episode per row, an unbiased sample; later episodes of a row that
    finish before the cut would favour short, successful ones).

    Returns:
        dict with ``reward_per_step``, ``episodes``, ``success``, ``spl``,
        ``return``, ``length`` (``nan`` where no episode finished).
    """
    reward = batch.get(("next", "reward")).reshape(batch.shape)
    done = batch.get(("next", "done")).reshape(batch.shape)
    has_end = done.any(-1)
    end = done.float().argmax(-1)
    rows = torch.arange(batch.shape[0])[has_end]
    end = end[has_end]
    stats = {"reward_per_step": float(reward.mean()), "episodes": int(has_end.sum())}
    if len(rows) == 0:
        return {**stats, "success": float("nan"), "spl": float("nan"), "return": float("nan"), "length": float("nan")}
    steps = torch.arange(batch.shape[1])
    within = steps[None, :] <= end[:, None]
    returns = (reward[rows] * within).sum(-1)
    success = batch.get(("next", "success")).reshape(batch.shape)[rows, end].float()
    spl = batch.get(("next", "spl")).reshape(batch.shape)[rows, end].float()
    return {
        **stats,
        "success": float(success.mean()),
        "spl": float(spl.mean()),
        "return": float(returns.mean()),
        "length": float((end + 1).float().mean()),
    }


# ---------------------------------------------------------------------- training
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
        ValueError: the env's sizes do not match the checkpoint's, or ``last.pt``
            was written with another ``frames_per_batch`` / collector layout.

    Examples:
        >>> results = train_ppo(PPOConfig(output_dir="runs/ppo-example"))  # doctest: +SKIP
        >>> results["after"]["test"]["success"]  # doctest: +SKIP
        0.52
    """
    threads = torch.get_num_threads()
    if config.num_threads:
        torch.set_num_threads(config.num_threads)
    try:
        return _PPORun(config).run(callback)
    finally:
        torch.set_num_threads(threads)


class _PPORun:
    """The state of one run: modules, optimisers, progress, and the files it writes."""

    def __init__(self, config: PPOConfig) -> None:
        self.config = config
        self.output = Path(config.output_dir)
        self.output.mkdir(parents=True, exist_ok=True)
        _atomic_json(self.output / "config.json", asdict(config))
        self.last_path, self.best_path = self.output / "last.pt", self.output / "best.pt"

        payload = load_checkpoint(config.checkpoint)
        self.model_type, self.policy_config = payload["model_type"], payload["model_config"]
        self.env_config = _checked_env_config(config, self.policy_config)
        self.val_config = with_episode_sizes(config.val, self.env_config)
        self.test_config = with_episode_sizes(config.test, self.env_config)

        torch.manual_seed(config.seed)
        self.policy = build_policy(self.model_type, self.policy_config)
        self.policy.load_state_dict(payload["model"])
        self.policy.eval()  # see the module docstring: kept in eval mode throughout
        self.actor, self.critic = make_ppo_modules(self.policy, config.value_hidden, config.critic_trunk_grad)
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
        )
        self.advantage_module = GAE(gamma=config.gamma, lmbda=config.lmbda, value_network=None, average_gae=False)
        self.policy_optimizer = torch.optim.Adam(self.policy.parameters(), lr=config.lr)
        self.critic_optimizer = torch.optim.Adam(self.critic.parameters(), lr=config.critic_lr)
        self.layout = {"frames_per_batch": config.frames_per_batch, "rows_per_batch": config.rows_per_batch}
        self.iteration = 0
        self.history: list[dict] = []
        self.best: dict = {}
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
        state = load_checkpoint(self.last_path, expected_model_type=self.model_type)
        if state.get("layout") != self.layout:
            raise ValueError(
                f"{self.last_path} was written with {state.get('layout')}, this config has {self.layout}: "
                f"frames_per_batch and the collector's agents must not change on resume (or use a new output_dir)."
            )
        self.policy.load_state_dict(state["model"])
        self.critic.module.load_state_dict(state["value_head"])
        self.policy_optimizer.load_state_dict(state["policy_optimizer"])
        self.critic_optimizer.load_state_dict(state["critic_optimizer"])
        self.iteration, self.history, self.best, self.start = state["iteration"], state["history"], state["best"], state["start"]
        torch.set_rng_state(state["torch_rng"])
        logger.info("resuming %s after iteration %d", self.output, self.iteration)

    def _evaluate_start(self) -> None:
        logger.info("evaluating the start policy %s on val and test", self.config.checkpoint)
        val, _ = evaluate_policy(self.policy, self.val_config, progress=self.config.progress)
        test, _ = evaluate_policy(self.policy, self.test_config, progress=self.config.progress)
        self.start = {"val": val, "test": test}
        logger.info("start: val success %.3f, test success %.3f", val["success"], test["success"])
        self.best = {"iteration": 0, "success": val["success"], "spl": val["spl"]}
        self._save_best(val)
        self._save_last()

    def _train(self, callback: Callable[[dict], None] | None) -> None:
        config = self.config
        num_iterations = config.num_iterations
        collector = make_collector(
            self.actor,
            self.env_config,
            config.collector,
            frames_per_batch=config.frames_per_batch,
            total_frames=(num_iterations - self.iteration) * config.frames_per_batch,
            seed=config.seed + _COLLECTOR_SALT * self.iteration,
            reset_at_each_iter=True,
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
                if self.iteration % config.val_every == 0 or self.iteration == num_iterations:
                    self._validate(record)
                self.history.append(record)
                self._save_last()
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
        record = episode_statistics(batch)
        compute_values(policy, self.critic, batch)
        with torch.no_grad():
            self.advantage_module(batch)
        keys = set(policy.in_keys) | {"action", "action_log_prob", "advantage", "value_target", VALUE_KEY, policy.features_key}
        if config.bc_coef > 0:
            keys.add(EXPERT_KEY)
        train_td = batch.select(*keys, strict=False)
        if self.reference is not None:
            ref_td = train_td.select(*self.reference.in_keys, strict=False).clone(False)
            with torch.no_grad(), set_recurrent_mode(True):
                train_td.set(REF_LOGITS_KEY, self.reference(ref_td).get(self.reference.logits_key))
        warmup = self.iteration < config.critic_warmup_iters
        generator = torch.Generator().manual_seed(config.seed * _PERMUTATION_SALT + self.iteration)
        sums: dict[str, float] = {}
        count = skipped = 0
        log_ratio_first = None
        for _ in range(config.ppo_epochs):
            order = torch.randperm(train_td.shape[0], generator=generator)
            for rows in order.split(config.minibatch_rows):
                minibatch = train_td[rows]
                self.policy_optimizer.zero_grad(set_to_none=True)
                self.critic_optimizer.zero_grad(set_to_none=True)
                if warmup:  # fit the new value head on the collected features; the policy is left as it is
                    loss_critic, _, explained = self.loss_module.loss_critic(minibatch)
                    total = loss_critic.mean()
                    metrics = {"loss_critic": total.detach()}
                    if explained is not None:
                        metrics["explained_variance"] = explained.detach()
                else:
                    out = self.loss_module(minibatch)
                    total = sum(value for key, value in out.items() if key.startswith("loss_"))
                    metrics = {key: value.detach() for key, value in out.items()}
                    if log_ratio_first is None:
                        log_ratio_first = float(metrics["max_abs_log_ratio"])
                total.backward()
                critic_norm = nn.utils.clip_grad_norm_(self.critic.parameters(), config.max_grad_norm)
                policy_norm = (
                    nn.utils.clip_grad_norm_(policy.parameters(), config.max_grad_norm) if not warmup else critic_norm
                )
                if not (torch.isfinite(total) and torch.isfinite(critic_norm) and torch.isfinite(policy_norm)):
                    # one bad minibatch must not turn the weights into NaN: skip its step, count it
                    skipped += 1
                    logger.warning("iteration %d: non-finite loss or gradient, update skipped", self.iteration + 1)
                    continue
                self.critic_optimizer.step()
                if not warmup:
                    self.policy_optimizer.step()
                for key, value in metrics.items():
                    if value.numel() == 1:
                        sums[key] = sums.get(key, 0.0) + float(value)
                count += 1
        record.update({key: value / max(count, 1) for key, value in sums.items()})
        record["skipped_updates"] = skipped
        record["critic_warmup"] = warmup
        if log_ratio_first is not None:
            record["log_ratio_first"] = log_ratio_first
            if log_ratio_first > RATIO_SYNC_TOLERANCE:
                logger.warning(
                    "iteration %d: the first minibatch's |log-ratio| is %.4f, not 0: the collector acted with "
                    "other weights than the learner's (weight sync), or the recurrent replay differs.",
                    self.iteration + 1,
                    log_ratio_first,
                )
        return record

    def _validate(self, record: dict) -> None:
        start = time.time()
        val, _ = evaluate_policy(self.policy, self.val_config, progress=False)
        record.update(val_success=val["success"], val_spl=val["spl"], val_seconds=time.time() - start)
        if (val["success"], val["spl"]) > (self.best["success"], self.best["spl"]):
            self.best = {"iteration": self.iteration, "success": val["success"], "spl": val["spl"]}
            self._save_best(val)

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
            "seed": self.config.seed,
            "wall_seconds_this_run": seconds,
            "config": asdict(self.config),
        }
        _atomic_json(self.output / "results.json", results)
        plot_if_available(
            plot_ppo, val_history, start, self.output / "ppo.png", title=f"PPO from {Path(self.config.checkpoint).name}"
        )
        return results

    # ------------------------------------------------------------------ checkpoints
    def _save_best(self, val: dict) -> None:
        """``best.pt``: the policy (same model type as the start) and value head, with its val scores."""
        save_checkpoint(
            self.best_path,
            self.model_type,
            self.policy_config,
            {"model": self.policy.state_dict(), "value_head": self.critic.module.state_dict(), "iteration": self.iteration, "val": val},
        )

    def _save_last(self) -> None:
        """``last.pt``: everything a resumed run needs (atomic)."""
        save_checkpoint(
            self.last_path,
            self.model_type,
            self.policy_config,
            {
                "model": self.policy.state_dict(),
                "value_head": self.critic.module.state_dict(),
                "policy_optimizer": self.policy_optimizer.state_dict(),
                "critic_optimizer": self.critic_optimizer.state_dict(),
                "iteration": self.iteration,
                "history": self.history,
                "best": self.best,
                "start": self.start,
                "layout": self.layout,
                "torch_rng": torch.get_rng_state(),
            },
        )


# ---------------------------------------------------------------------- helpers
def _checked_env_config(config: PPOConfig, policy_config) -> CollectionEnvConfig:
    env = config.env
    if env.demo_length != policy_config.demo_length:
        raise ValueError(
            f"env.demo_length must equal the checkpoint's demo_length {policy_config.demo_length}, got {env.demo_length}."
        )
    if (env.image_size, env.image_size) != tuple(policy_config.image_size):
        raise ValueError(
            f"env.image_size must equal the checkpoint's image size {tuple(policy_config.image_size)}, got {env.image_size}."
        )
    if config.bc_coef > 0 and not env.with_expert:
        logger.info("bc_coef > 0: the env emits expert_action (env.with_expert=True)")
        env = dataclasses.replace(env, with_expert=True)
    return env


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
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
