"""The model registry: the SPF policy or a baseline built from a model name and hyper-parameters,
through the factories of :mod:`spf_rl.modules.factories`."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from spf_rl.modules.config import SPFConfig
from spf_rl.modules.factories import make_action_only_policy, make_rpf_original_policy, make_rpf_policy, make_spf_policy
from spf_rl.modules.memory import validate_sparsity_range
from spf_rl.modules.policy import SPFPolicy

#: Model names the recipes accept.
MODEL_NAMES = ("spf", "rpf", "rpf_original", "action_only", "spf_random")
#: Default sparsity range of ``"spf_random"`` (a sparsity per training episode).
DEFAULT_SPARSITY_RANGE = (0.2, 1.0)


@dataclass
class ModelConfig:
    """Which policy to train and its hyper-parameters.

    Args:
        name: ``"spf"`` (sparse memory), ``"rpf"`` (SPF with full memory),
            ``"rpf_original"`` (the RPF lab code's memory network, full memory), ``"action_only"``,
            or ``"spf_random"`` (one SPF model trained with a sparsity drawn per
            episode from ``sparsity_range``; not in the paper).
        sparsity: memory sparsity for ``"spf"``, in (0, 1]; for ``"spf_random"`` the
            sparsity it is validated and tested at (change it later with
            :meth:`~spf_rl.modules.policy.SPFPolicy.set_sparsity`).
        pointer_update: ``"paper"`` or ``"rpf"``.
        k: half-width of the hard action window.
        feature_dim: image feature size.
        hidden_size: GRU hidden size.
        initial_pointer_step: untrained pointer increment tanh(b) (see :class:`SPFConfig`).
        sparsity_range: ``[low, high]``, ``0 < low <= high <= 1``: the training
            sparsities of ``"spf_random"`` (ignored by the other models).

    Examples:
        >>> cfg = ModelConfig(name="spf_random", sparsity=0.6)
        >>> spf_config(cfg, demo_length=30, image_size=64).sparsity_range
        (0.2, 1.0)
    """

    name: str = "spf"
    sparsity: float = SPFConfig.sparsity
    pointer_update: str = SPFConfig.pointer_update
    k: int = SPFConfig.k
    feature_dim: int = SPFConfig.feature_dim
    hidden_size: int = SPFConfig.hidden_size
    initial_pointer_step: float = SPFConfig.initial_pointer_step
    sparsity_range: list[float] = field(default_factory=lambda: list(DEFAULT_SPARSITY_RANGE))

    def __post_init__(self) -> None:
        if self.name not in MODEL_NAMES:
            raise ValueError(f"model name must be one of {MODEL_NAMES}, got {self.name!r}.")
        # the network's hyper-parameters are checked here, when the config is loaded, with
        # SPFConfig's own checks: a bad one is refused (naming it) before any data is built or run written
        try:
            self.sparsity_range = list(validate_sparsity_range(self.sparsity_range))
            SPFConfig(
                sparsity=self.sparsity, pointer_update=self.pointer_update, k=self.k, feature_dim=self.feature_dim,
                hidden_size=self.hidden_size, initial_pointer_step=self.initial_pointer_step,
            )
        except ValueError as err:
            raise ValueError(f"model.{err}") from None


def spf_config(model: ModelConfig, demo_length: int, image_size: int, num_actions: int = 3) -> SPFConfig:
    """The :class:`SPFConfig` of a :class:`ModelConfig` for an env's sizes.

    ``sparsity_range`` is set only for ``"spf_random"``.
    """
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
        sparsity_range=tuple(model.sparsity_range) if model.name == "spf_random" else None,
    )


def build_policy(model_type: str, config: SPFConfig) -> SPFPolicy:
    """The policy module of a model type (the config's memory mode is set by the type).

    ``"spf_random"`` needs ``config.sparsity_range`` and ``"spf"`` refuses it, so that a
    checkpoint's type and its memory layout always agree; ``"rpf"`` and
    ``"action_only"`` drop it.

    Raises:
        ValueError: unknown ``model_type``, or ``config.sparsity_range`` does not fit it.
    """
    if model_type in ("spf", "spf_random"):
        has_range = config.sparsity_range is not None
        if has_range != (model_type == "spf_random"):
            raise ValueError(
                f"model_type {model_type!r} needs config.sparsity_range "
                f"{'set (a (low, high) pair)' if model_type == 'spf_random' else 'None'}, "
                f"got sparsity_range={config.sparsity_range!r}."
            )
        return make_spf_policy(dataclasses.replace(config, memory_mode="sparse"))
    if model_type == "rpf":
        return make_rpf_policy(config)
    if model_type == "rpf_original":
        return make_rpf_original_policy(config)
    if model_type == "action_only":
        return make_action_only_policy(config)
    raise ValueError(f"model_type must be one of {MODEL_NAMES}, got {model_type!r}.")
