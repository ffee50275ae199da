"""Tests for spf_rl.metrics."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from spf_rl.metrics import bootstrap_ci, spl, success, summarize


def test_success_hand_cases():
    # radius = max(2 * 0.3 = 0.6 m, 10% of initial)
    final = [0.6, 0.61, 0.9, 1.0, 1.01, 0.0]
    initial = [2.0, 2.0, 9.0, 10.0, 10.0, 0.0]
    expected = [True, False, True, True, False, True]
    assert success(final, initial).tolist() == expected
    out = success(torch.tensor(final), torch.tensor(initial))
    assert isinstance(out, torch.Tensor) and out.tolist() == expected
    assert bool(success(0.7, 2.0, step_size_m=0.5)) is True  # radius 1.0
    assert bool(success(0.7, 2.0, num_steps=1)) is False  # radius 0.3


def test_spl_hand_cases():
    s = [1, 1, 1, 0, True]
    length = [4.0, 4.0, 4.0, 4.0, 0.0]
    path = [4.0, 8.0, 2.0, 4.0, 0.0]  # shorter-than-shortest path counts as L
    out = spl(s, length, path)
    np.testing.assert_allclose(out, [1.0, 0.5, 1.0, 0.0, 1.0])
    t = spl(torch.tensor([1.0, 1.0]), torch.tensor([3.0, 3.0]), torch.tensor([6.0, 4.0]))
    torch.testing.assert_close(t, torch.tensor([0.5, 0.75], dtype=torch.float64))


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


if __name__ == "__main__":
    pytest.main([__file__, "--capture", "no", "--exitfirst"])
