"""Summaries of evaluation episodes: mean success and SPL with bootstrap confidence intervals.

What success and SPL of one episode are is defined once, by the env's rules
(:class:`envs.follow.FollowRules`, paper Sec. 4.1; SPL after Anderson et al. 2018,
https://arxiv.org/abs/1807.06757); each episode's record carries them, and this module
only aggregates records (:func:`~spf_rl.stats.bootstrap_ci` for the intervals).
"""
from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from spf_rl.stats import DEFAULT_CONFIDENCE, bootstrap_ci

logger = logging.getLogger(__name__)

__all__ = ["summarize"]

#: Per-episode values summarised beside success and SPL when every record has them: the RPF
#: lab code's success, and how closely the path followed the route (envs.path_fidelity).
OPTIONAL_METRICS = ("success_lab", "ndtw", "sdtw", "path_length_ratio", "wall_hits")
#: Resamples of a run summary's bootstrap intervals (fewer than the studies' ``spf_rl.stats.DEFAULT_NUM_RESAMPLES``:
#: a summary is written after every validation).
SUMMARY_NUM_RESAMPLES = 2000


def summarize(
    records: Iterable[Mapping[str, Any]],
    confidence: float = DEFAULT_CONFIDENCE,
    num_resamples: int = SUMMARY_NUM_RESAMPLES,
    seed: int = 0,
) -> dict[str, Any]:
    """Aggregate per-episode records into mean success, SPL and their bootstrap CIs.

    Args:
        records: one mapping per episode with keys ``"success"`` (bool / 0-1) and
            ``"spl"`` (float).
        confidence (float, optional): CI level. Defaults to 0.95.
        num_resamples (int, optional): bootstrap resamples. Defaults to 2000.
        seed (int, optional): bootstrap seed. Defaults to 0.

    Returns:
        dict with ``episodes``, ``success``, ``success_ci``, ``spl``, ``spl_ci``, and
        ``<key>`` / ``<key>_ci`` for each key of :data:`OPTIONAL_METRICS` that every
        record has (``success_lab``, ``ndtw``, ``sdtw``, ``path_length_ratio``, ``wall_hits``).

    Examples:
        >>> out = summarize([{"success": 1, "spl": 0.8}, {"success": 0, "spl": 0.0}])
        >>> out["episodes"], out["success"], out["spl"]
        (2, 0.5, 0.4)
        >>> summarize([{"success": 1, "spl": 0.8, "ndtw": 0.9}, {"success": 0, "spl": 0.0, "ndtw": 0.5}])["ndtw"]
        0.7
    """
    records = list(records)
    for i, r in enumerate(records):
        missing = {"success", "spl"} - set(r)
        if missing:
            raise KeyError(f"record {i} lacks the keys {sorted(missing)} (needs 'success' and 'spl').")
    s = np.asarray([float(r["success"]) for r in records], dtype=np.float64)
    p = np.asarray([float(r["spl"]) for r in records], dtype=np.float64)
    nan = float("nan")
    summary = {
        "episodes": len(records),
        "success": float(s.mean()) if s.size else nan,
        "success_ci": bootstrap_ci(s, confidence, num_resamples, seed),
        "spl": float(p.mean()) if p.size else nan,
        "spl_ci": bootstrap_ci(p, confidence, num_resamples, seed),
    }
    for key in OPTIONAL_METRICS:
        if records and all(key in r for r in records):
            values = np.asarray([float(r[key]) for r in records], dtype=np.float64)
            summary[key], summary[f"{key}_ci"] = float(values.mean()), bootstrap_ci(values, confidence, num_resamples, seed)
    return summary
