"""Re-anchoring the pointer on what the agent sees (beyond the paper and RPF; issue #62).

SPF's attention weighs the memory by position alone (``exp(-|eta - j|)``), and RPF's pointer
rule, ``eta + 1 + tanh(b)``, never goes back: once the pointer has run ahead of the agent,
nothing brings it back (``docs/results.md``, the pointer traces). The anchor compares the
current frame with the memory slots near the pointer and proposes where the agent is:

* :class:`PointerAnchor` (in the attention): a query of the current frame's features and a
  key of each memory slot's, both unit vectors; over the used slots within ``radius`` route
  steps of the pointer, a softmax of their cosines (times a learned temperature) gives the
  **anchor**, the expected route step of the slot the frame matches, and the **confidence**,
  the expected cosine. An empty band leaves the anchor on the pointer, with confidence 0.
* :func:`reanchor` (in the cell): a learned gate ``g = sigmoid(w . [h, confidence, (anchor -
  eta) / radius] + c)`` moves the rule's next pointer by ``g (anchor - eta)``: the pointer
  can go back to where the frame says the agent is, by at most ``radius`` steps, or hold to
  the rule where the memory disagrees with the view (low confidence: a changed world, or
  another route's frames).

The gate starts nearly shut (``c = -4``: ``g = 0.018``, its weights 0), so a policy grown from
weights without an anchor starts where they were.

Examples:
    >>> import torch
    >>> anchor = PointerAnchor(feature_dim=4, radius=2.0, key_dim=4)
    >>> memory = torch.eye(4).expand(1, 4, 4)  # four slots, each its own feature
    >>> with torch.no_grad():
    ...     _ = anchor.query.weight.copy_(torch.eye(4)); _ = anchor.key.weight.copy_(torch.eye(4))
    ...     _ = anchor.query.bias.zero_(); _ = anchor.key.bias.zero_()
    >>> slots = torch.tensor([[0, 3, 6, 9]])
    >>> place, confidence = anchor.locate(memory[:, 1], memory, slots, None, torch.tensor([[4.0]]))
    >>> round(place.item(), 2), round(confidence.item(), 2)  # the frame is slot 1's: route step 3
    (3.0, 1.0)
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["PointerAnchor", "reanchor", "anchor_gate", "DEFAULT_ANCHOR_RADIUS"]

#: Route steps either side of the pointer that the anchor searches.
DEFAULT_ANCHOR_RADIUS = 8
#: Size of the anchor's query and keys.
ANCHOR_KEY_DIM = 64
#: The softmax temperature over cosines at the start (learned, as its logarithm).
INITIAL_TEMPERATURE = 10.0
#: The gate's bias at the start: ``sigmoid(-4) = 0.018``, nearly shut.
GATE_INITIAL_BIAS = -4.0
#: A score that never wins a softmax (finite, so an exported graph has no NaN to guard).
_OFF_BAND = -1.0e4


class PointerAnchor(nn.Module):
    """Where the current frame says the agent is on the route: a match of the frame against the
    memory slots within ``radius`` route steps of the pointer (see the module).

    Args:
        feature_dim: size of the frame's and the slots' features.
        radius: route steps either side of the pointer searched (> 0).
        key_dim: size of the query and the keys.

    Examples:
        >>> import torch
        >>> anchor = PointerAnchor(feature_dim=8, radius=4.0)
        >>> place, confidence = anchor.locate(torch.randn(2, 8), torch.randn(2, 5, 8), torch.tensor([0, 2, 4, 6, 8]),
        ...                                   torch.ones(2, 5, dtype=torch.bool), torch.tensor([[0.0], [30.0]]))
        >>> place.shape, bool(0 <= place[0] <= 4), place[1].item(), confidence[1].item()  # no slot near 30: stays
        (torch.Size([2, 1]), True, 30.0, 0.0)
    """

    def __init__(self, feature_dim: int, radius: float = DEFAULT_ANCHOR_RADIUS, key_dim: int = ANCHOR_KEY_DIM) -> None:
        super().__init__()
        if not float(radius) > 0:
            raise ValueError(f"anchor radius must be > 0 route steps, got {radius!r}.")
        self.radius = float(radius)
        self.query = nn.Linear(feature_dim, key_dim)
        self.key = nn.Linear(feature_dim, key_dim)
        self.log_temperature = nn.Parameter(torch.tensor(math.log(INITIAL_TEMPERATURE)))

    def locate(
        self,
        phi: torch.Tensor,
        memory: torch.Tensor,
        slots: torch.Tensor,
        used: torch.Tensor | None,
        eta: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The anchor and the confidence, ``[R, 1]`` each.

        Args:
            phi: the current frame's features ``[R, D]``.
            memory: the slots' features ``[R, l, D]``.
            slots: each slot's route step ``[l]`` or ``[R, l]``.
            used: which slots hold the route's frames ``[R, l]`` (``None``: all).
            eta: the pointer the step reads ``[R, 1]``.
        """
        query = F.normalize(self.query(phi), dim=-1)
        keys = F.normalize(self.key(memory.to(phi.dtype)), dim=-1)
        cosine = (keys @ query.unsqueeze(-1)).squeeze(-1)  # [R, l]
        positions = slots.to(eta.dtype).expand_as(cosine)
        band = (positions - eta).abs() <= self.radius
        if used is not None:
            band = band & used.to(torch.bool)
        scores = (cosine * self.log_temperature.exp()).masked_fill(~band, _OFF_BAND)
        weights = torch.softmax(scores, -1) * band.to(scores.dtype)
        total = weights.sum(-1, keepdim=True)
        weights = weights / total.clamp(min=1e-12)
        found = total > 0
        place = torch.where(found, (weights * positions).sum(-1, keepdim=True), eta)
        confidence = (weights * cosine).sum(-1, keepdim=True)
        return place, confidence


def anchor_gate(hidden_size: int) -> nn.Linear:
    """The gate's layer over ``[h, confidence, offset]``: weights 0, bias :data:`GATE_INITIAL_BIAS`."""
    gate = nn.Linear(hidden_size + 2, 1)
    nn.init.zeros_(gate.weight)
    nn.init.constant_(gate.bias, GATE_INITIAL_BIAS)
    return gate


def reanchor(
    eta_next: torch.Tensor,
    eta: torch.Tensor,
    place: torch.Tensor,
    confidence: torch.Tensor,
    hidden: torch.Tensor,
    gate: nn.Linear,
    radius: float,
) -> torch.Tensor:
    """The rule's next pointer ``eta_next`` moved by ``g (place - eta)``, ``g`` the gate over
    ``[hidden, confidence, (place - eta) / radius]`` (all ``[R, *]``).

    Examples:
        >>> import torch
        >>> gate = anchor_gate(2)
        >>> with torch.no_grad():
        ...     _ = gate.bias.fill_(50.0)  # wide open
        >>> reanchor(torch.tensor([[11.0]]), torch.tensor([[10.0]]), torch.tensor([[4.0]]), torch.tensor([[0.9]]),
        ...          torch.zeros(1, 2), gate, 8.0).item()  # back to the frame's place, then the rule's step
        5.0
    """
    offset = place - eta
    opening = torch.sigmoid(gate(torch.cat([hidden, confidence, offset / radius], -1)))
    return eta_next + opening * offset
