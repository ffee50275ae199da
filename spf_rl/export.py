"""Export a policy to ONNX for a robot: a **teach** graph, run once per route, and a **step** graph, run
every step, through :func:`torch.export.export` and :func:`torch.onnx.export` (opset 18, dynamic batch,
route length and number of memory slots).

- teach: ``frames`` uint8 ``[N, H, W, 3]`` (the route's kept frames) and ``actions`` ``[N]`` (their
  demonstrated actions; read by the original RPF's slot network only) -> ``memory`` ``[N, D]``.
- step: ``frame`` uint8 ``[B, H, W, 3]``, ``memory`` ``[B, l, D]``, ``slot_indices`` ``[B, l]`` (the kept
  frames' route steps ``M*``), ``demo_actions`` ``[B, n]``, ``route_length`` ``[B]``, ``eta`` ``[B]`` (the
  pointer) and ``hidden`` ``[B, Hs]`` -> ``logits`` ``[B, A]``, ``eta_next`` ``[B]``, ``hidden_next``; a model
  with a start check (``SPFConfig.start_check``) also carries ``start_match`` ``[B]`` -> ``start_match_next``
  (:mod:`spf_rl.modules.replay_gate`; it starts at the manifest's ``step.initial_state``, "unmeasured").

The graphs compute what the eager policy computes in step mode (:class:`~spf_rl.modules.policy.SPFPolicy`):
the same submodules, with the route's length as a tensor (the eager policy's ``demo_steps`` form) and the
episode start left to the caller (teach the route, then set the state to the manifest's ``step.initial_state``:
``eta = 0``, ``hidden = 0`` and ``start_match`` unmeasured, which is what ``is_init`` does). Which frames a route keeps is the caller's too (:func:`~spf_rl.modules.memory.memory_indices`
at the policy's sparsity), so that one step graph serves every route length and, for the random-sparsity
model, every sparsity.

:func:`export_policy` writes the graphs and a ``manifest.json`` (format version, model type and config,
weight precision, each file's SHA-256, the source's identity, the versions that made it) to a directory
that :class:`spf_rl_runtime.Follower` (the ``runtime/`` distribution, numpy and ONNX Runtime only) reads.
``recipes/export.py`` is its command line.
"""
from __future__ import annotations

import copy
import logging
import os
from pathlib import Path
from typing import Any

import torch
from torch import nn

from envs.atomic_io import atomic_write_json
from spf_rl.checkpoint import file_sha256
from spf_rl.modules.anchor import reanchor
from spf_rl.modules.policy import SPFPolicy
from spf_rl.modules.replay_gate import UNMEASURED, carry_start, fall_back, replay_opening, start_cosine

logger = logging.getLogger(__name__)

#: Version of an export directory's layout (the manifest and the graphs' inputs and outputs). 2: the step
#: graph may carry a start match, and the manifest gives the step state's initial values.
EXPORT_FORMAT_VERSION = 2
MANIFEST_NAME = "manifest.json"
TEACH_FILE, STEP_FILE = "teach.onnx", "step.onnx"
OPSET = 18
#: Weight precisions an export may hold: float32, or int8 (dynamic quantisation of the matrix products).
WEIGHT_PRECISIONS = ("fp32", "int8")
TEACH_INPUTS, TEACH_OUTPUTS = ("frames", "actions"), ("memory",)
STEP_INPUTS = ("frame", "memory", "slot_indices", "demo_actions", "route_length", "eta", "hidden")
STEP_OUTPUTS = ("logits", "eta_next", "hidden_next")
#: The step graph's extra state with a start check (an input, and its next value an output).
START_INPUT, START_OUTPUT = "start_match", "start_match_next"


def _one_hot(actions: torch.Tensor, num_classes: int, dtype: torch.dtype) -> torch.Tensor:
    """``F.one_hot(actions, C).to(dtype)`` without its data-dependent range check (the same values for
    actions in ``[0, C)``)."""
    return (actions.unsqueeze(-1) == torch.arange(num_classes, device=actions.device)).to(dtype)


class TeachGraph(nn.Module):
    """A policy's memory encoder: kept frames (and their actions) -> memory features.

    Examples:
        >>> from spf_rl.modules import SPFConfig
        >>> policy = SPFPolicy(SPFConfig(demo_length=6, feature_dim=8, hidden_size=8, image_size=(16, 16))).eval()
        >>> TeachGraph(policy)(torch.zeros(5, 16, 16, 3, dtype=torch.uint8), torch.zeros(5, dtype=torch.long)).shape
        torch.Size([5, 8])
    """

    def __init__(self, policy: SPFPolicy) -> None:
        super().__init__()
        self.phi = policy.encoder.module
        self.slot_mlp = policy.memory.slot_mlp if policy.use_memory and hasattr(policy.memory, "slot_mlp") else None
        self.num_actions = policy.config.num_actions

    def forward(self, frames: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        features = self.phi(frames)
        if self.slot_mlp is not None:  # the original RPF: a slot network over [phi(frame), one-hot(action)]
            features = self.slot_mlp.net(torch.cat([features, _one_hot(actions, self.num_actions, features.dtype)], -1))
        return features


class StepGraph(nn.Module):
    """A policy's step: one frame, the route's memory and actions, the pointer and hidden state -> logits,
    the next pointer and hidden state (batched).

    Examples:
        >>> from spf_rl.modules import SPFConfig
        >>> policy = SPFPolicy(SPFConfig(demo_length=6, feature_dim=8, hidden_size=8, image_size=(16, 16))).eval()
        >>> logits, eta, hidden = StepGraph(policy)(torch.zeros(2, 16, 16, 3, dtype=torch.uint8), torch.zeros(2, 5, 8),
        ...     torch.tensor([[0, 1, 2, 4, 5]] * 2), torch.zeros(2, 6, dtype=torch.long), torch.tensor([6, 6]),
        ...     torch.zeros(2), torch.zeros(2, 8))
        >>> logits.shape, eta.shape, hidden.shape
        (torch.Size([2, 3]), torch.Size([2]), torch.Size([2, 8]))
    """

    def __init__(self, policy: SPFPolicy) -> None:
        super().__init__()
        attention = policy.attention.attention
        self.phi = policy.encoder.module
        self.use_memory = policy.use_memory
        self.lab_rpf = policy.config.architecture == "rpf_original"
        self.psi = None if self.lab_rpf else attention.psi
        self.k = 0 if self.lab_rpf else attention.k
        self.soft = bool(getattr(attention, "soft_action_memory", False))
        self.num_actions = policy.config.num_actions
        self.paper_rule = policy.cell.pointer_update == "paper"
        self.gru, self.logits_head, self.pointer_head = policy.cell.gru, policy.cell.logits_head, policy.cell.pointer_head
        self.anchor, self.anchor_gate, self.anchor_radius = policy.attention.anchor, policy.cell.anchor_gate, policy.cell.anchor_radius
        self.replay_gate = policy.cell.replay_gate
        self.start_check = policy.cell.start_check

    def forward(self, frame, memory, slot_indices, demo_actions, route_length, eta, hidden, start_match=None):
        num_actions = self.num_actions
        phi = self.phi(frame)  # [B, D]
        eta = eta.reshape(-1, 1).to(phi.dtype)
        last = route_length.reshape(-1, 1).long() - 1
        actions = demo_actions.long()
        parts = []
        anchor = ()
        start = None
        if self.use_memory:  # w_j = exp(-|eta - M*_j|) over the used slots, then the weighted sum
            slots = slot_indices.long()
            used = (slots >= 0) & (slots <= last)
            weights = torch.exp(-(eta - slots.clamp(min=0).to(eta.dtype)).abs()).masked_fill(~used, 0.0)
            parts.append((weights.unsqueeze(-1) * memory.to(eta.dtype)).sum(-2))
            if self.anchor is not None:  # where the frame says the agent is (spf_rl.modules.anchor)
                anchor = self.anchor.locate(phi, memory.to(eta.dtype), slots.clamp(min=0), used, eta)
            if self.start_check is not None:  # the first step's cosine with the route's first frame, then carried
                start = carry_start(start_match.reshape(-1, 1).to(eta.dtype), start_cosine(phi, memory.to(eta.dtype), slots, used))
        window = None
        if self.lab_rpf:  # the original RPF: mu is the attended memory, no action window
            mu = parts[0]
        else:  # the demonstrated actions at floor(eta) - k .. floor(eta) + k, one-hot, zero off the route
            offsets = torch.arange(-self.k, self.k + 1, device=eta.device)
            centre = torch.minimum(eta.detach().floor().long().clamp(min=0), last)
            positions = centre + offsets
            valid = (positions >= 0) & (positions <= last)
            picked = actions.gather(-1, torch.minimum(positions.clamp(min=0), last))
            window = _one_hot(picked, num_actions, eta.dtype) * valid.unsqueeze(-1).to(eta.dtype)
            parts.append(window.flatten(-2))
            if self.soft:  # action-only: the soft action memory over the whole route
                steps = torch.arange(actions.shape[-1], device=eta.device).unsqueeze(0)
                on_route = steps <= last
                soft = torch.exp(-(eta - steps.to(eta.dtype)).abs()).masked_fill(~on_route, 0.0)
                parts.append((soft.unsqueeze(-1) * _one_hot(actions.masked_fill(~on_route, 0), num_actions, eta.dtype)).sum(-2))
            mu = self.psi(torch.cat(parts, -1))
        hidden_next = self.gru(torch.cat([mu, phi] + ([] if window is None else [window.flatten(-2)]), -1), hidden.to(phi.dtype))
        logits = self.logits_head(hidden_next)
        increment = torch.tanh(self.pointer_head(hidden_next))
        eta_next = eta + increment if self.paper_rule else torch.minimum(eta + 1.0 + increment, last.to(eta.dtype))
        if anchor:
            eta_next = reanchor(eta_next, eta, *anchor, hidden_next, self.anchor_gate, self.anchor_radius)
        if self.replay_gate is not None or start is not None:  # toward blind replay (spf_rl.modules.replay_gate)
            opening = replay_opening(hidden_next, anchor[1] if anchor else None, self.replay_gate, start, self.start_check)
            logits, eta_next = fall_back(logits, eta_next, eta, window, opening)
        if (anchor or start is not None) and not self.paper_rule:
            eta_next = torch.minimum(eta_next, last.to(eta.dtype))
        if start is not None:
            return logits, eta_next.reshape(-1), hidden_next, start.reshape(-1)
        return logits, eta_next.reshape(-1), hidden_next


def _versions() -> dict[str, str]:
    import importlib.metadata as metadata

    versions = {}
    for name in ("torch", "onnx", "onnxscript", "onnxruntime", "spf-rl"):
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def memory_width(policy: SPFPolicy) -> int:
    """The size of one memory slot's features (the feature size; the original RPF's slot network's output)."""
    if not policy.use_memory:
        return policy.config.feature_dim
    with torch.no_grad():
        frame = torch.zeros(1, *policy.config.image_size, 3, dtype=torch.uint8)
        return int(TeachGraph(policy)(frame, torch.zeros(1, dtype=torch.long)).shape[-1])


def _example_step_inputs(policy: SPFPolicy) -> tuple[torch.Tensor, ...]:
    config = policy.config
    batch, n = 2, max(config.demo_length, 3)
    slots = 3
    width = memory_width(policy)
    return (
        torch.zeros(batch, *config.image_size, 3, dtype=torch.uint8),
        torch.zeros(batch, slots, width),
        torch.tensor([[0, 1, n - 1][:slots]] * batch),
        torch.zeros(batch, n, dtype=torch.long),
        torch.full((batch,), n, dtype=torch.long),
        torch.zeros(batch),
        torch.zeros(batch, config.hidden_size),
    ) + ((torch.full((batch,), UNMEASURED),) if config.start_check is not None else ())


def step_state(policy: SPFPolicy) -> tuple[tuple[str, ...], tuple[str, ...], dict[str, float]]:
    """The step graph's input names, output names and the initial value of each recurrent state input.

    Examples:
        >>> from spf_rl.modules import SPFConfig
        >>> step_state(SPFPolicy(SPFConfig(feature_dim=8, hidden_size=8, start_check=0.5)))[2]
        {'eta': 0.0, 'hidden': 0.0, 'start_match': 2.0}
    """
    initial = {"eta": 0.0, "hidden": 0.0}
    if policy.config.start_check is None:
        return STEP_INPUTS, STEP_OUTPUTS, initial
    return STEP_INPUTS + (START_INPUT,), STEP_OUTPUTS + (START_OUTPUT,), {**initial, START_INPUT: UNMEASURED}


def _export_onnx(module: nn.Module, args: tuple, dynamic_shapes: tuple, names: tuple, outputs: tuple, path: Path) -> None:
    program = torch.export.export(module, args, dynamic_shapes=dynamic_shapes, strict=False)
    onnx_program = torch.onnx.export(program, args, input_names=list(names), output_names=list(outputs),
                                     dynamo=True, opset_version=OPSET, verbose=False)
    tmp = path.with_name(f".{path.name}.tmp")
    onnx_program.save(str(tmp))
    os.replace(tmp, path)


def _quantize(path: Path) -> None:
    """Int8 weights: dynamic quantisation of the graph's matrix products (ONNX Runtime's)."""
    from onnxruntime.quantization import QuantType, quantize_dynamic

    tmp = path.with_name(f".{path.name}.int8")
    quantize_dynamic(str(path), str(tmp), weight_type=QuantType.QInt8)
    os.replace(tmp, path)


def export_policy(policy: SPFPolicy, out: str | os.PathLike, model_type: str, weights: str = "fp32",
                  source: dict[str, Any] | None = None) -> dict:
    """Write ``policy``'s teach and step graphs (action-only: the step graph alone) and their manifest to ``out``.

    Args:
        policy: the policy (a random-sparsity one at the sparsity it should keep by default).
        out: the export directory (made; files in it are replaced).
        model_type: the checkpoint's model type (written to the manifest).
        weights: ``"fp32"`` or ``"int8"`` (:data:`WEIGHT_PRECISIONS`).
        source: what the export was made from (a checkpoint's path, the policy's weights hash).

    Returns:
        The manifest.

    Raises:
        ValueError: an unknown ``weights``.
    """
    from torch.export import Dim

    from spf_rl.records_cache import policy_sha256

    if weights not in WEIGHT_PRECISIONS:
        raise ValueError(f"weights must be one of {WEIGHT_PRECISIONS}, got {weights!r}.")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    policy = copy.deepcopy(policy).cpu().eval()  # the caller's module stays where and as it was
    batch, slots, route = Dim("batch", min=1, max=4096), Dim("slots", min=1, max=4096), Dim("route", min=2, max=4096)
    files = {}
    with torch.no_grad():
        if policy.use_memory:
            kept = Dim("kept", min=1, max=4096)
            teach_args = (torch.zeros(3, *policy.config.image_size, 3, dtype=torch.uint8), torch.zeros(3, dtype=torch.long))
            _export_onnx(TeachGraph(policy).eval(), teach_args, ({0: kept}, {0: kept}), TEACH_INPUTS, TEACH_OUTPUTS, out / TEACH_FILE)
            files[TEACH_FILE] = out / TEACH_FILE
        step_inputs, step_outputs, initial_state = step_state(policy)
        step_shapes = ({0: batch}, {0: batch, 1: slots}, {0: batch, 1: slots}, {0: batch, 1: route}, {0: batch},
                       {0: batch}, {0: batch}) + (({0: batch},) if len(step_inputs) > len(STEP_INPUTS) else ())
        _export_onnx(StepGraph(policy).eval(), _example_step_inputs(policy), step_shapes, step_inputs, step_outputs,
                     out / STEP_FILE)
        files[STEP_FILE] = out / STEP_FILE
    if weights == "int8":
        for path in files.values():
            _quantize(path)
    if not policy.use_memory:
        (out / TEACH_FILE).unlink(missing_ok=True)  # an earlier export's, in the same directory
    config = policy.config.to_dict()
    manifest = {
        "format_version": EXPORT_FORMAT_VERSION,
        "model_type": model_type,
        "model_config": config,
        "weights": weights,
        "sparsity": float(policy.sparsity) if policy.use_memory else None,
        "uses_memory": bool(policy.use_memory),
        "memory_width": memory_width(policy),
        "opset": OPSET,
        "teach": {"inputs": list(TEACH_INPUTS), "outputs": list(TEACH_OUTPUTS)} if policy.use_memory else None,
        "step": {"inputs": list(step_inputs), "outputs": list(step_outputs), "initial_state": initial_state},
        "files": {name: file_sha256(path) for name, path in files.items()},
        "source": {**(source or {}), "policy_sha256": policy_sha256(policy)},
        "versions": _versions(),
    }
    atomic_write_json(out / MANIFEST_NAME, manifest, default=str)
    logger.info("exported %s (%s weights) to %s", model_type, weights, out)
    return manifest


def export_checkpoint(name_or_path: str | os.PathLike, out: str | os.PathLike, weights: str = "fp32",
                      sparsity: float | None = None) -> dict:
    """:func:`export_policy` of a shipped name or checkpoint file (checked as :func:`spf_rl.load_policy`
    checks it); ``sparsity``: a random-sparsity model's default sparsity (otherwise its config's)."""
    from spf_rl.hub import checked_checkpoint, policy_from_checkpoint

    path = checked_checkpoint(name_or_path)
    policy, payload = policy_from_checkpoint(path)
    if sparsity is not None:
        policy.set_sparsity(sparsity)
    return export_policy(policy, out, payload["model_type"], weights, source={"checkpoint": str(name_or_path)})


__all__ = ["EXPORT_FORMAT_VERSION", "STEP_INPUTS", "StepGraph", "step_state", "TEACH_INPUTS", "TeachGraph", "WEIGHT_PRECISIONS",
           "export_checkpoint", "export_policy"]
