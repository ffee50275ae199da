"""Tests for spf_rl.stats: seed summaries, house-level bootstrap intervals, paired bootstrap tests."""
from __future__ import annotations

import time

import numpy as np
import pytest

from spf_rl.stats import bootstrap_ci, hierarchical_bootstrap_ci, paired_bootstrap, seed_summary

HOUSES = np.repeat(np.arange(18), 50)  # 900 episodes in 18 houses, as the test split has


def house_effect_scores(rng: np.random.Generator, spread: float, seeds: int = 3) -> np.ndarray:
    """0/1 outcomes (seeds, episodes) whose success rate varies from house to house by ``spread``."""
    rate = np.clip(0.5 + spread * (rng.random(18) - 0.5), 0.0, 1.0)[HOUSES]
    return (rng.random((seeds, HOUSES.size)) < rate).astype(float)


def test_seed_summary_is_the_mean_and_sample_sd():
    summary = seed_summary(np.array([0.70, 0.74, 0.81]))
    assert summary.mean == pytest.approx(0.75)
    assert summary.sd == pytest.approx(np.std([0.70, 0.74, 0.81], ddof=1))  # not ddof=0
    assert summary.num_seeds == 3
    assert seed_summary([0.5]).sd is None


def test_hierarchical_interval_with_one_episode_per_house_is_the_flat_bootstrap():
    rng = np.random.default_rng(0)
    scores = (rng.random(1000) < 0.6).astype(float)
    low, high = hierarchical_bootstrap_ci(scores, np.arange(1000), num_resamples=4000)
    flat_low, flat_high = bootstrap_ci(scores, num_resamples=4000)
    assert low < scores.mean() < high
    assert high - low == pytest.approx(flat_high - flat_low, rel=0.1)


def test_hierarchical_interval_is_wider_when_houses_differ():
    rng = np.random.default_rng(1)
    scores = house_effect_scores(rng, spread=1.0)
    low, high = hierarchical_bootstrap_ci(scores, HOUSES, num_resamples=4000)
    flat_low, flat_high = hierarchical_bootstrap_ci(scores, np.arange(HOUSES.size), num_resamples=4000)
    assert high - low > 2.0 * (flat_high - flat_low)
    assert low < scores.mean() < high
    # houses that do not differ: resampling at both levels counts the episode noise twice
    # (about sqrt(2) wider); resampling houses only agrees with the flat interval
    same = house_effect_scores(rng, spread=0.0)
    low, high = hierarchical_bootstrap_ci(same, HOUSES, num_resamples=4000)
    flat_low, flat_high = hierarchical_bootstrap_ci(same, np.arange(HOUSES.size), num_resamples=4000)
    assert 1.2 < (high - low) / (flat_high - flat_low) < 1.7
    low, high = hierarchical_bootstrap_ci(same, HOUSES, num_resamples=4000, within=False)
    assert high - low == pytest.approx(flat_high - flat_low, rel=0.2)


def test_hierarchical_interval_covers_the_true_mean_at_about_its_level():
    """Coverage over 60 simulated test sets with a strong house effect: near 95%, far above the flat one's."""
    rng = np.random.default_rng(2)
    covered, flat_covered = 0, 0
    for _ in range(60):
        rates = np.clip(0.5 + 0.8 * (rng.random(18) - 0.5), 0, 1)  # true mean 0.5 over houses
        scores = (rng.random(HOUSES.size) < rates[HOUSES]).astype(float)
        low, high = hierarchical_bootstrap_ci(scores, HOUSES, num_resamples=1000, seed=3)
        flat_low, flat_high = hierarchical_bootstrap_ci(scores, np.arange(HOUSES.size), num_resamples=1000, seed=3)
        covered += low <= 0.5 <= high
        flat_covered += flat_low <= 0.5 <= flat_high
    assert covered >= 50 and flat_covered < covered


def test_bootstraps_are_deterministic_given_the_seed():
    rng = np.random.default_rng(4)
    a, b = house_effect_scores(rng, 0.5), house_effect_scores(rng, 0.5)
    assert paired_bootstrap(a, b, HOUSES, seed=7) == paired_bootstrap(a, b, HOUSES, seed=7)
    assert hierarchical_bootstrap_ci(a, HOUSES, seed=7) == hierarchical_bootstrap_ci(a, HOUSES, seed=7)
    assert hierarchical_bootstrap_ci(a, HOUSES, seed=7) != hierarchical_bootstrap_ci(a, HOUSES, seed=8)


def test_a_constant_paired_gain_is_found_with_its_size():
    rng = np.random.default_rng(5)
    b = house_effect_scores(rng, 1.0) * 0.8
    result = paired_bootstrap(b + 0.1, b, HOUSES)
    assert result.difference == pytest.approx(0.1)
    assert result.ci == pytest.approx((0.1, 0.1))
    assert result.p_greater == 0.0 and result.p_two_sided == 0.0
    # the other way round: "a > b" is refused
    assert paired_bootstrap(b, b + 0.1, HOUSES).p_greater == 1.0


def test_identical_policies_show_no_difference():
    rng = np.random.default_rng(6)
    a = house_effect_scores(rng, 1.0)
    result = paired_bootstrap(a, a.copy(), HOUSES)
    assert result.difference == 0.0 and result.ci == (0.0, 0.0)
    assert result.p_two_sided == 1.0


def test_equal_policies_with_noise_are_not_called_different():
    """Two independent draws of the same success rates: p is not small, and near 0.5 on average."""
    rng = np.random.default_rng(7)
    p_values = []
    for _ in range(20):
        a, b = house_effect_scores(rng, 1.0), house_effect_scores(rng, 1.0)
        p_values.append(paired_bootstrap(a, b, HOUSES, num_resamples=1000).p_greater)
    assert 0.3 < np.mean(p_values) < 0.7
    assert sum(p < 0.05 for p in p_values) <= 3


def test_pairing_makes_a_small_gain_detectable():
    """A gain of 0.05 on top of large shared house effects: the paired test finds it, unpaired CIs overlap."""
    rng = np.random.default_rng(8)
    base = np.clip(0.5 + 1.2 * (rng.random(18) - 0.5), 0, 1)[HOUSES]
    uniforms = rng.random((3, HOUSES.size))
    b = (uniforms < base).astype(float)
    a = (uniforms < base + 0.05).astype(float)  # same episodes: a succeeds wherever b does
    result = paired_bootstrap(a, b, HOUSES)
    assert result.p_greater < 0.05 and result.ci[0] > 0
    a_low, _ = hierarchical_bootstrap_ci(a, HOUSES)
    _, b_high = hierarchical_bootstrap_ci(b, HOUSES)
    assert a_low < b_high


def test_seeds_may_differ_between_the_two_sides():
    rng = np.random.default_rng(9)
    a = house_effect_scores(rng, 0.5, seeds=3)
    b = house_effect_scores(rng, 0.5, seeds=1)
    result = paired_bootstrap(a, list(b), HOUSES)
    assert result.difference == pytest.approx(a.mean() - b.mean())
    assert result.num_episodes == HOUSES.size and result.num_groups == 18


def test_ten_thousand_resamples_of_a_thousand_episodes_are_fast():
    rng = np.random.default_rng(10)
    houses = rng.integers(0, 18, 1000)
    a, b = rng.random((3, 1000)), rng.random((3, 1000))
    start = time.perf_counter()
    paired_bootstrap(a, b, houses, num_resamples=10_000)
    hierarchical_bootstrap_ci(a, houses, num_resamples=10_000)
    assert time.perf_counter() - start < 4.0  # well under 1 s each on an idle core


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: paired_bootstrap(np.ones((3, 10)), np.ones((3, 9)), np.arange(10)), "a and b must hold the same episodes"),
        (lambda: paired_bootstrap(np.ones(10), np.ones(10), np.arange(9)), "groups must give one group per episode"),
        (lambda: paired_bootstrap([], [], []), "a is empty"),
        (lambda: paired_bootstrap(np.ones(4), [1, 1, np.nan, 1], np.arange(4)), "b holds 1 non-finite"),
        (lambda: paired_bootstrap(np.ones((2, 2, 2)), np.ones(2), np.arange(2)), "a must have shape"),
        (lambda: paired_bootstrap([[1, 0], [1]], np.ones(2), np.arange(2)), "a must be numbers"),
        (lambda: hierarchical_bootstrap_ci([1.0, np.inf], [0, 1]), "values holds 1 non-finite"),
        (lambda: hierarchical_bootstrap_ci([1.0, 0.0], [0, 1], confidence=95), "confidence must be in"),
        (lambda: hierarchical_bootstrap_ci([1.0, 0.0], [0, 1], num_resamples=0), "num_resamples must be"),
        (lambda: seed_summary([]), "per_seed_means is empty"),
        (lambda: seed_summary([[0.5, 0.6]]), "per_seed_means must be one score per seed"),
    ],
)
def test_bad_input_is_refused_with_the_parameter_named(call, match):
    with pytest.raises(ValueError, match=match):
        call()
