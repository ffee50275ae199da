"""The SPF path-following policy (paper Sec. 3.2, eqs. 1-4) and its baselines, composed of TensorDict modules.

:class:`SPFPolicy` chains four parts, each a TensorDict module with documented keys
that a user can take out, replace or reuse:

* ``encoder``: :class:`~tensordict.nn.TensorDictModule` over an image encoder phi
  (``pixels`` -> ``pixel_features``; :class:`~spf_rl.modules.ImageEncoder` by default);
* ``memory``: :class:`~spf_rl.modules.SparseMemory` (``demo_frames`` at ``M*`` ->
  ``memory_features``, encoded once per episode and carried as recurrent state,
  plus ``memory_mask`` for random sparsity);
* ``attention``: :class:`~spf_rl.modules.MemoryAttention` (eq. 2: ``eta``,
  ``memory_features``, ``demo_actions`` -> ``mu``, ``action_window``, ``eta_used``);
* ``cell``: :class:`~spf_rl.modules.SPFCell` (eqs. 3-4: ``mu``, ``pixel_features``,
  ``action_window``, ``spf_hidden``, ``eta_used`` -> ``logits``, ``features``, next
  ``spf_hidden`` and ``eta``).

Step mode runs the four in order; sequence mode unrolls attention and cell together over time
(:meth:`SPFPolicy._forward_sequence`).
Baselines from the same parts (:mod:`spf_rl.modules.factories`): RPF as SPF at
sparsity 1, the RPF lab code's memory network, and action-only.
"""
from __future__ import annotations

import logging
from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.envs import TensorDictPrimer
from torchrl.modules.tensordict_module.rnn import recurrent_mode

from spf_rl.modules.anchor import PointerAnchor
from spf_rl.modules.attention import MemoryAttention, PointerAttention
from spf_rl.modules.cell import SPFCell
from spf_rl.modules.config import SPFConfig
from spf_rl.modules.encoder import ImageEncoder
from spf_rl.modules.replay_gate import UNMEASURED, carry_start
from spf_rl.modules.rpf import RPF_HEAD_HIDDEN, RPFAttention, SlotMLP
from spf_rl.modules.sparse_memory import SparseMemory
from spf_rl.modules.td_utils import DEMO_STEPS_KEY, demo_lengths, flat_or_zeros, init_flags, next_key, with_batch_dim

logger = logging.getLogger(__name__)

__all__ = ["SPFPolicy"]

class SPFPolicy(TensorDictModuleBase):
    """Sparse-memory path-following policy (SPF), a recurrent TensorDict module built from four parts.

    Reads the current frame, the demonstration, ``is_init`` and the recurrent state;
    writes action logits, the GRU output ``features`` (e.g. for a value head), the
    pointer used, the parts' intermediate keys (``pixel_features``, ``mu``,
    ``action_window``) and the next state under ``"next"``. The parts are
    :attr:`encoder`, :attr:`memory` (``None`` when action-only), :attr:`attention`, :attr:`cell`.

    **Step mode** (default): the input has batch shape ``[]`` or ``[*B]``. Where
    ``is_init`` is true, ``h`` and ``eta`` are reset to 0 and the memory frames are
    encoded from ``demo_frames``; elsewhere the stored state is used, and no memory
    frame is encoded. A missing state key counts as zeros (and a missing memory as
    "encode now").

    **Sequence mode**, inside ``torchrl.modules.set_recurrent_mode(True)``: the input
    is ``[*B, T]`` (time last). All frames are encoded in one call; the memory is
    encoded at ``t = 0`` and at every step where ``is_init`` is true; attention and
    GRU cell are unrolled over ``T``. As in :class:`~torchrl.modules.GRUModule`, a
    segment (``t = 0`` or ``is_init``) starts from the *stored* ``h`` and ``eta`` of
    that step: zeros at a real episode start (the primer zeroes them at reset), the
    carried state at a slice start that :class:`~torchrl.data.SliceSampler` marks
    with ``is_init``. The logits equal those of step mode on the same trajectory.
    Sequence mode always re-encodes the memory, so gradients reach the encoder
    through the memory too.

    **Random sparsity** (``config.sparsity_range``): see :class:`~spf_rl.modules.SparseMemory`.

    **Demonstrations of different lengths in one batch**: the optional input
    ``demo_steps`` (int64 ``[*B, 1]``) gives each demonstration's own number of steps
    ``n_i``, ``1 <= n_i <= n = config.demo_length``; ``demo_frames`` and
    ``demo_actions`` are padded after ``n_i`` (with anything: the padding is never
    read). Each row then runs as the network built for ``n_i`` steps
    (``spf_rl.modules.views.policy_for_length``) would on its unpadded demonstration:
    the memory holds that demonstration's memory (fixed sparsity: the frames at
    ``memory_indices(n_i, s)``, in the first slots; random sparsity: the mask
    ``memory_mask(n_i, s)``), no slot past ``n_i`` is attended, the action window
    and soft action memory end at ``n_i`` and the ``"rpf"`` pointer rule caps the
    pointer at ``n_i - 1``. In step and sequence mode alike. Without the key, or
    with every ``n_i = n``, every output is that of the fixed-length computation, bit
    for bit. An ``n_i`` outside ``[1, n]`` raises a ``ValueError`` before any work.

    Args:
        config (SPFConfig, optional): model configuration. Defaults to ``SPFConfig()``.
        encoder (nn.Module or TensorDictModule, optional): image encoder phi mapping
            ``[*, H, W, 3]`` frames to ``[*, D]``, shared by observations and memory
            frames. A :class:`~tensordict.nn.TensorDictModule` brings its own pixel and
            feature keys. ``D`` is read from ``feature_dim`` if the encoder has it, else
            ``config.feature_dim``. Defaults to :class:`ImageEncoder` built from the config.

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
        demo_steps_key (NestedKey, optional): optional input key of each demonstration's
            length ``n_i`` (``[1]`` int64); ``None``: never read (every demonstration is
            ``n`` long). Defaults to ``"demo_steps"`` (:data:`~spf_rl.modules.td_utils.DEMO_STEPS_KEY`).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from tensordict.nn import TensorDictModule, TensorDictSequential
        >>> from torch import nn
        >>> from spf_rl.modules import SPFConfig, SPFPolicy
        >>> cfg = SPFConfig(demo_length=6, sparsity=0.5, feature_dim=16, hidden_size=16, image_size=(16, 16))
        >>> policy = SPFPolicy(cfg)
        >>> def inputs():
        ...     return TensorDict({
        ...         "pixels": torch.randint(0, 256, (2, 16, 16, 3), dtype=torch.uint8),
        ...         "demo_frames": torch.randint(0, 256, (2, 6, 16, 16, 3), dtype=torch.uint8),
        ...         "demo_actions": torch.randint(0, 3, (2, 6)),
        ...         "is_init": torch.ones(2, 1, dtype=torch.bool)}, batch_size=[2])
        >>> out = policy(inputs())
        >>> out["logits"].shape, out["next", "memory_features"].shape
        (torch.Size([2, 3]), torch.Size([2, 3, 16]))
        >>> # 1. your own encoder in SPF: any module mapping [*, H, W, 3] frames to [*, D]
        >>> class TinyCNN(nn.Module):
        ...     feature_dim = 16
        ...     def __init__(self):
        ...         super().__init__()
        ...         self.net = nn.Sequential(nn.Conv2d(3, 8, 4, stride=4), nn.ReLU(), nn.Flatten(), nn.Linear(128, 16))
        ...     def forward(self, frames):
        ...         x = frames.reshape(-1, *frames.shape[-3:]).permute(0, 3, 1, 2).float() / 255
        ...         return self.net(x).reshape(*frames.shape[:-3], 16)
        >>> mine = SPFPolicy(cfg, TensorDictModule(TinyCNN(), in_keys=["pixels"], out_keys=["pixel_features"]))
        >>> mine(inputs())["logits"].shape
        torch.Size([2, 3])
        >>> # 2. SPF's memory and attention inside your own TensorDictSequential policy
        >>> head = TensorDictModule(nn.Linear(16, 3), in_keys=["mu"], out_keys=["logits"])
        >>> own = TensorDictSequential(policy.memory, policy.attention, head)
        >>> own(inputs())["logits"].shape
        torch.Size([2, 3])
        >>> # 3. a value head on the keys the policy declares (as PPO does)
        >>> policy.features_key in policy.out_keys
        True
        >>> value = TensorDictModule(nn.Linear(cfg.hidden_size, 1), in_keys=[policy.features_key], out_keys=["state_value"])
        >>> value(policy(inputs()))["state_value"].shape
        torch.Size([2, 1])
        >>> # 4. demonstrations of 4 and 6 steps in one batch (padded to demo_length = 6): the
        >>> # first row's logits are those of the same weights built for 4-step demonstrations
        >>> import dataclasses
        >>> td = inputs()
        >>> td["demo_steps"] = torch.tensor([[4], [6]])
        >>> four = SPFPolicy(dataclasses.replace(cfg, demo_length=4))
        >>> _ = four.load_state_dict(policy.state_dict())
        >>> alone = TensorDict({key: td[key][:1] for key in ("pixels", "is_init")}, batch_size=[1])
        >>> alone["demo_frames"], alone["demo_actions"] = td["demo_frames"][:1, :4], td["demo_actions"][:1, :4]
        >>> torch.allclose(policy(td)["logits"][:1], four(alone)["logits"], atol=1e-6)
        True
    """

    def __init__(
        self,
        config: SPFConfig | None = None,
        encoder: nn.Module | TensorDictModule | None = None,
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
        demo_steps_key: NestedKey | None = DEMO_STEPS_KEY,
    ) -> None:
        super().__init__()
        config = SPFConfig() if config is None else config
        if not isinstance(config, SPFConfig):
            raise TypeError(f"config must be an SPFConfig, got {type(config).__name__}.")
        self.config = config
        if isinstance(encoder, TensorDictModule):
            pixels_key, pixel_features_key = encoder.in_keys[0], encoder.out_keys[0]
            phi = encoder.module
        else:
            phi = ImageEncoder(config.feature_dim, config.image_size, normalize=config.normalize_frames) if encoder is None else encoder
            pixel_features_key = "pixel_features"
            encoder = TensorDictModule(phi, in_keys=[pixels_key], out_keys=[pixel_features_key])
        self.feature_dim = int(getattr(phi, "feature_dim", config.feature_dim))
        self.use_memory = config.memory_mode != "none"
        self.random_sparsity = config.sparsity_range is not None
        self.encoder = encoder
        mu_dim = config.mu_dim or config.feature_dim
        lab_rpf = config.architecture == "rpf_original"
        self.memory = (
            SparseMemory(
                phi,
                config.demo_length,
                config.effective_sparsity,
                config.sparsity_range,
                feature_dim=self.feature_dim,
                slot_mlp=SlotMLP(self.feature_dim, config.num_actions, mu_dim) if lab_rpf else None,
                demo_actions_key=demo_actions_key,
                demo_frames_key=demo_frames_key,
                is_init_key=is_init_key,
                memory_key=memory_key,
                memory_mask_key=memory_mask_key,
                demo_steps_key=demo_steps_key,
            )
            if self.use_memory
            else None
        )
        if lab_rpf:
            pointer_attention: nn.Module = RPFAttention(mu_dim, config.num_actions)
        else:
            pointer_attention = PointerAttention(
                self.feature_dim,
                mu_dim,
                k=config.k,
                num_action_classes=config.num_actions,
                action_only=not self.use_memory,
                soft_action_memory=config.use_soft_action_memory,
            )
        self.attention = MemoryAttention(
            pointer_attention,
            self.memory.indices if self.use_memory else None,
            sparsity=config.effective_sparsity if self.use_memory and not self.random_sparsity else None,
            eta_key=eta_key,
            is_init_key=is_init_key,
            memory_key=memory_key,
            memory_mask_key=memory_mask_key if self.random_sparsity else None,
            demo_actions_key=demo_actions_key,
            eta_used_key=eta_used_key,
            demo_steps_key=demo_steps_key,
            anchor=None if config.anchor_radius is None else PointerAnchor(self.feature_dim, config.anchor_radius),
            pixel_features_key=pixel_features_key,
            start_check=config.start_check is not None,
        )
        self.cell = SPFCell(
            (mu_dim, self.feature_dim, pointer_attention.window_dim),
            config.hidden_size,
            config.num_actions,
            config.demo_length,
            config.pointer_update,
            config.initial_pointer_step,
            RPF_HEAD_HIDDEN if lab_rpf else None,
            config.anchor_radius,
            config.replay_gate,
            config.start_check,
            pixel_features_key=pixel_features_key,
            eta_used_key=eta_used_key,
            is_init_key=is_init_key,
            hidden_key=hidden_key,
            eta_key=eta_key,
            logits_key=logits_key,
            features_key=features_key,
            demo_steps_key=demo_steps_key,
        )
        self.pixels_key, self.demo_frames_key, self.demo_actions_key = pixels_key, demo_frames_key, demo_actions_key
        self.is_init_key, self.hidden_key, self.eta_key, self.memory_key = is_init_key, hidden_key, eta_key, memory_key
        self.logits_key, self.features_key, self.eta_used_key = logits_key, features_key, eta_used_key
        self.memory_mask_key, self.demo_steps_key = memory_mask_key, demo_steps_key
        state_keys = [hidden_key, eta_key] + ([memory_key] if self.use_memory else []) + (
            [self.cell.start_match_key] if self.start_checks else []
        )
        self.in_keys = (
            [pixels_key]
            + ([demo_frames_key] if self.use_memory else [])
            + [demo_actions_key, is_init_key]
            + ([demo_steps_key] if demo_steps_key is not None else [])
            + state_keys
        )
        self.out_keys = (
            [logits_key, features_key, eta_used_key]
            + ([memory_mask_key] if self.random_sparsity else [])
            + [pixel_features_key, self.attention.mu_key, self.attention.action_window_key]
            + ([self.attention.anchor_key, self.attention.anchor_confidence_key] if self.anchors else [])
            + ([self.attention.start_cosine_key] if self.start_checks else [])
            + [next_key(key) for key in state_keys]
        )

    # ------------------------------------------------------------------ helpers
    @property
    def anchors(self) -> bool:
        """Whether the pointer is re-anchored on the frame (``config.anchor_radius``, :mod:`spf_rl.modules.anchor`)."""
        return self.attention.anchor is not None

    @property
    def start_checks(self) -> bool:
        """Whether the route's start is checked against the memory (``config.start_check``,
        :mod:`spf_rl.modules.replay_gate`)."""
        return self.config.start_check is not None

    @property
    def memory_length(self) -> int:
        """Number of slots in ``memory_features``: ``l`` (``n`` with ``sparsity_range``; 0 without memory)."""
        return self.memory.num_slots if self.use_memory else 0

    @property
    def sparsity(self) -> float:
        """Sparsity the memory is read at (``config.effective_sparsity`` unless :meth:`set_sparsity`)."""
        return self.memory.sparsity if self.use_memory else 0.0

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
        if not self.use_memory:
            raise RuntimeError("set_sparsity needs a policy with visual memory; this one is action-only.")
        self.memory.set_sparsity(sparsity)
        return self

    def make_tensordict_primer(self) -> TensorDictPrimer:
        """Primer for the recurrent state keys (zeroed at every (partial) reset).

        Examples:
            >>> from spf_rl.modules import SPFConfig, SPFPolicy
            >>> primer = SPFPolicy(SPFConfig(feature_dim=8, hidden_size=8)).make_tensordict_primer()
            >>> sorted(primer.primers.keys())
            ['eta', 'memory_features', 'spf_hidden']
        """
        specs = dict(self.cell.make_tensordict_primer().primers.items())
        if self.use_memory:
            specs.update(self.memory.make_tensordict_primer().primers.items())
        if not self.start_checks:
            return TensorDictPrimer(specs, expand_specs=True)
        defaults = {key: 0.0 for key in specs} | dict(self.cell.state_defaults())  # start_match: UNMEASURED
        return TensorDictPrimer(specs, expand_specs=True, default_value=defaults)

    def update_pointer(self, eta: torch.Tensor, b: torch.Tensor, lengths: torch.Tensor | None = None) -> torch.Tensor:
        """Pointer update (eq. 4 or the RPF code's clipped version; ``lengths``: each row's demonstration length)."""
        return self.cell.update_pointer(eta, b, lengths)

    def check_inputs(self, td: TensorDictBase, new_episodes_only: bool = False) -> None:
        """Raise a ``ValueError`` for demo lengths, demo actions or pixels that do not fit the config.

        With ``new_episodes_only`` (step mode), the action values are checked in the rows
        where ``is_init`` is true only: a demonstration does not change within an episode.
        With ``demo_steps``, only each demonstration's own ``n_i`` actions are checked (the
        padding may hold anything).
        """
        n, demo_actions = self.config.demo_length, td.get(self.demo_actions_key)
        if demo_actions.shape[-1] != n:
            raise ValueError(
                f"demo_actions has {demo_actions.shape[-1]} steps but SPFConfig.demo_length is "
                f"{n}: the demonstration must have exactly demo_length steps (a shorter one padded "
                f"to demo_length, its own length in demo_steps; a memory longer than the demo is "
                f"not allowed)."
            )
        lengths = demo_lengths(td, self.demo_steps_key, n, td.batch_size)
        is_init = td.get(self.is_init_key, None) if new_episodes_only else None
        rows = None if is_init is None else is_init.reshape(td.batch_size)
        values = demo_actions if rows is None else demo_actions[rows]
        if lengths is not None:
            steps = (lengths if rows is None else lengths[rows]).to(values.device)
            values = values[torch.arange(n, device=values.device) < steps]
        if values.numel():
            low, high = (int(v) for v in torch.aminmax(values))
            if low < 0 or high >= self.config.num_actions:
                raise ValueError(
                    f"demo_actions values must be in range(num_actions={self.config.num_actions}), got min {low}, max {high}."
                )
        check = getattr(self.encoder.module, "check_frames", None)
        if check is not None:
            check(td.get(self.pixels_key), "pixels")

    # ------------------------------------------------------------------ forward
    def forward(self, tensordict: TensorDictBase, valid: torch.Tensor | None = None) -> TensorDictBase:
        """Run one step (step mode) or a ``[*B, T]`` sequence (recurrent mode).

        ``valid`` (recurrent mode only; ``[*B, T]`` bool): encode only these steps'
        frames, for sequences padded after their episodes' ends (see
        :meth:`_forward_sequence`).
        """
        if recurrent_mode():
            return self._forward_sequence(tensordict, valid)
        if valid is not None:
            raise ValueError("valid applies to recurrent (sequence) mode only; step mode encodes every row.")
        return with_batch_dim(self._forward_step, tensordict)

    def encode_pixels(self, td: TensorDictBase, valid: torch.Tensor | None = None) -> None:
        """Write the encoder's features (the module called on the tensor: no TensorDictModule overhead);
        with ``valid`` (bool of ``td``'s batch shape), only those rows are encoded, the others are zeros."""
        pixels = td.get(self.encoder.in_keys[0])
        if valid is None:
            td.set(self.encoder.out_keys[0], self.encoder.module(pixels))
            return
        if valid.shape != td.batch_size:
            raise ValueError(f"valid must have the batch shape {tuple(td.batch_size)}, got {tuple(valid.shape)}.")
        valid = valid.to(device=pixels.device, dtype=torch.bool)
        if td.batch_dims and (valid[..., 1:] & ~valid[..., :-1]).any():
            raise ValueError("valid must be a prefix along time (padding after each episode's last step only).")
        encoded = self.encoder.module(pixels[valid])
        features = encoded.new_zeros(*valid.shape, encoded.shape[-1])
        features[valid] = encoded
        td.set(self.encoder.out_keys[0], features)

    def _forward_sequence(self, tensordict: TensorDictBase, valid: torch.Tensor | None = None) -> TensorDictBase:
        """Sequence mode: attention and GRU cell unrolled together over time.

        The attention at step ``t`` reads the pointer the cell wrote at step ``t - 1``,
        so the two cannot run over all steps one after the other; frames and memories
        are encoded for every step at once, then the loop runs on tensors (no
        TensorDict work per step).

        Runs the policy over a ``[*B, T]`` sequence (time last), writing its outputs for every step.

        A segment (``t = 0`` or ``is_init``) starts from the stored ``h`` and ``eta`` of
        that step, as in :class:`~torchrl.modules.GRUModule` (and, with a start check, the stored
        ``start_match``: unmeasured where ``is_init`` or where the input has none).

        ``valid`` (``[*B, T]`` bool, e.g. a training batch's ``mask``): only these steps'
        frames are encoded; the others get zero features. For padding *after* an
        episode's last step: every output is causal, so the valid steps' outputs are
        those of the full sequence, and the padded steps' outputs are meaningless.

        ``demo_steps`` (``[*B, T, 1]``, optional) is read at every step, as the demo actions
        are; a segment's memory is that of the demonstration length at its first step.
        """
        if tensordict.batch_dims == 0:
            raise ValueError(
                "SPFPolicy in recurrent mode needs an input with a time dimension "
                "(batch shape [*B, T]); got a 0-d tensordict."
            )
        self.check_inputs(tensordict)
        self.encode_pixels(tensordict, valid)
        segments = self.memory.encode_segments(tensordict) if self.use_memory else None
        td = tensordict.reshape(-1, tensordict.shape[-1])
        rows, steps = td.batch_size
        # per-step views by unbind and per-segment gathers: their backward passes stack and
        # index-add small tensors, where t-slices of [B, T, ...] tensors would each
        # accumulate a zero-filled gradient of the whole sequence
        phi = td.get(self.encoder.out_keys[0]).reshape(rows, steps, -1).unbind(1)
        demo_actions = td.get(self.demo_actions_key).reshape(rows, steps, -1).long().unbind(1)
        lengths = demo_lengths(td, self.demo_steps_key, self.config.demo_length, td.batch_size)
        step_lengths = [None] * steps if lengths is None else lengths.to(phi[0].device).unbind(1)
        is_init = init_flags(td, self.is_init_key, phi[0].device)
        start = is_init.clone()
        start[:, 0] = True
        h0 = flat_or_zeros(td.get(self.hidden_key, None), (rows, steps, self.config.hidden_size), phi[0])
        eta0 = flat_or_zeros(td.get(self.eta_key, None), (rows, steps, 1), phi[0])
        match0 = None
        if self.start_checks:
            stored = td.get(self.cell.start_match_key, None)
            unmeasured = torch.full((rows, steps, 1), UNMEASURED, dtype=phi[0].dtype, device=phi[0].device)
            match0 = unmeasured if stored is None else torch.where(is_init.unsqueeze(-1), unmeasured, stored.reshape(rows, steps, 1).to(phi[0].dtype))
        stacked = self._unroll(phi, demo_actions, step_lengths, start, h0, eta0, segments, match0)
        out = {
            self.logits_key: stacked["logits"],
            self.features_key: stacked["h"],
            self.eta_used_key: stacked["eta_used"],
            self.attention.mu_key: stacked["mu"],
            self.attention.action_window_key: stacked["window"],
            **({self.attention.anchor_key: stacked["anchor"], self.attention.anchor_confidence_key: stacked["anchor_confidence"]}
               if self.anchors else {}),
            **({self.attention.start_cosine_key: stacked["start_cosine"], next_key(self.cell.start_match_key): stacked["start_match"]}
               if self.start_checks else {}),
            next_key(self.hidden_key): stacked["h"],
            next_key(self.eta_key): stacked["eta_next"],
        }
        shape = tensordict.batch_size
        for key, value in out.items():
            tensordict.set(key, value.reshape(*shape, *value.shape[2:]))
        if segments is not None:
            self.memory.write_segments(tensordict, *segments)
        return tensordict

    def _unroll(
        self,
        phi: Sequence[torch.Tensor],
        demo_actions: Sequence[torch.Tensor],
        step_lengths: Sequence[torch.Tensor | None],
        start: torch.Tensor,
        h0: torch.Tensor,
        eta0: torch.Tensor,
        segments: tuple[torch.Tensor, torch.Tensor, torch.Tensor | None] | None,
        match0: torch.Tensor | None = None,
    ) -> dict[str, torch.Tensor]:
        """The attention and the cell unrolled over the steps, on tensors: per-step
        ``phi``, ``demo_actions`` and ``step_lengths`` of ``[rows]`` leading shape, ``start``
        ``[rows, T]`` segment starts, ``h0`` / ``eta0`` (/ ``match0``, with a start check)
        ``[rows, T, *]`` the states a segment starts from; returns each output stacked to ``[rows, T, *]``."""
        h, eta = h0[:, 0], eta0[:, 0]
        match = None if match0 is None else match0[:, 0]
        names = ("logits", "h", "eta_used", "eta_next", "mu", "window") + (("anchor", "anchor_confidence") if self.anchors else ()) + (
            ("start_cosine", "start_match") if self.start_checks else ()
        )
        outputs: dict[str, list[torch.Tensor]] = {name: [] for name in names}
        for t in range(len(phi)):
            segment_start = start[:, t].unsqueeze(-1)
            h = torch.where(segment_start, h0[:, t], h)
            eta = torch.where(segment_start, eta0[:, t], eta)
            if match is not None:
                match = torch.where(segment_start, match0[:, t], match)
            memory = mask = None
            if segments is not None:
                feats, segment, masks = segments
                memory = feats.index_select(0, segment[:, t])
                mask = masks.index_select(0, segment[:, t]) if masks is not None else None
            mu, window = self.attention.attend(memory, demo_actions[t], eta, mask, step_lengths[t])
            anchor = (
                self.attention.locate(memory, phi[t], eta, demo_actions[t].shape[-1], mask, step_lengths[t]) if self.anchors else ()
            )
            checked = ()
            if match is not None:
                cosine = self.attention.start_cosine(memory, phi[t], demo_actions[t].shape[-1], mask, step_lengths[t])
                match = carry_start(match, cosine)
                checked = (cosine, match)
            logits, h, eta_next = self.cell.step(mu, phi[t], window, eta, h, step_lengths[t], *(anchor or (None, None)),
                                                 None if match is None else match)
            for name, value in zip(outputs, (logits, h, eta, eta_next, mu, window, *anchor, *checked)):
                outputs[name].append(value)
            eta = eta_next
        return {name: torch.stack(values, 1) for name, values in outputs.items()}

    def _forward_step(self, td: TensorDictBase) -> TensorDictBase:
        # the parts' step forwards, called directly: the batch dim is already there
        self.check_inputs(td, new_episodes_only=True)
        self.encode_pixels(td)
        if self.use_memory:
            self.memory._forward_step(td)
        self.attention._forward_step(td)
        return self.cell._forward_step(td)
