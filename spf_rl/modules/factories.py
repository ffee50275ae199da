"""Factories of the SPF policy and its baselines, all composed of the same parts (:class:`~spf_rl.modules.SPFPolicy`)."""
from __future__ import annotations

import dataclasses

import torch
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Categorical
from torchrl.modules import ProbabilisticActor

from spf_rl.modules.config import FULL_MEMORY_SPARSITY, NUM_PAPER_ACTIONS, SPFConfig
from spf_rl.modules.policy import SPFPolicy

__all__ = ["make_action_only_policy", "make_actor", "make_rpf_original_policy", "make_rpf_policy", "make_spf_policy"]


def make_spf_policy(config: SPFConfig | None = None, encoder: nn.Module | None = None, **kwargs) -> SPFPolicy:
    """Build the SPF policy (sparse memory) from a config.

    Args:
        config (SPFConfig, optional): configuration. Defaults to ``SPFConfig()``.
        encoder (nn.Module, optional): image encoder phi. Defaults to :class:`ImageEncoder`.
        **kwargs: key overrides forwarded to :class:`SPFPolicy`.

    Examples:
        >>> policy = make_spf_policy(SPFConfig(feature_dim=8, hidden_size=8))
        >>> policy.memory_length  # round(0.8 * 30)
        24
    """
    return SPFPolicy(config, encoder, **kwargs)


def make_rpf_policy(
    config: SPFConfig | None = None, encoder: nn.Module | None = None, **kwargs
) -> SPFPolicy:
    """RPF baseline: the same network with the full visual memory (sparsity 1.0).

    The pointer update is taken from ``config`` (pass
    ``dataclasses.replace(config, pointer_update="rpf")`` for the RPF code's rule);
    ``sparsity_range`` is dropped (the memory is always full).

    Examples:
        >>> make_rpf_policy(SPFConfig(feature_dim=8, hidden_size=8)).memory_length
        30
    """
    config = SPFConfig() if config is None else config
    config = dataclasses.replace(
        config, memory_mode="full", sparsity=FULL_MEMORY_SPARSITY, sparsity_range=None
    )
    return SPFPolicy(config, encoder, **kwargs)


def make_action_only_policy(
    config: SPFConfig | None = None, encoder: nn.Module | None = None, **kwargs
) -> SPFPolicy:
    """RPF action-only baseline: no frames in memory; psi sees only the demo actions.

    psi takes the hard action window and, unless ``config.soft_action_memory`` is
    ``False``, the soft action memory ``sum_j exp(-|eta - j|) onehot(a_j)``, through
    which the pointer gets a gradient (``soft_action_memory=None``, the default,
    resolves to ``True`` here). With ``soft_action_memory=False`` the pointer
    only enters through ``floor(eta)`` and the pointer head receives no gradient.
    ``sparsity_range`` is dropped (there are no memory frames).

    Examples:
        >>> make_action_only_policy(SPFConfig(feature_dim=8, hidden_size=8)).memory_length
        0
    """
    config = SPFConfig() if config is None else config
    config = dataclasses.replace(config, memory_mode="none", sparsity_range=None)
    return SPFPolicy(config, encoder, **kwargs)


def make_rpf_original_policy(
    config: SPFConfig | None = None, encoder: nn.Module | TensorDictModule | None = None, **kwargs
) -> SPFPolicy:
    """RPF as its authors' lab code builds it: full memory of MLP slots, the ``"rpf"`` pointer, 2-layer heads.

    See :mod:`spf_rl.modules.rpf`. ``mu_dim`` (default ``feature_dim``) is the
    memory-slot size; ``sparsity_range``, ``k`` and ``soft_action_memory`` do not apply.

    Examples:
        >>> policy = make_rpf_original_policy(SPFConfig(feature_dim=8, hidden_size=8))
        >>> policy.memory_length, policy.config.pointer_update, "demo_actions" in policy.memory.in_keys
        (30, 'rpf', True)
    """
    config = SPFConfig() if config is None else config
    config = dataclasses.replace(
        config,
        memory_mode="full",
        sparsity=FULL_MEMORY_SPARSITY,
        sparsity_range=None,
        pointer_update="rpf",
        soft_action_memory=False,
        architecture="rpf_original",
    )
    return SPFPolicy(config, encoder, **kwargs)


def make_actor(
    policy: TensorDictModuleBase,
    num_actions: int = NUM_PAPER_ACTIONS,
    *,
    logits_key: NestedKey = "logits",
    action_key: NestedKey = "action",
) -> ProbabilisticActor:
    """Wrap a logits-producing policy in a :class:`~torchrl.modules.ProbabilisticActor`.

    Samples from ``Categorical(logits)`` (greedy argmax under
    ``ExplorationType.DETERMINISTIC``) and writes ``action`` and its log-probability.

    Args:
        policy (TensorDictModuleBase): module writing ``logits_key``.
        num_actions (int, optional): number of actions. Defaults to 3.

    Keyword Args:
        logits_key (NestedKey): logits key. Defaults to ``"logits"``.
        action_key (NestedKey): action key. Defaults to ``"action"``.

    Examples:
        >>> from spf_rl.modules import SPFConfig, make_spf_policy, make_actor
        >>> actor = make_actor(make_spf_policy(SPFConfig(feature_dim=8, hidden_size=8)), 3)
        >>> "action" in actor.out_keys
        True
    """
    return ProbabilisticActor(
        module=policy,
        in_keys=[logits_key],
        out_keys=[action_key],
        spec=Categorical(num_actions),
        distribution_class=torch.distributions.Categorical,
        return_log_prob=True,
    )
