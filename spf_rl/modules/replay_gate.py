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

The **start check** is the second way to open it, and it is not learned. A route is repeated from
the pose it was taught from, and the memory always keeps the route's first frame, so the first
frame the agent sees should match the memory's first slot. Its cosine ``s`` (the encoder's features
of the two, :func:`start_cosine`) is measured at the episode's first step and carried as recurrent
state (``start_match``: :data:`UNMEASURED` until then). With a threshold ``tau``
(``SPFConfig.start_check``, calibrated on the validation houses by ``recipes/start_check.py``), a
second opening ``r_s = sigmoid(S (tau - s))`` (``S =`` :data:`START_CHECK_SHARPNESS`) joins the
gate's: ``r = 1 - (1 - r_g)(1 - r_s)``. A start that does not match the memory (another route's
frames) makes the whole episode a replay; one that does leaves the learned gate alone.

Examples:
    >>> import torch
    >>> gate = replay_gate_layer(2)
    >>> with torch.no_grad():
    ...     _ = gate.bias.fill_(50.0)  # wide open: blind replay
    >>> window = torch.nn.functional.one_hot(torch.tensor([[0, 2, 1]]), 3).float()  # k = 1: the centre is action 2
    >>> opening = replay_opening(torch.zeros(1, 2), torch.tensor([[0.1]]), gate)
    >>> logits, eta_next = fall_back(torch.tensor([[5.0, 0.0, 0.0]]), torch.tensor([[9.0]]), torch.tensor([[4.0]]),
    ...                              window, opening)
    >>> logits.argmax(-1).item(), eta_next.item()  # the demonstrated action, one route step on
    (2, 5.0)
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

__all__ = [
    "replay_gate_layer",
    "replay_score",
    "replay_opening",
    "fall_back",
    "start_cosine",
    "carry_start",
    "GATE_INITIAL_BIAS",
    "CONFIDENCE_SCALE",
    "START_CHECK_SHARPNESS",
    "UNMEASURED",
]

#: The gate's bias at the start: ``sigmoid(-4) = 0.018``, nearly shut.
GATE_INITIAL_BIAS = -4.0
#: The anchor's confidence (a cosine) is multiplied by this before the gate (see the module).
CONFIDENCE_SCALE = 10.0
#: The start check's opening is ``sigmoid(START_CHECK_SHARPNESS * (tau - s))``: 0.1 of cosine is 5 logits.
START_CHECK_SHARPNESS = 50.0
#: The start match before the episode's first step is measured (a cosine is at most 1).
UNMEASURED = 2.0
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


def _log_sigmoid(x: torch.Tensor) -> torch.Tensor:
    """``log(sigmoid(x))`` written out: ONNX Runtime's exported ``F.logsigmoid`` (``Log(Sigmoid(x))``) is
    ``-inf`` below about ``x = -16``, where its sigmoid rounds to 0."""
    return torch.minimum(x, torch.zeros_like(x)) - torch.log(1.0 + torch.exp(-x.abs()))


def start_cosine(phi: torch.Tensor, memory: torch.Tensor, slots: torch.Tensor, used: torch.Tensor | None) -> torch.Tensor:
    """The cosine ``[R, 1]`` of the frame's features ``phi`` ``[R, D]`` with the memory slot that holds the
    route's first frame (``memory`` ``[R, l, D]``, each slot's route step ``slots`` ``[l]`` or ``[R, l]``,
    ``used`` ``[R, l]`` or ``None``: all); 1 (a match) for a row whose memory holds no first frame.

    Examples:
        >>> import torch
        >>> memory = torch.tensor([[[1.0, 0.0], [0.0, 1.0]]])
        >>> start_cosine(torch.tensor([[1.0, 1.0]]), memory, torch.tensor([0, 5]), None).item()  # 45 degrees off slot 0
        0.7071067690849304
    """
    first = (slots == 0).expand(memory.shape[:-1])
    if used is not None:
        first = first & used.to(torch.bool)
    start = (first.unsqueeze(-1).to(memory.dtype) * memory).sum(-2)  # [R, D]: the first frame's features, or 0
    cosine = F.cosine_similarity(phi, start.to(phi.dtype), dim=-1, eps=1e-8).unsqueeze(-1)
    return torch.where(first.any(-1, keepdim=True), cosine, torch.ones_like(cosine))


def carry_start(state: torch.Tensor, cosine: torch.Tensor) -> torch.Tensor:
    """The start match after this step: ``cosine`` where ``state`` is :data:`UNMEASURED` (the episode's first
    step), else ``state`` (``[R, 1]`` each).

    Examples:
        >>> import torch
        >>> carry_start(torch.tensor([[UNMEASURED], [0.3]]), torch.tensor([[0.9], [0.8]])).flatten().tolist()
        [0.8999999761581421, 0.30000001192092896]
    """
    return torch.where(state > 1.0, cosine, state)


def replay_opening(
    hidden: torch.Tensor,
    confidence: torch.Tensor | None,
    gate: nn.Linear | None,
    start: torch.Tensor | None = None,
    threshold: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(log r, log(1 - r))`` ``[R, 1]`` of the opening ``r = 1 - (1 - r_g)(1 - r_s)``: the learned
    gate's ``r_g`` (``gate`` over ``[hidden, s * confidence]``; ``gate=None``: 0) and the start check's
    ``r_s = sigmoid(S (threshold - start))`` (``threshold=None``: 0). One of the two must be given.

    Examples:
        >>> import torch
        >>> log_open, log_shut = replay_opening(torch.zeros(2, 3), None, None, torch.tensor([[0.2], [0.95]]), 0.5)
        >>> log_open.exp().flatten().round(decimals=3).tolist()  # a start far from the memory's: replay
        [1.0, 0.0]
    """
    scores = []
    if gate is not None:
        scores.append(replay_score(hidden, confidence, gate))
    if threshold is not None:
        scores.append(START_CHECK_SHARPNESS * (threshold - start))
    if not scores:
        raise ValueError("replay_opening needs a gate or a start-check threshold.")
    if len(scores) == 1:
        return _log_sigmoid(scores[0]), _log_sigmoid(-scores[0])
    learned, check = scores
    log_shut = _log_sigmoid(-learned) + _log_sigmoid(-check)
    # log(r_g + r_s (1 - r_g)), written out as a log-sum-exp for the exporters
    a, b = _log_sigmoid(learned), _log_sigmoid(check) + _log_sigmoid(-learned)
    top = torch.maximum(a, b)
    return top + torch.log(torch.exp(a - top) + torch.exp(b - top)), log_shut


def fall_back(
    logits: torch.Tensor,
    eta_next: torch.Tensor,
    eta: torch.Tensor,
    window: torch.Tensor,
    opening: tuple[torch.Tensor, torch.Tensor],
) -> tuple[torch.Tensor, torch.Tensor]:
    """The logits and the next pointer moved toward blind replay by the opening (see the module).

    Args:
        logits: the network's action logits ``[R, C]``.
        eta_next: the rule's (and the anchor's) next pointer ``[R, 1]``.
        eta: the pointer this step read ``[R, 1]``.
        window: the one-hot demonstrated actions ``[R, 2k + 1, C]`` around ``floor(eta)`` (zero off
            the route: a row without a demonstrated action keeps the network's distribution).
        opening: ``(log r, log(1 - r))`` ``[R, 1]`` each, from :func:`replay_opening`.

    Returns:
        The log-probabilities ``[R, C]`` of the mixture (where the window's centre is empty, the
        network's log-probabilities plus ``log(1 - r)``: the same distribution) and the next pointer ``[R, 1]``.
    """
    log_open, log_shut = opening
    shown = window[:, (window.shape[1] - 1) // 2]  # the demonstrated action at floor(eta)
    own = F.log_softmax(logits, -1) + log_shut
    replay = torch.where(shown > 0, torch.zeros_like(shown), torch.full_like(shown, _NOT_SHOWN)) + log_open
    top = torch.maximum(own, replay)  # log(exp(own) + exp(replay)), written out for the exporters
    mixed = top + torch.log(torch.exp(own - top) + torch.exp(replay - top))
    return mixed, eta_next + torch.exp(log_open) * (eta + 1.0 - eta_next)
