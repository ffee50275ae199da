"""Calibrating the start check (:mod:`spf_rl.modules.replay_gate`): the threshold on the cosine of the
encoder's features of the repeat's first frame and the demonstration's first frame below which an episode
is replayed blind.

A route is repeated from the pose it was taught from, so with the route's own memory the two frames show
the same place: the cosine is near 1 in the teaching world and lower as the world changes (light, paint,
furniture, camera, sensor). With another route's frames the two places differ and the cosine is low. On
episodes of the validation houses, :func:`start_cosines` measures it for the route's own memory under
each condition and strength, and for a mismatched memory; :func:`calibrate` picks the threshold that
catches the most mismatched memories while it flags at most 5% of the route's own under any condition
(:data:`MAX_FALSE_ALARM`; a flagged episode is replayed blind, which under a changed world does worse
than the network, so the flags are capped where the conditions' targets are tight). The first frame depends on
the route's start alone, so one episode per start suffices: no policy is rolled out.

``recipes/start_check.py`` is the command line: it writes the checkpoint with ``start_check`` set and the
measurement's JSON.
"""
from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from envs.nav_env import PathFollowEnv
from spf_rl.modules.policy import SPFPolicy

logger = logging.getLogger(__name__)

#: The conditions the route's own memory is measured under by default (each at both strengths).
CHECK_CONDITIONS = ("light", "paint", "furniture", "camera", "sensor")
CHECK_STRENGTHS = (0.5, 1.0)
#: Episodes reset at once.
BATCH = 16
#: The share of the route's own memories the threshold may flag under any one condition (:func:`calibrate`).
MAX_FALSE_ALARM = 0.05
#: Percentiles written for each measured set.
PERCENTILES = (2, 10, 50, 90, 98)


def start_cosines(policy: SPFPolicy, split: str, episodes: int, seed: int, condition: str = "none",
                  mismatch: bool = False) -> np.ndarray:
    """The cosine of the encoder's features of the agent's first frame and of the demonstration's first
    frame (which the memory's first slot holds), for the first ``episodes`` episodes of ``split`` from
    env seed ``seed``, under ``condition`` (a name of :mod:`envs.conditions`, ``"light@1"``), with the
    route's own memory or (``mismatch``) another route's.

    Examples:
        >>> from spf_rl.modules import SPFConfig
        >>> policy = SPFPolicy(SPFConfig(feature_dim=8, hidden_size=8)).eval()
        >>> cosines = start_cosines(policy, "val", episodes=4, seed=0)
        >>> cosines.shape, bool(np.allclose(cosines, 1.0, atol=1e-5))  # the teaching world: the same frame
        ((4,), True)
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes!r}.")
    encoder = policy.encoder.module
    batch = min(BATCH, episodes)
    height, width = policy.config.image_size
    if height != width:
        raise ValueError(f"the env renders square frames; this policy reads {height}x{width}.")
    env = PathFollowEnv(split, image_size=height, conditions=condition,
                        memory_mismatch=1.0 if mismatch else None, num_agents=batch)
    env.set_seed(seed)
    out: list[float] = []
    try:
        with torch.no_grad():
            while len(out) < episodes:
                td = env.reset()
                first = encoder(td["pixels"].to(next(policy.parameters()).device))
                taught = encoder(td["demo_frames"][:, 0].to(first.device))
                out += F.cosine_similarity(first, taught, dim=-1, eps=1e-8).cpu().tolist()
    finally:
        env.close()
    return np.asarray(out[:episodes], dtype=np.float64)


def calibrate(own: dict[str, np.ndarray], mismatched: np.ndarray, max_false_alarm: float = MAX_FALSE_ALARM) -> tuple[float, dict]:
    """The threshold that catches the most mismatched memories (``mismatched``: their start cosines) while it
    flags at most ``max_false_alarm`` of the route's own memories under every condition (``own``: the start
    cosines under each), and what it catches.

    The candidates are the midpoints between consecutive distinct cosines (and one below them all, which
    flags nothing); the highest that keeps every condition's flagged share within ``max_false_alarm`` wins.
    A false alarm costs what the network does better than blind replay under that condition, so it is
    capped per condition rather than traded against the catches.

    Returns:
        ``(threshold, stats)``: ``stats`` holds ``mismatch_caught``, ``false_alarms`` per condition, their
        maximum and ``max_false_alarm``.

    Examples:
        >>> threshold, stats = calibrate({"none": np.array([1.0, 0.99]), "light@1": np.array([0.9, 0.6, 0.95, 0.97])},
        ...                              np.array([0.2, 0.3, 0.5, 0.7]), max_false_alarm=0.25)
        >>> round(threshold, 3), stats["mismatch_caught"], stats["false_alarms"]["light@1"]  # flags 0.6, one in four
        (0.8, 1.0, 0.25)
        >>> round(calibrate({"none": np.array([1.0, 0.99]), "light@1": np.array([0.9, 0.6, 0.95, 0.97])},
        ...                 np.array([0.2, 0.3, 0.5, 0.7]), max_false_alarm=0.0)[0], 3)  # flags none
        0.55
    """
    if not 0.0 <= max_false_alarm < 1.0:
        raise ValueError(f"max_false_alarm must be in [0, 1), got {max_false_alarm!r}.")
    if not own or any(len(values) == 0 for values in own.values()) or len(mismatched) == 0:
        raise ValueError("calibrate needs start cosines of the route's own memory under at least one condition and of a mismatched memory.")
    values = np.unique(np.concatenate([*own.values(), mismatched]))
    candidates = np.concatenate([[values[0] - 1e-3], (values[:-1] + values[1:]) / 2])
    caught = (mismatched[None, :] < candidates[:, None]).mean(1)
    flagged = np.stack([(cosines[None, :] < candidates[:, None]).mean(1) for cosines in own.values()])  # [conditions, candidates]
    allowed = np.flatnonzero(flagged.max(0) <= max_false_alarm)  # never empty: the lowest candidate flags nothing
    best = int(allowed[-1])
    stats = {
        "mismatch_caught": float(caught[best]),
        "false_alarms": {name: float(row[best]) for name, row in zip(own, flagged)},
        "worst_false_alarm": float(flagged[:, best].max()),
        "max_false_alarm": float(max_false_alarm),
    }
    return float(candidates[best]), stats


def measure(policy: SPFPolicy, split: str = "val", episodes: int = 128, seed: int = 0,
            conditions: Sequence[str] = CHECK_CONDITIONS, strengths: Sequence[float] = CHECK_STRENGTHS,
            max_false_alarm: float = MAX_FALSE_ALARM) -> dict:
    """Start cosines on ``split`` (the route's own memory in the teaching world and under each condition at
    each strength; another route's memory in the teaching world), the calibrated threshold and its stats."""
    own = {"none": start_cosines(policy, split, episodes, seed)}
    for name in conditions:
        for strength in strengths:
            key = f"{name}@{strength:g}"
            own[key] = start_cosines(policy, split, episodes, seed, condition=key)
            logger.info("start cosines under %s: median %.3f", key, float(np.median(own[key])))
    mismatched = start_cosines(policy, split, episodes, seed, mismatch=True)
    threshold, stats = calibrate(own, mismatched, max_false_alarm)
    logger.info("start check threshold %.4f: catches %.3f of mismatched memories, flags at most %.3f of the route's own",
                threshold, stats["mismatch_caught"], stats["worst_false_alarm"])
    percentiles = {name: np.percentile(values, PERCENTILES).round(4).tolist() for name, values in {**own, "mismatch": mismatched}.items()}
    return {"split": split, "episodes": episodes, "seed": seed, "threshold": threshold, **stats,
            "percentiles": {"at": list(PERCENTILES), **percentiles}}


__all__ = ["CHECK_CONDITIONS", "CHECK_STRENGTHS", "MAX_FALSE_ALARM", "calibrate", "measure", "start_cosines"]
