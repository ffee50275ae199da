"""Evaluation metrics for path following: success, SPL and bootstrap confidence intervals.

Success (paper Sec. 4.1): the agent ends within 2 steps (2 x 0.3 m) or 10% of
the initial distance to the goal, whichever is larger. SPL (Anderson et al. 2018,
https://arxiv.org/abs/1807.06757) is ``S * L / max(P, L)`` with ``L`` the geodesic
shortest-path length and ``P`` the length the agent travelled.
"""
from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
import torch

logger = logging.getLogger(__name__)

__all__ = ["bootstrap_ci", "spl", "success", "summarize"]

#: Forward step length of the agent, in metres.
STEP_SIZE_M = 0.3
#: Success radius in steps.
SUCCESS_NUM_STEPS = 2
#: Success radius as a fraction of the initial distance.
SUCCESS_FRACTION = 0.1
#: Tolerance on the success radius, in metres, so that float32 distances exactly on
#: the radius (e.g. 0.6 m stored as 0.60000002) count as successes.
DISTANCE_TOLERANCE_M = 1e-6
DEFAULT_CONFIDENCE = 0.95
DEFAULT_NUM_RESAMPLES = 2000


def _as_float(x: Any) -> torch.Tensor | np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.to(torch.float64) if not x.is_floating_point() else x
    return np.asarray(x, dtype=np.float64)


def success(
    final_distance_m: Any,
    initial_distance_m: Any,
    step_size_m: float = STEP_SIZE_M,
    num_steps: int = SUCCESS_NUM_STEPS,
    fraction: float = SUCCESS_FRACTION,
) -> Any:
    """Success flag: ``final <= max(num_steps * step_size, fraction * initial)``.

    The comparison allows ``DISTANCE_TOLERANCE_M`` (1 micrometre) for float rounding.

    Vectorised over tensors, arrays or scalars (returns a bool tensor / array).

    Args:
        final_distance_m: distance to the goal at the end of the episode, in metres.
        initial_distance_m: distance to the goal at the start, in metres.
        step_size_m (float, optional): forward step length, metres. Defaults to 0.3.
        num_steps (int, optional): success radius in steps. Defaults to 2.
        fraction (float, optional): success radius as a fraction of the initial
            distance. Defaults to 0.1.

    Examples:
        >>> success([0.5, 0.7, 1.0], [3.0, 3.0, 12.0]).tolist()
        [True, False, True]
    """
    final = _as_float(final_distance_m)
    initial = _as_float(initial_distance_m)
    fixed = num_steps * step_size_m
    if isinstance(final, torch.Tensor) or isinstance(initial, torch.Tensor):
        final = torch.as_tensor(final, dtype=torch.float64)
        initial = torch.as_tensor(initial, dtype=torch.float64)
        radius = torch.clamp(fraction * initial, min=fixed)
        return final <= radius + DISTANCE_TOLERANCE_M
    radius = np.maximum(fixed, fraction * initial)
    return final <= radius + DISTANCE_TOLERANCE_M


def spl(success: Any, shortest_length_m: Any, path_length_m: Any) -> Any:
    """Success weighted by (normalised inverse) path length: ``S * L / max(P, L)``.

    Args:
        success: success flags (bool or 0/1).
        shortest_length_m: geodesic shortest-path length ``L``, metres.
        path_length_m: length ``P`` actually travelled, metres.

    Examples:
        >>> spl([1, 1, 0], [3.0, 3.0, 3.0], [3.0, 6.0, 3.0]).tolist()
        [1.0, 0.5, 0.0]
    """
    s, length, path = (_as_float(x) for x in (success, shortest_length_m, path_length_m))
    if any(isinstance(x, torch.Tensor) for x in (s, length, path)):
        s, length, path = (torch.as_tensor(x, dtype=torch.float64) for x in (s, length, path))
        denom = torch.maximum(path, length)
        return torch.where(denom > 0, s * length / denom.clamp(min=1e-12), s)
    denom = np.maximum(path, length)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(denom > 0, s * length / np.where(denom > 0, denom, 1.0), s)


def bootstrap_ci(
    values: Any,
    confidence: float = DEFAULT_CONFIDENCE,
    num_resamples: int = DEFAULT_NUM_RESAMPLES,
    seed: int = 0,
) -> tuple[float, float]:
    """Percentile bootstrap confidence interval of the mean (deterministic given ``seed``).

    Args:
        values: 1-d sample (tensor, array or sequence).
        confidence (float, optional): confidence level in ``(0, 1)``. Defaults to 0.95.
        num_resamples (int, optional): number of bootstrap resamples. Defaults to 2000.
        seed (int, optional): seed of the numpy generator. Defaults to 0.

    Returns:
        (low, high) as floats; ``(nan, nan)`` for an empty sample.

    Examples:
        >>> lo, hi = bootstrap_ci([0.0, 1.0, 1.0, 0.0, 1.0])
        >>> lo <= 0.6 <= hi
        True
    """
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence!r}.")
    if num_resamples < 1:
        raise ValueError(f"num_resamples must be a positive int, got {num_resamples!r}.")
    if isinstance(values, torch.Tensor):
        values = values.detach().cpu().double().numpy()
    x = np.asarray(values, dtype=np.float64).reshape(-1)
    if x.size == 0:
        return float("nan"), float("nan")
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, x.size, size=(num_resamples, x.size))
    means = x[idx].mean(axis=1)
    alpha = (1.0 - confidence) / 2.0
    low, high = np.quantile(means, [alpha, 1.0 - alpha])
    return float(low), float(high)


def summarize(
    records: Iterable[Mapping[str, Any]],
    confidence: float = DEFAULT_CONFIDENCE,
    num_resamples: int = DEFAULT_NUM_RESAMPLES,
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
        ``success_lab`` / ``success_lab_ci`` when every record has ``"success_lab"``.

    Examples:
        >>> out = summarize([{"success": 1, "spl": 0.8}, {"success": 0, "spl": 0.0}])
        >>> out["episodes"], out["success"], out["spl"]
        (2, 0.5, 0.4)
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
    if records and all("success_lab" in r for r in records):  # the RPF lab code's criterion, beside ours
        lab = np.asarray([float(r["success_lab"]) for r in records], dtype=np.float64)
        summary["success_lab"], summary["success_lab_ci"] = float(lab.mean()), bootstrap_ci(lab, confidence, num_resamples, seed)
    return summary
