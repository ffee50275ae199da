"""Success and SPL of an episode (the env's rules, :class:`envs.follow.FollowRules`), and their
summaries (:mod:`spf_rl.metrics`, with :func:`spf_rl.stats.bootstrap_ci`)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from envs.follow import SUCCESS_FRACTION, SUCCESS_RADIUS_M, FollowRules
from spf_rl.metrics import summarize
from spf_rl.stats import bootstrap_ci

#: The follow protocol's rules (paper Sec. 4.1): radius max(2 x 0.3 m, 10% of the initial distance).
RULES = FollowRules(
    max_steps=50, success_radius_m=SUCCESS_RADIUS_M, success_fraction=SUCCESS_FRACTION, stop_action=False,
    progress_reward_per_m=1.0, success_reward=2.5, step_penalty=0.01,
)


def outcome(final, initial, shortest=None, path=None, steps=1):
    """The rules' score of a step that ends ``final`` metres from the route's end."""
    final = np.asarray(final, dtype=np.float64)
    initial = np.asarray(initial, dtype=np.float64)
    return RULES.score(
        action=np.zeros(final.shape, dtype=np.int64), distance_m=final, previous_distance_m=final,
        initial_distance_m=initial, path_length_m=initial if path is None else np.asarray(path, dtype=np.float64),
        shortest_length_m=initial if shortest is None else np.asarray(shortest, dtype=np.float64), steps=steps,
    )


def test_success_hand_cases():
    # radius = max(2 * 0.3 = 0.6 m, 10% of initial)
    assert SUCCESS_RADIUS_M == pytest.approx(0.6) and SUCCESS_FRACTION == 0.1
    final = [0.6, 0.61, 0.9, 1.0, 1.01, 0.0]
    initial = [2.0, 2.0, 9.0, 10.0, 10.0, 0.0]
    assert outcome(final, initial).success.tolist() == [True, False, True, True, False, True]
    # arrival ends the episode; away from the end it goes on until the step limit, which fails it
    assert outcome(final, initial).terminated.tolist() == [True, False, True, True, False, True]
    late = outcome([1.01], [10.0], steps=RULES.max_steps)
    assert late.truncated.tolist() == [True] and late.success.tolist() == [False]


def test_spl_hand_cases():
    # S * L / max(P, L): a path shorter than the shortest counts as L; failures score 0
    shortest = [4.0, 4.0, 4.0, 4.0]
    path = [4.0, 8.0, 2.0, 4.0]
    final = [0.0, 0.0, 0.0, 3.0]
    out = outcome(final, initial=[4.0] * 4, shortest=shortest, path=path)
    np.testing.assert_allclose(out.spl, [1.0, 0.5, 1.0, 0.0])


def test_bootstrap_ci_contains_mean_and_is_deterministic():
    rng = np.random.default_rng(1)
    values = rng.random(50)
    lo, hi = bootstrap_ci(values, seed=3)
    assert lo < values.mean() < hi
    assert (lo, hi) == bootstrap_ci(values, seed=3)
    assert (lo, hi) != bootstrap_ci(values, seed=4)
    lo90, hi90 = bootstrap_ci(values, confidence=0.5, seed=3)
    assert lo < lo90 < hi90 < hi
    assert bootstrap_ci(torch.ones(5)) == (1.0, 1.0)


def test_bootstrap_bad_args():
    with pytest.raises(ValueError, match="confidence"):
        bootstrap_ci([1.0], confidence=1.5)
    with pytest.raises(ValueError, match="num_resamples"):
        bootstrap_ci([1.0], num_resamples=0)


def test_summarize():
    records = [{"success": s, "spl": p} for s, p in [(1, 0.8), (0, 0.0), (1, 1.0), (1, 0.6)]]
    out = summarize(records)
    assert out["episodes"] == 4
    assert out["success"] == pytest.approx(0.75)
    assert out["spl"] == pytest.approx(0.6)
    assert out["success_ci"][0] <= 0.75 <= out["success_ci"][1]
    assert out["spl_ci"][0] <= 0.6 <= out["spl_ci"][1]
    with pytest.raises(KeyError, match="spl"):
        summarize([{"success": 1}])
