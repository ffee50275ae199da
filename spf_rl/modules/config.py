"""Configuration of the SPF policy and its baselines: :class:`SPFConfig` and the model's named constants."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Literal

import torch

from spf_rl.modules.memory import memory_indices, memory_length, validate_sparsity, validate_sparsity_range

__all__ = ["SPFConfig"]

#: Paper action set: 0 forward, 1 turn left, 2 turn right.
NUM_PAPER_ACTIONS = 3
#: Action index of the optional STOP action.
STOP_ACTION = 3
#: Action index of "turn left" (a move that keeps the agent's position).
TURN_LEFT_ACTION = 1
ALLOWED_NUM_ACTIONS = (NUM_PAPER_ACTIONS, NUM_PAPER_ACTIONS + 1)
#: Demonstration length n of the paper (Sec. 4.1).
DEFAULT_DEMO_LENGTH = 30
#: Default memory sparsity: the paper's headline model, SPF 0.8.
DEFAULT_SPARSITY = 0.8
#: Default untrained pointer increment tanh(b): the pointer starts moving about one demo index per step.
DEFAULT_INITIAL_POINTER_STEP = 0.9
POINTER_UPDATES = ("paper", "rpf")
MEMORY_MODES = ("sparse", "full", "none")
#: Memory networks: SPF's (psi over attended features + action window) or the RPF lab code's.
ARCHITECTURES = ("spf", "rpf_original")
#: Fields of :class:`SPFConfig` added after models were shipped: kept in its dict only when not at their default.
OPTIONAL_FIELDS = ("anchor_radius", "normalize_frames", "replay_gate", "start_check")
#: Sparsity used by the full-memory (RPF) baseline.
FULL_MEMORY_SPARSITY = 1.0


@dataclass
class SPFConfig:
    """Configuration of :class:`SPFPolicy`.

    Args:
        num_actions (int): number of policy actions, 3 (forward, left, right) or 4
            (with STOP = 3). Also the one-hot size of the demo actions in the window.
        demo_length (int): demonstration length ``n`` (frames and actions).
        sparsity (float): fraction of demo frames kept in memory, in ``(0, 1]``; 0.8 by default
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
            0.9 (default) starts the pointer moving along the demonstration about one
            index per step, as the RPF code's rule does; 0 is PyTorch's usual
            initialisation. The paper does not say how b is initialised.
        sparsity_range (tuple of float, optional): ``(low, high)`` with
            ``0 < low <= high <= 1``: train one model for many sparsities (needs
            ``memory_mode="sparse"``). The memory then holds a slot for each of the
            ``n`` demo frames and attends only to the slots at
            ``memory_indices(n, s)``: in training mode, sequence mode draws
            ``s ~ Uniform(low, high)`` per episode segment; otherwise ``s`` is
            :attr:`SPFPolicy.sparsity`. Not in the SPF paper. Defaults to ``None``
            (one fixed sparsity, ``l`` memory slots).
        architecture (str): ``"spf"`` (default) or ``"rpf_original"``, the RPF lab
            code's memory network (:mod:`spf_rl.modules.rpf`; needs full memory and
            the ``"rpf"`` pointer rule). ``mu_dim`` is then the memory-slot size.
        anchor_radius (int, optional): re-anchor the pointer on the memory slot the current
            frame matches within this many route steps of it (:mod:`spf_rl.modules.anchor`:
            the pointer may then go back); ``None`` (default): no anchor, as the paper. Needs
            visual memory and SPF's architecture. Not in the SPF paper.
        normalize_frames (bool): standardise every frame per channel before the encoder
            (:func:`~spf_rl.modules.encoder.normalize_frames`), the current one and the memory's:
            a change of exposure or light colour then does not reach the features. ``False``
            (default): raw frames, as the paper. Not in the SPF paper.
        replay_gate (bool): a learned gate on the anchor's confidence moves the action distribution
            and the pointer toward blind replay of the demonstrated actions
            (:mod:`spf_rl.modules.replay_gate`), where the memory disagrees with the view. Needs
            ``anchor_radius``. ``False`` (default): no gate. Not in the SPF paper.
        start_check (float, optional): replay the demonstrated actions for the whole episode when
            the cosine of the encoder's features of the first frame the agent sees and of the
            memory's first frame is below this threshold, in ``(-1, 1)``
            (:mod:`spf_rl.modules.replay_gate`: another route's frames). Not learned: set on a
            trained model by ``recipes/start_check.py``. Needs visual memory and SPF's
            architecture. ``None`` (default): no check. Not in the SPF paper.

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
    initial_pointer_step: float = DEFAULT_INITIAL_POINTER_STEP
    sparsity_range: tuple[float, float] | None = None
    architecture: Literal["spf", "rpf_original"] = "spf"
    anchor_radius: int | None = None
    normalize_frames: bool = False
    replay_gate: bool = False
    start_check: float | None = None

    def __post_init__(self) -> None:
        if self.architecture not in ARCHITECTURES:
            raise ValueError(f"architecture must be one of {ARCHITECTURES}, got {self.architecture!r}.")
        if self.architecture == "rpf_original" and (
            self.memory_mode != "full" or self.pointer_update != "rpf" or self.sparsity_range is not None
        ):
            raise ValueError(
                "architecture='rpf_original' needs memory_mode='full', pointer_update='rpf' and no sparsity_range "
                f"(got {self.memory_mode!r}, {self.pointer_update!r}, {self.sparsity_range!r}); "
                "use spf_rl.modules.make_rpf_original_policy."
            )
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
        if self.anchor_radius is not None and (
            isinstance(self.anchor_radius, bool) or not isinstance(self.anchor_radius, int) or self.anchor_radius < 1
        ):
            raise ValueError(f"anchor_radius must be a positive int (route steps) or None, got {self.anchor_radius!r}.")
        if self.anchor_radius is not None and (self.memory_mode == "none" or self.architecture != "spf"):
            raise ValueError(
                f"anchor_radius needs visual memory and architecture='spf' (got memory_mode={self.memory_mode!r}, "
                f"architecture={self.architecture!r}); set anchor_radius=None."
            )
        if not isinstance(self.normalize_frames, bool):
            raise ValueError(f"normalize_frames must be True or False, got {self.normalize_frames!r}.")
        if not isinstance(self.replay_gate, bool):
            raise ValueError(f"replay_gate must be True or False, got {self.replay_gate!r}.")
        if self.replay_gate and self.anchor_radius is None:
            raise ValueError("replay_gate needs anchor_radius (the gate reads the anchor's confidence); set anchor_radius or replay_gate=False.")
        if self.start_check is not None:
            if isinstance(self.start_check, bool) or not isinstance(self.start_check, (int, float)) or not -1.0 < self.start_check < 1.0:
                raise ValueError(f"start_check must be a cosine threshold in (-1, 1) or None, got {self.start_check!r}.")
            if self.memory_mode == "none" or self.architecture != "spf":
                raise ValueError(
                    f"start_check needs visual memory and architecture='spf' (got memory_mode={self.memory_mode!r}, "
                    f"architecture={self.architecture!r}); set start_check=None."
                )
            self.start_check = float(self.start_check)
        self.image_size = tuple(self.image_size)  # type: ignore[assignment]
        if len(self.image_size) != 2 or any(
            not isinstance(s, int) or s < 1 for s in self.image_size
        ):
            raise ValueError(
                f"image_size must be (height, width) in pixels, got {self.image_size!r}."
            )

    def to_dict(self) -> dict:
        """The fields as a dict, as checkpoints, exports and the result cache keep them: the fields of
        :data:`OPTIONAL_FIELDS` only when not at their default, so a model without them keeps the
        identity it had before they existed.

        Examples:
            >>> "anchor_radius" in SPFConfig().to_dict(), SPFConfig(anchor_radius=8).to_dict()["anchor_radius"]
            (False, 8)
            >>> "normalize_frames" in SPFConfig().to_dict(), SPFConfig(normalize_frames=True).to_dict()["normalize_frames"]
            (False, True)
        """
        defaults = {f.name: f.default for f in fields(self)}
        return {key: value for key, value in asdict(self).items() if not (key in OPTIONAL_FIELDS and value == defaults[key])}

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
