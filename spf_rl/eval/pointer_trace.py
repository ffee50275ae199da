"""Where a route-following policy fails: its pointer against the agent's place on the route
(``recipes/pointer_trace.py`` is the command line).

A policy with RPF's pointer rule (``pointer_update="rpf"``) keeps ``eta``, the
demonstration step it believes the agent is at, and attends to the memory around it.
This module plays routes of one style with such a policy and records, at every step:

* ``pointer``: the ``eta_used`` of the step, demonstration steps;
* ``route_step``: where the agent really is along the route, the demonstration step
  of :meth:`envs.route_expert.RouteExpert.route_step` (a progress index that only moves
  forward, so a route over the same place twice is counted in its order);
* ``off_path_m``: the agent's distance to the demonstrated path (the polyline through
  its positions), metres;
* ``anchor`` (a policy with an anchor, :mod:`spf_rl.modules.anchor`): the route step the frame
  matched near the pointer, and ``anchor_confidence``, how well.

The routes may be repeated in a changed world (``conditions``, ``memory_mismatch``: :mod:`envs.conditions`).

:func:`summarize_traces` reduces them to what decides the next change: whether failures
leave the path while the pointer still points at the right place (the memory was there;
the action was wrong: data or training), or after the pointer has drifted from the agent's
place by more than the attention window (the pointer rule or the window ``k``), or never
leave it and run out of steps (too slow: the step limit or the pointer's pace).

* :func:`distance_to_path`: a point's distance to a polyline;
* :func:`trace_routes`: play the routes of one style, return one :class:`Trace` per episode;
* :func:`summarize_traces`: the summary, per outcome;
* :func:`plot_traces`: pointer and route step over time for a few episodes of each outcome.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from envs.episode_spec import EpisodeSpec
from envs.episodes import episode_record
from envs.factory import make_env
from envs.follow import SUCCESS_RADIUS_M, default_max_steps
from envs.route_expert import RouteExpert
from spf_rl.evaluation import greedy_on_device
from spf_rl.modules.replay_gate import replay_score

logger = logging.getLogger(__name__)

#: A failure "left the path" at its first step farther than this from the demonstrated path, metres.
OFF_PATH_M = SUCCESS_RADIUS_M
#: Episodes of each outcome drawn by :func:`plot_traces`.
PLOTTED_PER_OUTCOME = 4

@dataclass
class Trace:
    """One episode of a policy on a route.

    Attributes:
        record: :func:`~envs.episodes.episode_record`'s keys (``success``, ``ndtw``, ``demo_steps``, ...).
        pointer: ``(T,)`` the pointer the policy used at each step, demonstration steps.
        route_step: ``(T,)`` the demonstration step the agent was at before each step.
        off_path_m: ``(T,)`` the agent's distance to the demonstrated path before each step, metres.
        anchor: ``(T,)`` the anchor's route step at each step (``None``: the policy has no anchor).
        anchor_confidence: ``(T,)`` its confidence (``None``: no anchor).
        replay_opening: ``(T,)`` the replay gate's opening at each step, 0 (the network) to 1 (blind
            replay; :mod:`spf_rl.modules.replay_gate`; ``None``: no gate).
    """

    record: dict
    pointer: np.ndarray
    route_step: np.ndarray
    off_path_m: np.ndarray
    anchor: np.ndarray | None = None
    anchor_confidence: np.ndarray | None = None
    replay_opening: np.ndarray | None = None

    @property
    def left_path_at(self) -> int | None:
        """The first step farther than :data:`OFF_PATH_M` from the path (``None``: never)."""
        far = np.flatnonzero(self.off_path_m > OFF_PATH_M)
        return int(far[0]) if len(far) else None

def distance_to_path(xy: np.ndarray, path_xy: np.ndarray) -> float:
    """Distance, metres, from the point ``xy`` to the polyline through ``path_xy`` (``(N, 2)``, N >= 1).

    Examples:
        >>> path = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]])
        >>> distance_to_path(np.array([0.5, 0.2]), path), distance_to_path(np.array([2.0, 1.0]), path)
        (0.2, 1.0)
    """
    xy, path_xy = np.asarray(xy, dtype=np.float64), np.asarray(path_xy, dtype=np.float64)
    if len(path_xy) == 1:
        return float(np.hypot(*(xy - path_xy[0])))
    start, end = path_xy[:-1], path_xy[1:]
    segment = end - start
    length2 = np.einsum("ij,ij->i", segment, segment)
    along = np.clip(np.einsum("ij,ij->i", xy - start, segment) / np.where(length2 > 0, length2, 1.0), 0.0, 1.0)
    nearest = start + along[:, None] * segment
    return float(np.hypot(*(nearest - xy).T).min())

def check_rpf_pointer(policy) -> None:
    """Raise ``ValueError`` unless ``policy`` keeps its pointer in demonstration steps (RPF's rule)."""
    config = getattr(policy, "config", None)
    if getattr(config, "pointer_update", None) != "rpf":
        raise ValueError(
            "policy must use RPF's pointer rule (config.pointer_update == 'rpf'), whose pointer counts "
            f"demonstration steps; got pointer_update={getattr(config, 'pointer_update', None)!r}."
        )

def trace_routes(
    policy,
    *,
    style: str,
    route_lengths: tuple[int, int],
    episodes: int,
    split: str = "test",
    noise: str = "paper",
    seed: int = 0,
    conditions: str | None = None,
    memory_mismatch: float | None = None,
) -> list[Trace]:
    """Play ``episodes`` routes of ``style`` (one agent each, stepped together) with the greedy policy.

    Args:
        policy: an SPF-family policy with RPF's pointer rule (:func:`spf_rl.load_policy`), in eval mode;
            its ``demo_length`` must be at least ``route_lengths[1]``.
        style: a route style (:mod:`envs.route_styles`).
        route_lengths: ``(shortest, longest)`` steps of the routes.
        episodes: routes played (the env's first episode of each agent).
        split: house split.
        noise: actuation-noise preset.
        seed: env seed: the same seed gives the same routes and noise.
        conditions: the repeat's world (:mod:`envs.conditions`; ``None``: the teaching world).
        memory_mismatch: the fraction of episodes shown another route's frames (``None``: none).

    Returns:
        One :class:`Trace` per agent, in agent order.
    """
    check_rpf_pointer(policy)
    demo_length = int(policy.config.demo_length)
    spec = EpisodeSpec(
        split=split, noise=noise, demo_length=demo_length, route_style=style, route_lengths=route_lengths,
        image_size=tuple(policy.config.image_size)[0], seed=seed, conditions=conditions, memory_mismatch=memory_mismatch,
    )
    env = make_env(spec, episodes, primer=policy.make_tensordict_primer(), seeded=True)
    base = env.base_env
    max_steps = default_max_steps(route_lengths[1])
    try:
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            start = env.reset()
            demos, houses = base.demonstrations, base.houses  # before any agent starts a second episode
            rollout = env.rollout(
                max_steps, greedy_on_device(policy), auto_reset=False, tensordict=start,
                break_when_any_done=False, return_contiguous=False,
            )
    finally:
        env.close()
    done = rollout.get(("next", "done")).reshape(episodes, -1)
    pointer = rollout.get("eta_used").reshape(episodes, -1).numpy()
    anchors = "anchor" in rollout.keys()
    if anchors:
        anchor = rollout.get("anchor").reshape(episodes, -1).numpy()
        confidence = rollout.get("anchor_confidence").reshape(episodes, -1).numpy()
    gate = getattr(getattr(policy, "cell", None), "replay_gate", None)
    if gate is not None:  # the gate's opening, from the step's new hidden state and the anchor's confidence
        with torch.no_grad():
            score = replay_score(rollout.get("features").reshape(-1, policy.config.hidden_size).to(next(gate.parameters()).device),
                                 rollout.get("anchor_confidence").reshape(-1, 1).to(next(gate.parameters()).device), gate)
        opening = torch.sigmoid(score).reshape(episodes, -1).cpu().numpy()
    poses = rollout.get("pose").reshape(episodes, -1, 3).numpy().astype(np.float64)
    traces = []
    for agent in range(episodes):
        last = int(torch.nonzero(done[agent])[0, 0])
        expert = RouteExpert(houses[agent], demos[agent])
        path_xy = demos[agent].poses[:, :2]
        agent_poses = poses[agent, : last + 1]

        traces.append(
            Trace(
                record=episode_record(rollout[agent, last].get("next")),
                pointer=pointer[agent, : last + 1].astype(np.float64),
                route_step=np.array([expert.route_step(pose) for pose in agent_poses]),
                off_path_m=np.array([distance_to_path(pose[:2], path_xy) for pose in agent_poses]),
                anchor=anchor[agent, : last + 1].astype(np.float64) if anchors else None,
                anchor_confidence=confidence[agent, : last + 1].astype(np.float64) if anchors else None,
                replay_opening=opening[agent, : last + 1].astype(np.float64) if gate is not None else None,
            )
        )
    return traces

def _mean(values: list[float]) -> float | None:
    return float(np.mean(values)) if values else None

def summarize_traces(traces: list[Trace], window: int) -> dict:
    """What the traces say, per outcome (``"success"``, ``"failure"``).

    Args:
        traces: :func:`trace_routes`' output.
        window: the policy's attention window half-width ``k``, demonstration steps.

    Returns:
        ``{outcome: {...}}`` with ``episodes``; ``mean_abs_pointer_error`` (steps, over every
        step); ``mean_pointer_lead`` (pointer minus route step, over every step: > 0 ahead);
        for failures also ``left_path`` (the fraction that went farther than
        :data:`OFF_PATH_M` from the path), and of those ``pointer_error_at_leaving`` (mean
        absolute steps), ``pointer_outside_window_at_leaving`` (the fraction off by more than
        ``window``) and ``route_fraction_at_leaving`` (mean route step over route length); for a
        policy with an anchor, ``mean_abs_anchor_error`` (steps) and ``mean_anchor_confidence``; with a
        replay gate, ``mean_replay_opening``.

    Examples:
        >>> on = Trace({"success": True, "demo_steps": 10}, np.arange(5.0), np.arange(5), np.zeros(5))
        >>> off = Trace({"success": False, "demo_steps": 10}, np.full(4, 6.0), np.array([0, 1, 2, 2]),
        ...             np.array([0.0, 0.1, 0.7, 0.9]))
        >>> out = summarize_traces([on, off], window=2)
        >>> out["success"]["mean_abs_pointer_error"], out["failure"]["left_path"]
        (0.0, 1.0)
        >>> out["failure"]["pointer_error_at_leaving"], out["failure"]["pointer_outside_window_at_leaving"]
        (4.0, 1.0)
    """
    out: dict = {}
    for outcome, wanted in (("success", True), ("failure", False)):
        group = [t for t in traces if bool(t.record["success"]) == wanted]
        errors = [float(e) for t in group for e in np.abs(t.pointer - t.route_step)]
        leads = [float(e) for t in group for e in t.pointer - t.route_step]
        summary = {"episodes": len(group), "mean_abs_pointer_error": _mean(errors), "mean_pointer_lead": _mean(leads)}
        anchored = [t for t in group if t.anchor is not None]
        if anchored:  # how far the frame's match is from the agent's place, and how sure it was
            summary["mean_abs_anchor_error"] = _mean([float(e) for t in anchored for e in np.abs(t.anchor - t.route_step)])
            summary["mean_anchor_confidence"] = _mean([float(c) for t in anchored for c in t.anchor_confidence])
        gated = [t for t in group if t.replay_opening is not None]
        if gated:  # how far the policy leaned on blind replay
            summary["mean_replay_opening"] = _mean([float(r) for t in gated for r in t.replay_opening])
        if not wanted:
            left = [t for t in group if t.left_path_at is not None]
            at = [abs(t.pointer[t.left_path_at] - t.route_step[t.left_path_at]) for t in left]
            summary.update({
                "left_path": len(left) / len(group) if group else None,
                "pointer_error_at_leaving": _mean([float(a) for a in at]),
                "pointer_outside_window_at_leaving": _mean([float(a > window) for a in at]),
                "route_fraction_at_leaving": _mean(
                    [float(t.route_step[t.left_path_at] / max(t.record["demo_steps"], 1)) for t in left]
                ),
            })
        out[outcome] = summary
    return out

def plot_traces(traces_by_style: dict[str, list[Trace]], path: str | Path) -> Path:
    """Pointer (solid) and route step (dashed) over time: a row per style, a column per outcome."""
    from spf_rl.viz import pyplot, write_figure

    plt = pyplot()
    styles = list(traces_by_style)
    fig, axes = plt.subplots(len(styles), 2, figsize=(9, 2.6 * len(styles)), squeeze=False)
    for row, style in enumerate(styles):
        for col, (outcome, wanted) in enumerate((("success", True), ("failure", False))):
            ax = axes[row, col]
            group = [t for t in traces_by_style[style] if bool(t.record["success"]) == wanted][:PLOTTED_PER_OUTCOME]
            for index, trace in enumerate(group):
                colour = f"C{index}"
                ax.plot(trace.pointer, color=colour)
                ax.plot(trace.route_step, color=colour, linestyle="--")
                if trace.left_path_at is not None:
                    ax.axvline(trace.left_path_at, color=colour, linestyle=":")
            ax.set_title(f"{style}: {outcome} ({len(group)} shown)", fontsize=9)
            ax.set_xlabel("step")
            ax.set_ylabel("demonstration step")
    fig.suptitle("pointer (solid) vs the agent's place on the route (dashed); dotted: left the path", fontsize=9)
    fig.tight_layout()
    return write_figure(fig, path, dpi=100)
