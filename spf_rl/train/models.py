"""Build the SPF policy or a baseline from a model name and hyper-parameters."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from spf_rl.modules.policy import (
    SPFConfig,
    SPFPolicy,
    make_action_only_policy,
    make_rpf_policy,
    make_spf_policy,
)

#: Model names the recipes accept.
MODEL_NAMES = ("spf", "rpf", "action_only")


@dataclass
class ModelConfig:
    """Which policy to train and its hyper-parameters.

    Args:
        name: ``"spf"`` (sparse memory), ``"rpf"`` (full memory) or ``"action_only"``.
        sparsity: memory sparsity for ``"spf"``, in (0, 1].
        pointer_update: ``"paper"`` or ``"rpf"``.
        k: half-width of the hard action window.
        feature_dim: image feature size.
        hidden_size: GRU hidden size.
        initial_pointer_step: untrained pointer increment tanh(b) (see :class:`SPFConfig`).
    """

    name: str = "spf"
    sparsity: float = 0.8
    pointer_update: str = "paper"
    k: int = 2
    feature_dim: int = 128
    hidden_size: int = 128
    initial_pointer_step: float = 0.0

    def __post_init__(self) -> None:
        if self.name not in MODEL_NAMES:
            raise ValueError(f"model name must be one of {MODEL_NAMES}, got {self.name!r}.")


def spf_config(model: ModelConfig, demo_length: int, image_size: int, num_actions: int = 3) -> SPFConfig:
    """The :class:`SPFConfig` of a :class:`ModelConfig` for an env's sizes."""
    return SPFConfig(
        num_actions=num_actions,
        demo_length=demo_length,
        sparsity=model.sparsity,
        k=model.k,
        feature_dim=model.feature_dim,
        hidden_size=model.hidden_size,
        pointer_update=model.pointer_update,
        initial_pointer_step=model.initial_pointer_step,
        image_size=(image_size, image_size),
    )


def build_policy(model_type: str, config: SPFConfig) -> SPFPolicy:
    """The policy module of a model type (the config's memory mode is set by the type)."""
    if model_type == "spf":
        return make_spf_policy(dataclasses.replace(config, memory_mode="sparse"))
    if model_type == "rpf":
        return make_rpf_policy(config)
    if model_type == "action_only":
        return make_action_only_policy(config)
    raise ValueError(f"model_type must be one of {MODEL_NAMES}, got {model_type!r}.")
