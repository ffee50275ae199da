"""The PPO loss of a recurrent SPF policy: actor, value head, loss and batch helpers.

What :func:`~spf_rl.train.ppo.train_ppo` optimises, with TorchRL's
:class:`~torchrl.objectives.ClipPPOLoss` and :class:`~torchrl.objectives.value.GAE`:

* **Critic.** A small MLP value head (:class:`ValueHead`) on the policy's GRU
  output ``"features"`` (a shared trunk). By default it reads the features
  detached, so only the policy loss shapes the pretrained trunk
  (``critic_trunk_grad=True`` lets the critic's gradient in). The head starts
  untrained: for the first ``critic_warmup_iters`` iterations only the head is
  fitted and the policy is left as it is.
* **Recurrence.** PPO minibatches are whole rows ``[B, T]``; the loss runs the
  policy in sequence mode (:func:`torchrl.modules.set_recurrent_mode`), which
  restarts from the stored state at ``t = 0`` and wherever ``is_init`` is true,
  so on the first epoch the recomputed log-probabilities equal the collected
  ``action_log_prob`` (:func:`recompute_log_prob`; the training loop records the
  largest ``|log-ratio|`` of the first minibatch as ``log_ratio_first``). Values for GAE
  are exact step-mode values: ``V(s_t)`` from the collected ``features`` and
  ``V(s_{t+1})`` from the next step's features (one step-mode call from the stored
  next state where the episode ended or the batch is cut) (:func:`compute_values`).
* **Regularisation toward the start** (optional): ``kl_coef * KL(pi || pi_BC)``
  against the frozen starting policy (run in sequence mode on the batch), and
  ``bc_coef * CE(pi, expert_action)`` on the env's expert labels (:class:`SPFPPOLoss`).
* **Mixed precision** (``amp``): the collection policy (:class:`Autocast`), the values
  and the loss run under bf16 autocast, so that step mode (collection) and sequence
  mode (the loss) agree up to bf16 rounding: on the shipped SPF 0.8 checkpoint their
  log-probabilities differ by about 0.015, hence :data:`AMP_RATIO_SYNC_TOLERANCE`.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torch import nn
from torchrl.modules import ProbabilisticActor, set_recurrent_mode
from torchrl.objectives import ClipPPOLoss

from spf_rl.device import autocast, module_device
from spf_rl.modules import SPFPolicy, make_actor

__all__ = [
    "AMP_RATIO_SYNC_TOLERANCE",
    "Autocast",
    "EXPERT_KEY",
    "RATIO_SYNC_TOLERANCE",
    "REF_LOGITS_KEY",
    "SPFPPOLoss",
    "VALUE_KEY",
    "ValueHead",
    "compute_values",
    "episode_statistics",
    "make_ppo_modules",
    "recompute_log_prob",
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
#: The same under bf16 autocast (``amp``): step and sequence mode then differ by bf16
#: rounding (about 0.015 in log-probability on the shipped SPF 0.8 checkpoint).
AMP_RATIO_SYNC_TOLERANCE = 5e-2


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


class Autocast(TensorDictModuleBase):
    """Run a TensorDict module under bf16 autocast and hand back float32 outputs.

    PPO collects with it under ``amp``, so that the collected log-probabilities come
    from the same bf16 computation as the loss's. The floating outputs (logits,
    ``action_log_prob``, the next recurrent state) are cast back to float32 (exact:
    every bf16 value is a float32), so the stored batch and the env's state stay
    float32. The module's recurrent-state primer is passed on.

    Args:
        module: the module (e.g. the actor of :func:`make_ppo_modules`).

    Examples:
        >>> from tensordict import TensorDict
        >>> linear = TensorDictModule(nn.Linear(2, 3), ["x"], ["y"])
        >>> Autocast(linear)(TensorDict({"x": torch.ones(4, 2)}, [4]))["y"].dtype
        torch.float32
    """

    def __init__(self, module: TensorDictModuleBase) -> None:
        super().__init__()
        self.module = module
        self.in_keys = list(module.in_keys)
        self.out_keys = list(module.out_keys)
        if hasattr(module, "make_tensordict_primer"):
            self.make_tensordict_primer = module.make_tensordict_primer

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """The module's forward under autocast, its floating outputs as float32."""
        with autocast(module_device(self.module), True):
            tensordict = self.module(tensordict)
        for key in self.out_keys:
            value = tensordict.get(key, None)
            if value is not None and value.is_floating_point() and value.dtype != torch.float32:
                tensordict.set(key, value.float())
        return tensordict


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
            log_p = torch.log_softmax(dist.logits.float(), -1)
            if self.kl_coef:
                ref = torch.log_softmax(tensordict.get(REF_LOGITS_KEY).float(), -1)
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


def compute_values(
    policy: SPFPolicy, critic: TensorDictModule, batch: TensorDictBase, amp: bool = False
) -> TensorDictBase:
    """Write ``state_value`` and ``("next", "state_value")`` of a collected ``[N, T]`` batch.

    ``V(s_t)`` is the value head on the collected ``features`` (the GRU output of the
    step, computed by the current weights during collection). ``V(s_{t+1})`` is
    ``V(s_{t+1})`` of the row where the episode goes on within the batch, and
    elsewhere (episode ended, batch cut) one step-mode call from the stored next
    state on the next observation (the terminal or cut-off observation).

    Args:
        policy: the trunk.
        critic: the value head module.
        batch: the batch (modified in place), on the device of the modules.
        amp: compute under bf16 autocast (the values are stored as float32).

    Returns:
        ``batch``.
    """
    features_key = policy.features_key
    with torch.no_grad(), autocast(module_device(policy), amp):
        value = critic.module(batch.get(features_key)).float()
        next_value = torch.roll(value, -1, dims=1)
        need = batch.get(("next", "done")).reshape(batch.shape).clone()
        need[:, -1] = True
        rows = batch.get("next").select(*policy.in_keys, strict=False)[need]
        rows = policy(rows)
        next_value[need] = critic.module(rows.get(features_key)).float()
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
    rows = torch.arange(batch.shape[0], device=has_end.device)[has_end]
    end = end[has_end]
    stats = {"reward_per_step": float(reward.mean()), "episodes": int(has_end.sum())}
    if len(rows) == 0:
        return {**stats, "success": float("nan"), "spl": float("nan"), "return": float("nan"), "length": float("nan")}
    steps = torch.arange(batch.shape[1], device=end.device)
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
