"""Falling back on the demonstrated actions where the memory disagrees with the view (issue #62).

Given another route's frames, or a world changed past what the encoder absorbs, SPF trusts its
memory blindly: the anchored route model succeeds 0.21 with mismatched frames where blind replay
of the same actions succeeds 0.54 (``docs/results.md``). Blind replay is a policy the network
already holds: the action window's centre is the demonstrated action at ``floor(eta)``, and a
pointer that moves one step per step plays the demonstration as it was shown.

The **replay gate** ``r = sigmoid(w . [h, s * confidence] + c)`` (``h`` the cell's new hidden state,
``confidence`` the anchor's expected cosine, :mod:`spf_rl.modules.anchor`, scaled by ``s =``
:data:`CONFIDENCE_SCALE`) moves the policy toward that replay:

* the action distribution becomes ``(1 - r) softmax(logits) + r onehot(a_floor(eta))`` (returned
  as its logarithm, so the cross-entropy, the argmax and a sampler read it as logits);
* the rule's next pointer moves toward ``eta + 1``: ``eta_next + r (eta + 1 - eta_next)``.

Shut (``r = 0``) it is the network as it was; open (``r = 1``) it is blind replay. Trained by the
same imitation loss, it opens where the demonstrated action is the expert's more often than the
network's own (a mismatched memory) and stays shut where the network is right. It starts nearly
shut (``c = -4``: ``r = 0.018``, its weights 0), so a policy grown from weights without it starts
nearly where they were. The scale: Adam moves a weight by about the learning rate per step, and the
confidence differs by about 0.2 between the teaching world and another route's frames (0.47-0.52
against 0.29-0.44, ``docs/results.md``); scaled by 10, a weight of 1 on it parts them by 2 logits.

Examples:
    >>> import torch
    >>> gate = replay_gate_layer(2)
    >>> with torch.no_grad():
    ...     _ = gate.bias.fill_(50.0)  # wide open: blind replay
    >>> window = torch.nn.functional.one_hot(torch.tensor([[0, 2, 1]]), 3).float()  # k = 1: the centre is action 2
    >>> logits, eta_next = fall_back(torch.tensor([[5.0, 0.0, 0.0]]), torch.tensor([[9.0]]), torch.tensor([[4.0]]),
    ...                              window, torch.tensor([[0.1]]), torch.zeros(1, 2), gate)
    >>> logits.argmax(-1).item(), eta_next.item()  # the demonstrated action, one route step on
    (2, 5.0)
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = ["replay_gate_layer", "replay_score", "fall_back", "GATE_INITIAL_BIAS", "CONFIDENCE_SCALE"]

#: The gate's bias at the start: ``sigmoid(-4) = 0.018``, nearly shut.
GATE_INITIAL_BIAS = -4.0
#: The anchor's confidence (a cosine) is multiplied by this before the gate (see the module).
CONFIDENCE_SCALE = 10.0
#: The log-probability of an action the demonstration did not take (finite: an exported graph has no inf).
_NOT_SHOWN = -1.0e4


def replay_gate_layer(hidden_size: int) -> nn.Linear:
    """The gate's layer over ``[h, s * confidence]``: weights 0, bias :data:`GATE_INITIAL_BIAS`.

    Examples:
        >>> replay_gate_layer(4).weight.abs().sum().item(), replay_gate_layer(4).bias.item()
        (0.0, -4.0)
    """
    gate = nn.Linear(hidden_size + 1, 1)
    nn.init.zeros_(gate.weight)
    nn.init.constant_(gate.bias, GATE_INITIAL_BIAS)
    return gate


def replay_score(hidden: torch.Tensor, confidence: torch.Tensor, gate: nn.Linear) -> torch.Tensor:
    """The gate's logit ``w . [h, s * confidence] + c`` ``[R, 1]`` (its opening is the sigmoid of it).

    Examples:
        >>> import torch
        >>> torch.sigmoid(replay_score(torch.zeros(1, 3), torch.tensor([[0.5]]), replay_gate_layer(3))).item() < 0.02
        True
    """
    return gate(torch.cat([hidden, confidence * CONFIDENCE_SCALE], -1))


def fall_back(
    logits: torch.Tensor,
    eta_next: torch.Tensor,
    eta: torch.Tensor,
    window: torch.Tensor,
    confidence: torch.Tensor,
    hidden: torch.Tensor,
    gate: nn.Linear,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The logits and the next pointer moved toward blind replay by the gate (see the module).

    Args:
        logits: the network's action logits ``[R, C]``.
        eta_next: the rule's (and the anchor's) next pointer ``[R, 1]``.
        eta: the pointer this step read ``[R, 1]``.
        window: the one-hot demonstrated actions ``[R, 2k + 1, C]`` around ``floor(eta)`` (zero off
            the route: a row without a demonstrated action keeps the network's distribution).
        confidence: the anchor's confidence ``[R, 1]``.
        hidden: the cell's new hidden state ``[R, H]``.
        gate: :func:`replay_gate_layer`'s layer.

    Returns:
        The log-probabilities ``[R, C]`` of the mixture (where the window's centre is empty, the
        network's log-probabilities plus ``log(1 - r)``: the same distribution) and the next pointer ``[R, 1]``.
    """
    score = replay_score(hidden, confidence, gate)
    shown = window[:, (window.shape[1] - 1) // 2]  # the demonstrated action at floor(eta)
    own = F.log_softmax(logits, -1) + F.logsigmoid(-score)
    replay = torch.where(shown > 0, torch.zeros_like(shown), torch.full_like(shown, _NOT_SHOWN)) + F.logsigmoid(score)
    top = torch.maximum(own, replay)  # log(exp(own) + exp(replay)), written out for the exporters
    mixed = top + torch.log(torch.exp(own - top) + torch.exp(replay - top))
    opening = torch.sigmoid(score)
    return mixed, eta_next + opening * (eta + 1.0 - eta_next)
