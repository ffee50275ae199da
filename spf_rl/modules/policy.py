"""The SPF path-following policy (paper Sec. 3.2, eqs. 1-4) and its baselines.

:class:`SPFPolicy` is a recurrent :class:`~tensordict.nn.TensorDictModuleBase`:

* ``mu_t = psi( sum_j m_j exp(-|eta_t - M*(j)|), a[floor(eta_t)-k .. floor(eta_t)+k] )`` (eq. 2),
  plus, with ``SPFConfig.soft_action_memory`` (default for the action-only
  baseline), the soft action memory ``sum_{j<n} exp(-|eta_t - j|) onehot(a_j)``
* ``h_{t+1}, b, a_t = pi(h_t, mu_t, phi(o_t), a_window)`` with ``pi`` a GRU cell (eq. 3)
* ``eta_{t+1} = eta_t + tanh(b)`` (eq. 4, ``pointer_update="paper"``) or the RPF
  authors' ``min(eta_t + 1 + tanh(b), n - 1)`` (``pointer_update="rpf"``).

Beyond the paper, ``SPFConfig.sparsity_range`` gives one model for many
sparsities: the memory holds all ``n`` demo frames and a mask keeps those at
``M*`` of a sparsity drawn per training episode, or of :attr:`SPFPolicy.sparsity`
(set with :meth:`SPFPolicy.set_sparsity`) at evaluation.

Indices and the pointer are 0-based (``eta_1 = 0``, ``h_1 = 0``). The memory
features are encoded once per episode (where ``is_init`` is true) and carried in
the recurrent state with the GRU hidden state and the pointer; the module
provides :meth:`SPFPolicy.make_tensordict_primer` so that
:func:`~torchrl.envs.utils.get_primers_from_module`, ``ParallelEnv(..., policy=)``
and ``Collector(auto_register_policy_transforms=True)`` register the state keys.

Baselines built from the same parts: :func:`make_rpf_policy` (full memory),
:func:`make_action_only_policy` (no frames in memory) and :class:`OpenLoopPolicy`
(replays the demonstration actions).
"""
from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass, field
from typing import Literal

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Categorical, Unbounded
from torchrl.envs import TensorDictPrimer
from torchrl.modules import ProbabilisticActor
from torchrl.modules.tensordict_module.rnn import recurrent_mode

from spf_rl.modules.attention import PointerAttention
from spf_rl.modules.encoder import ImageEncoder
from spf_rl.modules.memory import (
    MemoryEncoder,
    memory_indices,
    memory_length,
    memory_mask,
    validate_sparsity,
    validate_sparsity_range,
)

logger = logging.getLogger(__name__)

__all__ = [
    "OpenLoopPolicy",
    "SPFConfig",
    "SPFPolicy",
    "make_action_only_policy",
    "make_actor",
    "make_rpf_policy",
    "make_spf_policy",
]

#: Paper action set: 0 forward, 1 turn left, 2 turn right.
NUM_PAPER_ACTIONS = 3
#: Action index of the optional STOP action.
STOP_ACTION = 3
#: Action index of "turn left" (a move that keeps the agent's position).
TURN_LEFT_ACTION = 1
ALLOWED_NUM_ACTIONS = (NUM_PAPER_ACTIONS, NUM_PAPER_ACTIONS + 1)
#: Demonstration length n of the paper (Sec. 4.1).
DEFAULT_DEMO_LENGTH = 30
DEFAULT_SPARSITY = 0.4
POINTER_UPDATES = ("paper", "rpf")
MEMORY_MODES = ("sparse", "full", "none")
#: Sparsity used by the full-memory (RPF) baseline.
FULL_MEMORY_SPARSITY = 1.0
#: Logit given to non-replayed actions by :class:`OpenLoopPolicy`.
OPEN_LOOP_OFF_LOGIT = -1.0e4


@dataclass
class SPFConfig:
    """Configuration of :class:`SPFPolicy`.

    Args:
        num_actions (int): number of policy actions, 3 (forward, left, right) or 4
            (with STOP = 3). Also the one-hot size of the demo actions in the window.
        demo_length (int): demonstration length ``n`` (frames and actions).
        sparsity (float): fraction of demo frames kept in memory, in ``(0, 1]``
            (used when ``memory_mode="sparse"``). With ``sparsity_range`` it is the
            default evaluation sparsity (:attr:`SPFPolicy.sparsity`).
        k (int): half-width of the hard action window (``2k + 1`` actions).
        feature_dim (int): size of the image features phi(o) and memory features.
        hidden_size (int): GRU hidden size.
        pointer_update (str): ``"paper"`` (``eta + tanh(b)``) or ``"rpf"``
            (``min(eta + 1 + tanh(b), n - 1)``).
        memory_mode (str): ``"sparse"`` (``l = round(sparsity * n)`` frames),
            ``"full"`` (all ``n`` frames, RPF) or ``"none"`` (action only).
        image_size (tuple of int): frame ``(height, width)`` in pixels.
        mu_dim (int, optional): output size of psi; defaults to ``feature_dim``.
        soft_action_memory (bool, optional): psi also takes the soft-attended action
            memory ``sum_{j=0}^{n-1} exp(-|eta - j|) onehot(a_j)`` over all ``n`` demo
            actions (the un-normalised weights of eq. 2; see
            :func:`~spf_rl.modules.attention.soft_action_memory`). ``None`` (default)
            means ``True`` for ``memory_mode="none"`` and ``False`` otherwise: without
            visual memory the pointer would only enter through ``floor(eta)`` in the
            hard window, get no gradient and never learn; with visual memory the soft
            weights over the memory frames already make eta differentiable, and the
            paper's eq. 2 has no such term. ``None`` is kept (so that
            ``dataclasses.replace(cfg, memory_mode=...)`` re-resolves it); read the
            resolved value from :attr:`use_soft_action_memory`. Not in the SPF paper:
            it follows RPF's action memory.
        initial_pointer_step (float): pointer increment ``tanh(b)`` of the untrained
            network (the pointer head's bias is set to ``atanh`` of it), in ``(-1, 1)``.
            0 (default) is PyTorch's usual initialisation; a value near 1 starts the
            pointer moving along the demonstration about one index per step, as the
            RPF code's rule does. The paper does not say how b is initialised.
        sparsity_range (tuple of float, optional): ``(low, high)`` with
            ``0 < low <= high <= 1``: train one model for many sparsities (needs
            ``memory_mode="sparse"``). The memory then holds a slot for each of the
            ``n`` demo frames and attends only to the slots at
            ``memory_indices(n, s)``: in training mode, sequence mode draws
            ``s ~ Uniform(low, high)`` per episode segment; otherwise ``s`` is
            :attr:`SPFPolicy.sparsity`. Not in the SPF paper. Defaults to ``None``
            (one fixed sparsity, ``l`` memory slots).

    Examples:
        >>> cfg = SPFConfig(sparsity=0.4)
        >>> cfg.memory_length, cfg.memory_indices.tolist()[:4]
        (12, [0, 3, 5, 8])
        >>> cfg.use_soft_action_memory, SPFConfig(memory_mode="none").use_soft_action_memory
        (False, True)
        >>> SPFConfig(sparsity=0.8, sparsity_range=[0.2, 1]).sparsity_range
        (0.2, 1.0)
    """

    num_actions: int = NUM_PAPER_ACTIONS
    demo_length: int = DEFAULT_DEMO_LENGTH
    sparsity: float = DEFAULT_SPARSITY
    k: int = 2
    feature_dim: int = 128
    hidden_size: int = 128
    pointer_update: Literal["paper", "rpf"] = "paper"
    memory_mode: Literal["sparse", "full", "none"] = "sparse"
    image_size: tuple[int, int] = field(default=(64, 64))
    mu_dim: int | None = None
    soft_action_memory: bool | None = None
    initial_pointer_step: float = 0.0
    sparsity_range: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if self.num_actions not in ALLOWED_NUM_ACTIONS:
            raise ValueError(
                f"num_actions must be one of {ALLOWED_NUM_ACTIONS} (3 without STOP, 4 with STOP), "
                f"got {self.num_actions!r}."
            )
        if isinstance(self.demo_length, bool) or not isinstance(self.demo_length, int) or self.demo_length < 1:
            raise ValueError(f"demo_length must be a positive int, got {self.demo_length!r}.")
        validate_sparsity(self.sparsity)
        if not isinstance(self.k, int) or self.k < 0:
            raise ValueError(f"k must be an int >= 0, got {self.k!r}.")
        for name in ("feature_dim", "hidden_size"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive int, got {value!r}.")
        if self.mu_dim is not None and (not isinstance(self.mu_dim, int) or self.mu_dim < 1):
            raise ValueError(f"mu_dim must be a positive int or None, got {self.mu_dim!r}.")
        if not -1.0 < float(self.initial_pointer_step) < 1.0:
            raise ValueError(f"initial_pointer_step must be in (-1, 1), got {self.initial_pointer_step!r}.")
        if self.pointer_update not in POINTER_UPDATES:
            raise ValueError(
                f"pointer_update must be one of {POINTER_UPDATES}, got {self.pointer_update!r}."
            )
        if self.memory_mode not in MEMORY_MODES:
            raise ValueError(
                f"memory_mode must be one of {MEMORY_MODES}, got {self.memory_mode!r}."
            )
        if self.sparsity_range is not None:
            self.sparsity_range = validate_sparsity_range(self.sparsity_range)
            if self.memory_mode != "sparse":
                raise ValueError(
                    f"sparsity_range needs memory_mode='sparse' (a random sparsity of the visual "
                    f"memory), got memory_mode={self.memory_mode!r}; set sparsity_range=None."
                )
        if self.soft_action_memory is not None and not isinstance(self.soft_action_memory, bool):
            raise ValueError(
                f"soft_action_memory must be a bool or None (auto), got {self.soft_action_memory!r}."
            )
        self.image_size = tuple(self.image_size)  # type: ignore[assignment]
        if len(self.image_size) != 2 or any(
            not isinstance(s, int) or s < 1 for s in self.image_size
        ):
            raise ValueError(
                f"image_size must be (height, width) in pixels, got {self.image_size!r}."
            )

    @property
    def use_soft_action_memory(self) -> bool:
        """Resolved ``soft_action_memory``: the flag, or ``memory_mode == "none"`` when ``None``."""
        if self.soft_action_memory is None:
            return self.memory_mode == "none"
        return bool(self.soft_action_memory)

    @property
    def effective_sparsity(self) -> float:
        """Sparsity actually used: ``sparsity`` for sparse memory, 1.0 for full, 0 for none."""
        if self.memory_mode == "full":
            return FULL_MEMORY_SPARSITY
        if self.memory_mode == "none":
            return 0.0
        return float(self.sparsity)

    @property
    def memory_length(self) -> int:
        """Number of memory frames ``l`` (0 when ``memory_mode="none"``)."""
        if self.memory_mode == "none":
            return 0
        return memory_length(self.demo_length, self.effective_sparsity)

    @property
    def memory_indices(self) -> torch.Tensor:
        """0-based memory indices ``M*`` (empty when ``memory_mode="none"``)."""
        if self.memory_mode == "none":
            return torch.zeros(0, dtype=torch.long)
        return memory_indices(self.demo_length, self.effective_sparsity)


def _flat_or_zeros(
    value: torch.Tensor | None, shape: tuple[int, ...], like: torch.Tensor
) -> torch.Tensor:
    if value is None:
        return like.new_zeros(shape)
    return value.reshape(shape).to(like.dtype)


class SPFPolicy(TensorDictModuleBase):
    """Sparse-memory path-following policy (SPF), a recurrent TensorDict module.

    Reads the current frame, the demonstration (frames and actions), ``is_init``
    and the recurrent state (GRU hidden state, pointer, memory features); writes
    action logits, the GRU output ``features`` (e.g. for a value head), the pointer
    used at this step, and the next recurrent state under ``"next"``.

    **Step mode** (default): the input has batch shape ``[]`` or ``[*B]``. Where
    ``is_init`` is true, ``h`` and ``eta`` are reset to 0 and the memory frames are
    encoded from ``demo_frames``; elsewhere the stored state is used, and no memory
    frame is encoded. A missing state key counts as zeros (and a missing memory as
    "encode now").

    **Sequence mode**, inside ``torchrl.modules.set_recurrent_mode(True)``: the input
    is ``[*B, T]`` (time last). All frames are encoded in one call; the memory is
    encoded at ``t = 0`` and at every step where ``is_init`` is true; the GRU cell is
    unrolled over ``T``. As in :class:`~torchrl.modules.GRUModule`, a segment (``t = 0``
    or ``is_init``) starts from the *stored* ``h`` and ``eta`` of that step: zeros at a
    real episode start (the primer zeroes them at reset), the carried state at a
    slice start that :class:`~torchrl.data.SliceSampler` marks with ``is_init``. A
    missing state key counts as zeros. The logits equal those of step mode on the
    same trajectory. Sequence mode always re-encodes the memory, so gradients reach
    the encoder through the memory too; the stored memory features are not read.

    **Random sparsity** (``config.sparsity_range`` set, model ``"spf_random"``): the
    memory holds all ``n`` demo frames (``memory_features`` is ``[n, D]``) and a
    boolean mask ``[n]``, true at ``memory_indices(n, s)``, sets the attention weights
    of the other slots to exactly 0, so those frames do not reach the output. In
    training mode, sequence mode draws ``s ~ Uniform(*sparsity_range)`` from torch's
    global RNG (``torch.manual_seed`` fixes it) for each segment and keeps it for the
    whole segment. In eval mode, and always in step mode, ``s`` is :attr:`sparsity`
    (``config.sparsity`` until :meth:`set_sparsity`). The mask used is written to
    ``memory_mask``.

    Args:
        config (SPFConfig, optional): model configuration. Defaults to ``SPFConfig()``.
        encoder (nn.Module, optional): image encoder phi mapping ``[*, H, W, 3]`` to
            ``[*, D]``; it is shared by observations and memory frames. Its output size
            is read from ``encoder.feature_dim`` if present, else ``config.feature_dim``.
            Defaults to :class:`ImageEncoder` built from the config.

    Keyword Args:
        pixels_key, demo_frames_key, demo_actions_key, is_init_key (NestedKey): input keys.
            Defaults ``"pixels"``, ``"demo_frames"``, ``"demo_actions"``, ``"is_init"``.
        hidden_key, eta_key, memory_key (NestedKey): recurrent state keys. Defaults
            ``"spf_hidden"`` (``[hidden_size]``), ``"eta"`` (``[1]``),
            ``"memory_features"`` (``[l, D]``, ``[n, D]`` with ``config.sparsity_range``,
            absent when ``memory_mode="none"``).
        logits_key, features_key, eta_used_key (NestedKey): output keys. Defaults
            ``"logits"``, ``"features"``, ``"eta_used"``.
        memory_mask_key (NestedKey): output key of the memory mask (``[n]`` bool),
            written only with ``config.sparsity_range``. Defaults to ``"memory_mask"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from spf_rl.modules import SPFConfig, SPFPolicy
        >>> cfg = SPFConfig(demo_length=6, sparsity=0.5, feature_dim=16, hidden_size=16, image_size=(16, 16))
        >>> policy = SPFPolicy(cfg)
        >>> td = TensorDict({
        ...     "pixels": torch.randint(0, 256, (2, 16, 16, 3), dtype=torch.uint8),
        ...     "demo_frames": torch.randint(0, 256, (2, 6, 16, 16, 3), dtype=torch.uint8),
        ...     "demo_actions": torch.randint(0, 3, (2, 6)),
        ...     "is_init": torch.ones(2, 1, dtype=torch.bool)}, batch_size=[2])
        >>> out = policy(td)
        >>> out["logits"].shape, out["next", "memory_features"].shape
        (torch.Size([2, 3]), torch.Size([2, 3, 16]))
        >>> # one model for many sparsities: all n slots in memory, a mask picks M*
        >>> import dataclasses
        >>> random_policy = SPFPolicy(dataclasses.replace(cfg, sparsity_range=(0.2, 1.0)))
        >>> out = random_policy.set_sparsity(0.5)(td)
        >>> out["next", "memory_features"].shape, out["memory_mask"][0].tolist()
        (torch.Size([2, 6, 16]), [True, False, True, False, False, True])
    """

    def __init__(
        self,
        config: SPFConfig | None = None,
        encoder: nn.Module | None = None,
        *,
        pixels_key: NestedKey = "pixels",
        demo_frames_key: NestedKey = "demo_frames",
        demo_actions_key: NestedKey = "demo_actions",
        is_init_key: NestedKey = "is_init",
        hidden_key: NestedKey = "spf_hidden",
        eta_key: NestedKey = "eta",
        memory_key: NestedKey = "memory_features",
        logits_key: NestedKey = "logits",
        features_key: NestedKey = "features",
        eta_used_key: NestedKey = "eta_used",
        memory_mask_key: NestedKey = "memory_mask",
    ) -> None:
        super().__init__()
        config = SPFConfig() if config is None else config
        if not isinstance(config, SPFConfig):
            raise TypeError(f"config must be an SPFConfig, got {type(config).__name__}.")
        self.config = config
        if encoder is None:
            encoder = ImageEncoder(config.feature_dim, config.image_size)
        self.encoder = encoder
        feature_dim = int(getattr(encoder, "feature_dim", config.feature_dim))
        self.feature_dim = feature_dim
        self.use_memory = config.memory_mode != "none"
        self.random_sparsity = config.sparsity_range is not None
        slots = torch.arange(config.demo_length) if self.random_sparsity else config.memory_indices
        self.memory_encoder = MemoryEncoder(encoder, slots) if self.use_memory else None
        self._sparsity = config.effective_sparsity
        mu_dim = config.mu_dim or config.feature_dim
        self.attention = PointerAttention(
            feature_dim,
            mu_dim,
            k=config.k,
            num_action_classes=config.num_actions,
            action_only=not self.use_memory,
            soft_action_memory=config.use_soft_action_memory,
        )
        self.gru = nn.GRUCell(
            mu_dim + feature_dim + self.attention.window_dim, config.hidden_size
        )
        self.logits_head = nn.Linear(config.hidden_size, config.num_actions)
        self.pointer_head = nn.Linear(config.hidden_size, 1)
        if config.initial_pointer_step:
            nn.init.zeros_(self.pointer_head.weight)
            nn.init.constant_(self.pointer_head.bias, math.atanh(config.initial_pointer_step))

        self.pixels_key = pixels_key
        self.demo_frames_key = demo_frames_key
        self.demo_actions_key = demo_actions_key
        self.is_init_key = is_init_key
        self.hidden_key = hidden_key
        self.eta_key = eta_key
        self.memory_key = memory_key
        self.logits_key = logits_key
        self.features_key = features_key
        self.eta_used_key = eta_used_key
        self.memory_mask_key = memory_mask_key

        state_keys = [hidden_key, eta_key] + ([memory_key] if self.use_memory else [])
        self.in_keys = (
            [pixels_key]
            + ([demo_frames_key] if self.use_memory else [])
            + [demo_actions_key, is_init_key]
            + state_keys
        )
        self.out_keys = (
            [logits_key, features_key, eta_used_key]
            + ([memory_mask_key] if self.random_sparsity else [])
            + [("next", *((k,) if isinstance(k, str) else tuple(k))) for k in state_keys]
        )

    # ------------------------------------------------------------------ helpers
    @property
    def memory_length(self) -> int:
        """Number of slots in ``memory_features``: ``l`` (``n`` with ``sparsity_range``; 0 without memory)."""
        return self.memory_encoder.num_frames if self.use_memory else 0

    @property
    def sparsity(self) -> float:
        """Sparsity the memory is read at (``config.effective_sparsity`` unless :meth:`set_sparsity`)."""
        return self._sparsity

    def set_sparsity(self, sparsity: float) -> SPFPolicy:
        """Set the sparsity a random-sparsity policy reads its memory at in eval and step mode.

        Only for a policy built with ``config.sparsity_range`` (a fixed-sparsity policy's
        memory holds its ``l`` frames only). The mask takes effect at the next call,
        also mid-episode, since the memory holds all ``n`` frames. Training-mode
        sequence mode keeps drawing random sparsities. Not saved in the state dict.

        Args:
            sparsity (float): fraction of demo frames attended to, in ``(0, 1]``; it
                may lie outside ``config.sparsity_range``.

        Returns:
            SPFPolicy: ``self``.

        Raises:
            ValueError: ``sparsity`` is not in ``(0, 1]``.
            RuntimeError: the policy has no ``config.sparsity_range``.

        Examples:
            >>> cfg = SPFConfig(feature_dim=8, hidden_size=8, sparsity_range=(0.2, 1.0))
            >>> SPFPolicy(cfg).set_sparsity(0.6).sparsity
            0.6
        """
        sparsity = validate_sparsity(sparsity)
        if not self.random_sparsity:
            raise RuntimeError(
                f"set_sparsity needs a policy built with SPFConfig.sparsity_range (model "
                f"'spf_random'); this policy keeps a fixed memory of sparsity {self._sparsity}."
            )
        self._sparsity = sparsity
        return self

    def make_tensordict_primer(self) -> TensorDictPrimer:
        """Primer for the recurrent state keys (zeroed at every (partial) reset).

        Examples:
            >>> from spf_rl.modules import SPFConfig, SPFPolicy
            >>> primer = SPFPolicy(SPFConfig(feature_dim=8, hidden_size=8)).make_tensordict_primer()
            >>> sorted(primer.primers.keys())
            ['eta', 'memory_features', 'spf_hidden']
        """
        specs = {
            self.hidden_key: Unbounded(shape=(self.config.hidden_size,)),
            self.eta_key: Unbounded(shape=(1,)),
        }
        if self.use_memory:
            specs[self.memory_key] = Unbounded(shape=(self.memory_length, self.feature_dim))
        return TensorDictPrimer(specs, expand_specs=True)

    def update_pointer(self, eta: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Pointer update (eq. 4 or the RPF code's clipped version)."""
        if self.config.pointer_update == "paper":
            return eta + torch.tanh(b)
        return torch.clamp(eta + 1.0 + torch.tanh(b), max=float(self.config.demo_length - 1))

    def _check_demo_actions(self, demo_actions: torch.Tensor) -> None:
        n = self.config.demo_length
        if demo_actions.shape[-1] != n:
            raise ValueError(
                f"demo_actions has {demo_actions.shape[-1]} steps but SPFConfig.demo_length is "
                f"{n}: the demonstration must have exactly demo_length steps (a memory longer "
                f"than the demo is not allowed)."
            )
        if demo_actions.numel() and (
            int(demo_actions.min()) < 0 or int(demo_actions.max()) >= self.config.num_actions
        ):
            raise ValueError(
                f"demo_actions values must be in range(num_actions={self.config.num_actions}), "
                f"got min {int(demo_actions.min())}, max {int(demo_actions.max())}."
            )

    def _check_demo_frames(self, demo_frames: torch.Tensor, batch_dims: int) -> None:
        n = self.config.demo_length
        if demo_frames.ndim != batch_dims + 4 or demo_frames.shape[batch_dims] != n:
            raise ValueError(
                f"demo_frames must have shape [*batch, n={n}, H, W, 3] (n = SPFConfig.demo_length), "
                f"got {tuple(demo_frames.shape)} for {batch_dims} batch dim(s)."
            )
        check = getattr(self.encoder, "check_frames", None)
        if check is not None:
            check(demo_frames, "demo_frames")

    def _encode_pixels(self, pixels: torch.Tensor) -> torch.Tensor:
        check = getattr(self.encoder, "check_frames", None)
        if check is not None:
            check(pixels, "pixels")
        return self.encoder(pixels)

    def _encode_memory(
        self, demo_frames: torch.Tensor, mask: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Encode the memory of the rows where ``mask`` (batch-shaped) is true.

        Returns the features ``[K, l, D]`` and the flat row indices ``[K]``.
        """
        batch_index = mask.nonzero(as_tuple=True)
        feats = self.memory_encoder(demo_frames, batch_index)
        rows = mask.reshape(-1).nonzero().squeeze(-1)
        return feats, rows

    def _memory_masks(self, num_segments: int, device: torch.device, draw: bool) -> torch.Tensor:
        """``[K, n]`` memory masks of ``K`` segments: sparsities drawn from
        ``config.sparsity_range`` if ``draw``, else :attr:`sparsity` for all."""
        n = self.config.demo_length
        if not draw:
            return memory_mask(n, self._sparsity).to(device).repeat(num_segments, 1)
        low, high = self.config.sparsity_range
        draws = low + (high - low) * torch.rand(num_segments, dtype=torch.float64)
        masks = torch.zeros(num_segments, n, dtype=torch.bool)
        for row, sparsity in enumerate(draws.tolist()):
            masks[row] = memory_mask(n, sparsity)
        return masks.to(device)

    def _cell(
        self,
        phi: torch.Tensor,
        memory: torch.Tensor | None,
        demo_actions: torch.Tensor,
        eta: torch.Tensor,
        h: torch.Tensor,
        mask: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One step of eqs. 2-4 on flat ``[B, ...]`` tensors -> (logits, h_next, eta_next)."""
        indices = self.memory_encoder.indices if self.use_memory else None
        mu, window = self.attention(
            memory, indices, demo_actions, eta, return_window=True, mask=mask
        )
        x = torch.cat([mu, phi, window.flatten(-2)], -1)
        h_next = self.gru(x, h)
        logits = self.logits_head(h_next)
        b = self.pointer_head(h_next)
        return logits, h_next, self.update_pointer(eta, b)

    # ------------------------------------------------------------------ forward
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Run one step (step mode) or a ``[*B, T]`` sequence (recurrent mode)."""
        if recurrent_mode():
            return self._forward_sequence(tensordict)
        if tensordict.batch_dims == 0:
            out = self._forward_step(tensordict.unsqueeze(0))
            tensordict.update(out.squeeze(0))
            return tensordict
        return self._forward_step(tensordict)

    def _forward_step(self, td: TensorDictBase) -> TensorDictBase:
        cfg = self.config
        bs = td.batch_size
        nb = td.batch_dims
        pixels = td.get(self.pixels_key)
        phi = self._encode_pixels(pixels).reshape(-1, self.feature_dim)
        num_rows = phi.shape[0]
        demo_actions = td.get(self.demo_actions_key)
        self._check_demo_actions(demo_actions)
        demo_actions = demo_actions.reshape(num_rows, -1).long()
        is_init = td.get(self.is_init_key, None)
        if is_init is None:
            is_init = torch.zeros(bs, dtype=torch.bool, device=phi.device)
        else:
            is_init = is_init.reshape(bs)
        flat_init = is_init.reshape(num_rows, 1)

        h = _flat_or_zeros(td.get(self.hidden_key, None), (num_rows, cfg.hidden_size), phi)
        eta = _flat_or_zeros(td.get(self.eta_key, None), (num_rows, 1), phi)
        h = torch.where(flat_init, torch.zeros_like(h), h)
        eta = torch.where(flat_init, torch.zeros_like(eta), eta)

        memory = None
        if self.use_memory:
            stored = td.get(self.memory_key, None)
            shape = (num_rows, self.memory_length, self.feature_dim)
            if stored is None:
                fresh = torch.ones_like(is_init)
                memory = phi.new_zeros(shape)
            else:
                fresh = is_init
                memory = stored.reshape(shape).to(phi.dtype)
            if fresh.any():
                demo_frames = td.get(self.demo_frames_key)
                self._check_demo_frames(demo_frames, nb)
                feats, rows = self._encode_memory(demo_frames, fresh)
                memory = memory.index_copy(0, rows, feats.to(memory.dtype))

        mask = None
        if self.random_sparsity:  # step mode: always the evaluation sparsity
            mask = self._memory_masks(num_rows, phi.device, draw=False)
        logits, h_next, eta_next = self._cell(phi, memory, demo_actions, eta, h, mask)
        td.set(self.logits_key, logits.reshape(*bs, cfg.num_actions))
        if mask is not None:
            td.set(self.memory_mask_key, mask.reshape(*bs, cfg.demo_length))
        td.set(self.features_key, h_next.reshape(*bs, cfg.hidden_size))
        td.set(self.eta_used_key, eta.reshape(*bs, 1))
        td.set(("next", self.hidden_key), h_next.reshape(*bs, cfg.hidden_size))
        td.set(("next", self.eta_key), eta_next.reshape(*bs, 1))
        if self.use_memory:
            td.set(
                ("next", self.memory_key),
                memory.reshape(*bs, self.memory_length, self.feature_dim),
            )
        return td

    def _forward_sequence(self, tensordict: TensorDictBase) -> TensorDictBase:
        cfg = self.config
        if tensordict.batch_dims == 0:
            raise ValueError(
                "SPFPolicy in recurrent mode needs an input with a time dimension "
                "(batch shape [*B, T]); got a 0-d tensordict."
            )
        if tensordict.batch_dims == 1:
            td = tensordict.unsqueeze(0)
        elif tensordict.batch_dims == 2:
            td = tensordict
        else:
            td = tensordict.reshape(-1, tensordict.shape[-1])
        B, T = td.batch_size
        pixels = td.get(self.pixels_key)
        phi = self._encode_pixels(pixels).reshape(B, T, self.feature_dim)
        demo_actions = td.get(self.demo_actions_key)
        self._check_demo_actions(demo_actions)
        demo_actions = demo_actions.reshape(B, T, -1).long()
        is_init = td.get(self.is_init_key, None)
        if is_init is None:
            is_init = torch.zeros(B, T, dtype=torch.bool, device=phi.device)
        else:
            is_init = is_init.reshape(B, T)
        start = is_init.clone()
        start[:, 0] = True

        h0 = _flat_or_zeros(td.get(self.hidden_key, None), (B, T, cfg.hidden_size), phi)
        eta0 = _flat_or_zeros(td.get(self.eta_key, None), (B, T, 1), phi)

        memory = mask = None
        if self.use_memory:
            demo_frames = td.get(self.demo_frames_key)
            self._check_demo_frames(demo_frames, 2)
            feats, _ = self._encode_memory(demo_frames, start)  # [K, l, D]
            segment = start.reshape(-1).long().cumsum(0) - 1
            memory = feats.index_select(0, segment).reshape(
                B, T, self.memory_length, self.feature_dim
            )
            if self.random_sparsity:  # one mask per segment, [K, n] -> [B, T, n]
                masks = self._memory_masks(feats.shape[0], phi.device, draw=self.training)
                mask = masks.index_select(0, segment).reshape(B, T, cfg.demo_length)

        logits, features, eta_used, eta_next = [], [], [], []
        h = h0[:, 0]
        eta = eta0[:, 0]
        for t in range(T):
            s = start[:, t].unsqueeze(-1)
            h = torch.where(s, h0[:, t], h)
            eta = torch.where(s, eta0[:, t], eta)
            mem_t = memory[:, t] if memory is not None else None
            mask_t = mask[:, t] if mask is not None else None
            logit, h, eta_new = self._cell(phi[:, t], mem_t, demo_actions[:, t], eta, h, mask_t)
            logits.append(logit)
            features.append(h)
            eta_used.append(eta)
            eta_next.append(eta_new)
            eta = eta_new
        features_t = torch.stack(features, 1)
        out = {
            self.logits_key: torch.stack(logits, 1),
            self.features_key: features_t,
            self.eta_used_key: torch.stack(eta_used, 1),
            ("next", self.hidden_key): features_t,
            ("next", self.eta_key): torch.stack(eta_next, 1),
        }
        if memory is not None:
            out[("next", self.memory_key)] = memory
        if mask is not None:
            out[self.memory_mask_key] = mask
        shape = tensordict.batch_size
        for key, value in out.items():
            tensordict.set(key, value.reshape(*shape, *value.shape[2:]))
        return tensordict


# ---------------------------------------------------------------------- factories
def make_spf_policy(config: SPFConfig | None = None, encoder: nn.Module | None = None, **kwargs) -> SPFPolicy:
    """Build the SPF policy (sparse memory) from a config.

    Args:
        config (SPFConfig, optional): configuration. Defaults to ``SPFConfig()``.
        encoder (nn.Module, optional): image encoder phi. Defaults to :class:`ImageEncoder`.
        **kwargs: key overrides forwarded to :class:`SPFPolicy`.

    Examples:
        >>> policy = make_spf_policy(SPFConfig(feature_dim=8, hidden_size=8))
        >>> policy.memory_length
        12
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


class OpenLoopPolicy(TensorDictModuleBase):
    """Open-loop baseline: replays ``demo_actions[step]``, ignoring the observations.

    Keeps its own step counter in the recurrent state (reset to 0 where ``is_init``).
    After the demonstration ends it outputs ``action_after_demo``.

    Args:
        num_actions (int, optional): number of actions (3, or 4 with STOP). Defaults to 3.
        action_after_demo (int, optional): action once the demo is exhausted. Defaults
            to STOP (3) when ``num_actions == 4``, else turn left (1), which keeps the
            agent's position.

    Keyword Args:
        demo_actions_key, is_init_key, step_key, action_key, logits_key (NestedKey):
            keys. Defaults ``"demo_actions"``, ``"is_init"``, ``"open_loop_step"``
            (``[1]`` int64), ``"action"``, ``"logits"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> policy = OpenLoopPolicy()
        >>> td = TensorDict({"demo_actions": torch.tensor([[2, 0, 1]]),
        ...                  "is_init": torch.ones(1, 1, dtype=torch.bool)}, batch_size=[1])
        >>> policy(td)["action"].tolist(), td["next", "open_loop_step"].tolist()
        ([2], [[1]])
    """

    def __init__(
        self,
        num_actions: int = NUM_PAPER_ACTIONS,
        action_after_demo: int | None = None,
        *,
        demo_actions_key: NestedKey = "demo_actions",
        is_init_key: NestedKey = "is_init",
        step_key: NestedKey = "open_loop_step",
        action_key: NestedKey = "action",
        logits_key: NestedKey = "logits",
    ) -> None:
        super().__init__()
        if num_actions not in ALLOWED_NUM_ACTIONS:
            raise ValueError(
                f"num_actions must be one of {ALLOWED_NUM_ACTIONS}, got {num_actions!r}."
            )
        if action_after_demo is None:
            action_after_demo = STOP_ACTION if num_actions > NUM_PAPER_ACTIONS else TURN_LEFT_ACTION
        if not 0 <= action_after_demo < num_actions:
            raise ValueError(
                f"action_after_demo must be in range(num_actions={num_actions}), got {action_after_demo!r}."
            )
        self.num_actions = num_actions
        self.action_after_demo = action_after_demo
        self.demo_actions_key = demo_actions_key
        self.is_init_key = is_init_key
        self.step_key = step_key
        self.action_key = action_key
        self.logits_key = logits_key
        self.in_keys = [demo_actions_key, is_init_key, step_key]
        step_next = ("next", *((step_key,) if isinstance(step_key, str) else tuple(step_key)))
        self.out_keys = [action_key, logits_key, step_next]

    def make_tensordict_primer(self) -> TensorDictPrimer:
        """Primer for the step counter key (int64 ``[1]``, zeroed at reset)."""
        return TensorDictPrimer(
            {self.step_key: Unbounded(shape=(1,), dtype=torch.int64)}, expand_specs=True
        )

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Write the replayed action, one-hot-like logits and the next step counter."""
        demo_actions = tensordict.get(self.demo_actions_key).long()
        bs = demo_actions.shape[:-1]
        n = demo_actions.shape[-1]
        step = tensordict.get(self.step_key, None)
        step = (
            torch.zeros(*bs, 1, dtype=torch.long, device=demo_actions.device)
            if step is None
            else step.reshape(*bs, 1).long()
        )
        is_init = tensordict.get(self.is_init_key, None)
        if is_init is not None:
            step = torch.where(is_init.reshape(*bs, 1), torch.zeros_like(step), step)
        action = demo_actions.gather(-1, step.clamp(0, n - 1))
        action = torch.where(step >= n, torch.full_like(action, self.action_after_demo), action)
        action = action.squeeze(-1)
        logits = torch.full((*bs, self.num_actions), OPEN_LOOP_OFF_LOGIT, device=action.device)
        logits = logits.scatter(-1, action.unsqueeze(-1), 0.0)
        tensordict.set(self.action_key, action)
        tensordict.set(self.logits_key, logits)
        tensordict.set(self.out_keys[-1], step + 1)
        return tensordict


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
