"""The recurrent cell of the SPF policy (paper eqs. 3-4) as a TensorDict module.

``h_{t+1}, b, logits = pi(h_t, mu_t, phi(o_t), a_window)`` with ``pi`` a GRU cell,
then the pointer update ``eta_{t+1} = eta_t + tanh(b)`` (the paper) or
``min(eta_t + 1 + tanh(b), n - 1)`` (the RPF authors' code; ``n_i - 1`` for a
demonstration of ``n_i`` steps padded to ``n``, the optional ``demo_steps`` input).

Why not torchrl's :class:`~torchrl.modules.GRUModule`: in sequence mode it runs
``nn.GRU`` over inputs known for every step in advance. Here the GRU input at
step ``t`` holds ``mu_t``, which the attention computes from the pointer that the
cell itself produced at step ``t - 1``, so the attention and the cell must be
unrolled together, one step at a time (:class:`~spf_rl.modules.SPFPolicy` does).
A ``GRUCell`` serves both modes with one set of weights.
"""
from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import Unbounded
from torchrl.envs import TensorDictPrimer

from spf_rl.modules.anchor import anchor_gate, reanchor
from spf_rl.modules.config import POINTER_UPDATES
from spf_rl.modules.replay_gate import UNMEASURED, carry_start, fall_back, replay_gate_layer, replay_opening
from spf_rl.modules.td_utils import (
    ANCHOR_CONFIDENCE_KEY,
    ANCHOR_KEY,
    DEMO_STEPS_KEY,
    START_COSINE_KEY,
    START_MATCH_KEY,
    demo_lengths,
    flat_or_zeros,
    init_flags,
    next_key,
    with_batch_dim,
)

__all__ = ["SPFCell"]


class SPFCell(TensorDictModuleBase):
    """GRU cell, action logits and pointer update of SPF, reading and writing TensorDict keys.

    Reads ``mu``, ``pixel_features``, ``action_window``, the pointer ``eta_used``
    and the hidden state ``spf_hidden`` (reset to 0 where ``is_init``; a missing key
    counts as 0); writes ``logits``, ``features`` (the new hidden state, e.g. for a
    value head) and the next ``spf_hidden`` and ``eta`` under ``"next"``.

    Args:
        input_dims (tuple of int): sizes of ``mu``, ``pixel_features`` and the
            flattened ``action_window``.
        hidden_size (int): GRU hidden size.
        num_actions (int): number of action logits.
        demo_length (int): demonstration length ``n`` (bounds the RPF pointer rule).
        pointer_update (str): ``"paper"`` or ``"rpf"``.
        initial_pointer_step (float): ``tanh(b)`` of the untrained network, in ``(-1, 1)``.
        head_hidden (int, optional): hidden units of 2-layer action and pointer heads (the
            RPF lab code's); ``None`` (default): linear heads.
        anchor_radius (float, optional): re-anchor the next pointer on the anchor the attention
            found (:func:`~spf_rl.modules.anchor.reanchor`, a learned gate), reading ``anchor``
            and ``anchor_confidence``; ``None`` (default): the rule alone.
        replay_gate (bool): move the action distribution and the pointer toward blind replay of the
            demonstrated actions by a learned gate on the anchor's confidence
            (:mod:`spf_rl.modules.replay_gate`; needs ``anchor_radius``). ``False`` (default): no gate.
        start_check (float, optional): replay the demonstrated actions for the episode where the
            first frame's cosine with the memory's first frame (``start_cosine``, written by the
            attention) is below this threshold (:mod:`spf_rl.modules.replay_gate`); the first step's
            cosine is carried as recurrent state ``start_match``. ``None`` (default): no check.

    Keyword Args:
        mu_key, pixel_features_key, action_window_key, eta_used_key, is_init_key (NestedKey): inputs.
        demo_steps_key (NestedKey, optional): optional input, each demonstration's length
            ``n_i`` (int64 ``[1]``, padded to ``demo_length``): the ``"rpf"`` rule caps the
            pointer at ``n_i - 1``. ``None``: never read. Defaults ``"demo_steps"``.
        hidden_key, eta_key (NestedKey): recurrent state. Defaults ``"spf_hidden"``, ``"eta"``.
        start_cosine_key, start_match_key (NestedKey): the start check's input and recurrent state.
            Defaults ``"start_cosine"``, ``"start_match"``.
        logits_key, features_key (NestedKey): outputs. Defaults ``"logits"``, ``"features"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from spf_rl.modules import SPFCell
        >>> cell = SPFCell((16, 8, 15), hidden_size=32, num_actions=3, demo_length=10)
        >>> td = TensorDict({"mu": torch.randn(2, 16), "pixel_features": torch.randn(2, 8),
        ...                  "action_window": torch.zeros(2, 5, 3), "eta_used": torch.zeros(2, 1)}, [2])
        >>> cell(td)["logits"].shape, td["next", "eta"].shape
        (torch.Size([2, 3]), torch.Size([2, 1]))
        >>> sorted(cell.make_tensordict_primer().primers.keys())
        ['eta', 'spf_hidden']
        >>> checked = SPFCell((16, 8, 15), hidden_size=32, num_actions=3, demo_length=10, start_check=0.5)
        >>> td["action_window"] = torch.nn.functional.one_hot(torch.tensor([[0, 0, 2, 0, 0]] * 2), 3).float()  # shown: 2
        >>> td["start_cosine"] = torch.tensor([[0.1], [0.9]])  # the first frame: another route's, the route's own
        >>> out = checked(td)
        >>> out["next", "start_match"].flatten().tolist(), round(out["logits"][0].exp()[2].item(), 3)  # row 0 replays
        ([0.10000000149011612, 0.8999999761581421], 1.0)
        >>> rpf = SPFCell((16, 8, 15), hidden_size=32, num_actions=3, demo_length=10, pointer_update="rpf")
        >>> rpf.update_pointer(torch.tensor([[3.5], [3.5]]), torch.full((2, 1), 10.0), torch.tensor([[4], [10]])).tolist()
        [[3.0], [5.5]]
    """

    def __init__(
        self,
        input_dims: tuple[int, int, int],
        hidden_size: int,
        num_actions: int,
        demo_length: int,
        pointer_update: str = "paper",
        initial_pointer_step: float = 0.0,
        head_hidden: int | None = None,
        anchor_radius: float | None = None,
        replay_gate: bool = False,
        start_check: float | None = None,
        *,
        mu_key: NestedKey = "mu",
        pixel_features_key: NestedKey = "pixel_features",
        action_window_key: NestedKey = "action_window",
        eta_used_key: NestedKey = "eta_used",
        is_init_key: NestedKey = "is_init",
        hidden_key: NestedKey = "spf_hidden",
        eta_key: NestedKey = "eta",
        logits_key: NestedKey = "logits",
        features_key: NestedKey = "features",
        demo_steps_key: NestedKey | None = DEMO_STEPS_KEY,
        anchor_key: NestedKey = ANCHOR_KEY,
        anchor_confidence_key: NestedKey = ANCHOR_CONFIDENCE_KEY,
        start_cosine_key: NestedKey = START_COSINE_KEY,
        start_match_key: NestedKey = START_MATCH_KEY,
    ) -> None:
        super().__init__()
        if pointer_update not in POINTER_UPDATES:
            raise ValueError(f"pointer_update must be one of {POINTER_UPDATES}, got {pointer_update!r}.")
        self.hidden_size, self.num_actions, self.demo_length = hidden_size, num_actions, demo_length
        if replay_gate and anchor_radius is None:
            raise ValueError("replay_gate needs anchor_radius: the gate reads the anchor's confidence.")
        self.pointer_update = pointer_update
        self.gru = nn.GRUCell(sum(input_dims), hidden_size)
        self.logits_head = _head(hidden_size, num_actions, head_hidden)
        self.pointer_head = _head(hidden_size, 1, head_hidden)
        if initial_pointer_step:
            last = self.pointer_head if head_hidden is None else self.pointer_head[-1]
            nn.init.zeros_(last.weight)
            nn.init.constant_(last.bias, math.atanh(initial_pointer_step))
        self.mu_key, self.pixel_features_key, self.action_window_key = mu_key, pixel_features_key, action_window_key
        self.eta_used_key, self.is_init_key = eta_used_key, is_init_key
        self.hidden_key, self.eta_key = hidden_key, eta_key
        self.logits_key, self.features_key = logits_key, features_key
        self.demo_steps_key = demo_steps_key
        self.anchor_radius = None if anchor_radius is None else float(anchor_radius)
        self.anchor_gate = None if anchor_radius is None else anchor_gate(hidden_size)
        self.replay_gate = replay_gate_layer(hidden_size) if replay_gate else None
        self.start_check = None if start_check is None else float(start_check)
        self.anchor_key, self.anchor_confidence_key = anchor_key, anchor_confidence_key
        self.start_cosine_key, self.start_match_key = start_cosine_key, start_match_key
        checks = self.start_check is not None
        self.in_keys = [mu_key, pixel_features_key, action_window_key, eta_used_key, is_init_key, hidden_key] + (
            [demo_steps_key] if demo_steps_key is not None else []
        ) + ([anchor_key, anchor_confidence_key] if anchor_radius is not None else []) + (
            [start_cosine_key, start_match_key] if checks else []
        )
        self.out_keys = [logits_key, features_key, next_key(hidden_key), next_key(eta_key)] + (
            [next_key(start_match_key)] if checks else []
        )

    def make_tensordict_primer(self) -> TensorDictPrimer:
        """Primer for ``spf_hidden`` and ``eta`` (zeroed at every (partial) reset) and, with a start check,
        ``start_match`` (:data:`~spf_rl.modules.replay_gate.UNMEASURED` at every reset)."""
        specs = {self.hidden_key: Unbounded(shape=(self.hidden_size,)), self.eta_key: Unbounded(shape=(1,))}
        if self.start_check is not None:
            specs[self.start_match_key] = Unbounded(shape=(1,))
        return TensorDictPrimer(specs, expand_specs=True, default_value=self.state_defaults())

    def state_defaults(self) -> dict[NestedKey, float]:
        """Each recurrent state key's value at an episode's start."""
        defaults: dict[NestedKey, float] = {self.hidden_key: 0.0, self.eta_key: 0.0}
        if self.start_check is not None:
            defaults[self.start_match_key] = UNMEASURED
        return defaults

    def update_pointer(self, eta: torch.Tensor, b: torch.Tensor, lengths: torch.Tensor | None = None) -> torch.Tensor:
        """Pointer update (eq. 4, or the RPF code's clipped version, capped at ``n - 1``, or at
        ``n_i - 1`` per row with ``lengths``, int ``[*, 1]``)."""
        if self.pointer_update == "paper":
            return eta + torch.tanh(b)
        if lengths is None:
            return torch.clamp(eta + 1.0 + torch.tanh(b), max=float(self.demo_length - 1))
        return torch.minimum(eta + 1.0 + torch.tanh(b), (lengths.to(eta.device) - 1).to(eta.dtype))

    def step(
        self,
        mu: torch.Tensor,
        phi: torch.Tensor,
        window: torch.Tensor,
        eta: torch.Tensor,
        h: torch.Tensor,
        lengths: torch.Tensor | None = None,
        place: torch.Tensor | None = None,
        confidence: torch.Tensor | None = None,
        start: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One step on flat tensors -> (logits, next hidden state, next pointer); ``lengths``
        (int ``[*, 1]``, optional): each row's demonstration length; ``place`` and ``confidence``
        (``[*, 1]``): the anchor, with ``anchor_radius``; ``start`` (``[*, 1]``): the episode's start
        match (:func:`~spf_rl.modules.replay_gate.carry_start`), with ``start_check``."""
        h_next = self.gru(torch.cat([mu, phi, window.flatten(-2)], -1), h)
        logits = self.logits_head(h_next)  # before the pointer head: the order of their gradients' sum into h_next
        eta_next = self.update_pointer(eta, self.pointer_head(h_next), lengths)
        if self.anchor_gate is not None:
            if place is None or confidence is None:
                raise ValueError("this cell re-anchors its pointer: step() needs the anchor's place and confidence.")
            eta_next = reanchor(eta_next, eta, place, confidence, h_next, self.anchor_gate, self.anchor_radius)
        if self.replay_gate is not None or self.start_check is not None:
            if self.start_check is not None and start is None:
                raise ValueError("this cell checks the route's start: step() needs the start match.")
            opening = replay_opening(h_next, confidence, self.replay_gate, start, self.start_check)
            logits, eta_next = fall_back(logits, eta_next, eta, window, opening)
        if self.pointer_update == "rpf" and (self.anchor_gate is not None or self.start_check is not None):
            last = float(self.demo_length - 1) if lengths is None else (lengths.to(eta.device) - 1).to(eta.dtype)
            eta_next = torch.minimum(eta_next, torch.as_tensor(last, dtype=eta.dtype, device=eta.device))  # the rule's cap holds after them
        return logits, h_next, eta_next

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """One step: hidden state reset where ``is_init``, then eqs. 3-4."""
        return with_batch_dim(self._forward_step, tensordict)

    def _forward_step(self, td: TensorDictBase) -> TensorDictBase:
        batch = td.batch_size
        mu = td.get(self.mu_key)
        h = flat_or_zeros(td.get(self.hidden_key, None), (*batch, self.hidden_size), mu)
        is_init = init_flags(td, self.is_init_key, mu.device).unsqueeze(-1)
        h = torch.where(is_init, torch.zeros_like(h), h)
        eta = td.get(self.eta_used_key)
        flat = mu.reshape(-1, mu.shape[-1]).shape[0]
        lengths = demo_lengths(td, self.demo_steps_key, self.demo_length, batch)
        start = None
        if self.start_check is not None:
            state = td.get(self.start_match_key, None)
            state = torch.full((*batch, 1), UNMEASURED, dtype=mu.dtype, device=mu.device) if state is None else state.to(mu.dtype)
            state = torch.where(is_init, torch.full_like(state, UNMEASURED), state)
            start = carry_start(state, td.get(self.start_cosine_key).to(mu.dtype)).reshape(flat, 1)
        logits, h_next, eta_next = self.step(
            mu.reshape(flat, -1),
            td.get(self.pixel_features_key).reshape(flat, -1),
            td.get(self.action_window_key).reshape(flat, *td.get(self.action_window_key).shape[-2:]),
            eta.reshape(flat, 1),
            h.reshape(flat, self.hidden_size),
            None if lengths is None else lengths.reshape(flat, 1),
            *(
                (td.get(self.anchor_key).reshape(flat, 1), td.get(self.anchor_confidence_key).reshape(flat, 1))
                if self.anchor_gate is not None
                else (None, None)
            ),
            start,
        )
        td.set(self.logits_key, logits.reshape(*batch, self.num_actions))
        td.set(self.features_key, h_next.reshape(*batch, self.hidden_size))
        td.set(next_key(self.hidden_key), h_next.reshape(*batch, self.hidden_size))
        td.set(next_key(self.eta_key), eta_next.reshape(*batch, 1))
        if start is not None:
            td.set(next_key(self.start_match_key), start.reshape(*batch, 1))
        return td


def _head(in_features: int, out_features: int, hidden: int | None) -> nn.Module:
    """A linear head, or a 2-layer MLP (ReLU) when ``hidden`` is given."""
    if hidden is None:
        return nn.Linear(in_features, out_features)
    return nn.Sequential(nn.Linear(in_features, hidden), nn.ReLU(), nn.Linear(hidden, out_features))
