"""Statistics for comparing policies scored on shared episodes: seed summaries, house-level
bootstrap confidence intervals and paired bootstrap tests.

Every policy evaluated with the same :class:`~spf_rl.evaluation.EvalConfig` plays
the same episodes, so two policies can be compared episode by episode (a paired test),
which is far more sensitive than comparing two independent means. The episodes are
not independent draws, though: they come from a handful of houses (18 in the test
split), and episodes of one house succeed or fail together. The bootstraps here are
therefore hierarchical: they resample houses with replacement, then episodes with
replacement within each resampled house, so that the intervals cover the variation
between houses as well as between episodes.

Results of several training seeds of one model are pooled: each episode's value is the
mean over seeds (all seeds play the same episodes), and seeds themselves are not
resampled (with three seeds that would say little); their spread is reported apart,
by :func:`seed_summary`.

All functions take a seed and use their own :class:`numpy.random.Generator`, so their
results are deterministic.
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

logger = logging.getLogger(__name__)

__all__ = ["PairedResult", "SeedSummary", "bootstrap_ci", "hierarchical_bootstrap_ci", "paired_bootstrap", "seed_summary"]

#: Defaults of the bootstraps.
DEFAULT_CONFIDENCE = 0.95
DEFAULT_NUM_RESAMPLES = 10_000
#: Resamples drawn at once (bounds the memory: about 40 bytes per resampled episode).
CHUNK_RESAMPLES = 1_000


@dataclass(frozen=True)
class SeedSummary:
    """Mean and sample standard deviation of per-seed scores.

    Attributes:
        mean: mean over seeds.
        sd: sample standard deviation (``ddof=1``); ``None`` for a single seed.
        num_seeds: number of seeds.
    """

    mean: float
    sd: float | None
    num_seeds: int


@dataclass(frozen=True)
class PairedResult:
    """A paired bootstrap comparison of ``a`` against ``b`` (see :func:`paired_bootstrap`).

    Attributes:
        difference: mean(a) - mean(b), over seeds and episodes.
        ci: its ``confidence`` bootstrap interval ``(low, high)``.
        p_greater: one-sided p-value of "a > b": the fraction of resamples with a difference <= 0.
        p_two_sided: ``min(1, 2 * min(P(diff <= 0), P(diff >= 0)))``.
        num_resamples: bootstrap resamples.
        num_episodes: shared episodes.
        num_groups: houses.
    """

    difference: float
    ci: tuple[float, float]
    p_greater: float
    p_two_sided: float
    num_resamples: int
    num_episodes: int
    num_groups: int


def seed_summary(per_seed_means: Sequence[float] | np.ndarray) -> SeedSummary:
    """Mean and sample sd (``ddof=1``) over seeds of one score per seed.

    Raises:
        ValueError: ``per_seed_means`` is empty, not one-dimensional or not finite.

    Examples:
        >>> summary = seed_summary([0.5, 0.6, 0.7])
        >>> round(summary.mean, 6), round(summary.sd, 6), summary.num_seeds
        (0.6, 0.1, 3)
        >>> seed_summary([0.8]).sd is None
        True
    """
    x = _finite_array(per_seed_means, "per_seed_means")
    if x.ndim != 1:
        raise ValueError(f"per_seed_means must be one score per seed (1-D), got shape {x.shape}.")
    return SeedSummary(mean=float(x.mean()), sd=float(np.std(x, ddof=1)) if x.size > 1 else None, num_seeds=int(x.size))


def bootstrap_ci(
    values: Sequence | np.ndarray,
    confidence: float = DEFAULT_CONFIDENCE,
    num_resamples: int = DEFAULT_NUM_RESAMPLES,
    seed: int = 0,
) -> tuple[float, float]:
    """Percentile bootstrap interval of the mean of independent values (deterministic given ``seed``).

    The flat bootstrap: every value is its own group. For episodes grouped by house,
    :func:`hierarchical_bootstrap_ci` resamples the houses too.

    Args:
        values: 1-d sample (array, sequence or tensor).
        confidence: interval level, in (0, 1).
        num_resamples: bootstrap resamples (>= 1).
        seed: seed of the numpy generator.

    Returns:
        ``(low, high)``; ``(nan, nan)`` for an empty sample.

    Examples:
        >>> low, high = bootstrap_ci([0.0, 1.0, 1.0, 0.0, 1.0])
        >>> low <= 0.6 <= high
        True
    """
    _check_bootstrap_options(confidence, num_resamples)
    if hasattr(values, "detach"):  # a torch tensor
        values = values.detach().cpu().double().numpy()
    x = np.asarray(values, dtype=np.float64).reshape(-1)
    if x.size == 0:
        return float("nan"), float("nan")
    rng = np.random.default_rng(seed)
    means = x[rng.integers(0, x.size, size=(num_resamples, x.size))].mean(axis=1)
    return _percentile_interval(means, confidence)


def hierarchical_bootstrap_ci(
    values: Sequence | np.ndarray,
    groups: Sequence | np.ndarray,
    confidence: float = DEFAULT_CONFIDENCE,
    num_resamples: int = DEFAULT_NUM_RESAMPLES,
    seed: int = 0,
    within: bool = True,
) -> tuple[float, float]:
    """Percentile bootstrap interval of a mean, resampling groups (houses), then members within them.

    Each resample draws as many groups as there are, with replacement; each drawn group
    contributes as many of its members (episodes), drawn with replacement from it, as it
    has. The statistic is the mean over all drawn members. With one member per group
    this is the ordinary bootstrap of the mean.

    Resampling at both levels is conservative (Davison and Hinkley 1997, Sec. 3.8): the
    within-house noise is counted twice, once in the spread of the house means and once
    in the second stage, so when houses do not differ at all the interval is about
    sqrt(2) times wider than the flat one; when they differ a lot (the case it is made
    for) the house stage dominates. ``within=False`` (houses only) avoids the double
    count but assumes enough houses for their spread to be estimated alone.

    Args:
        values: per-episode values, shape ``(episodes,)``, or ``(seeds, episodes)`` (or a
            list of per-seed arrays) for several seeds on the same episodes, pooled: each
            episode counts with its mean over seeds.
        groups: the group (house) of each episode, shape ``(episodes,)``; any hashable labels.
        confidence: interval level, in (0, 1).
        num_resamples: bootstrap resamples (>= 1).
        seed: seed of the resampling.
        within: resample the episodes within each drawn house (the default); ``False``
            keeps each drawn house's episodes as they are (the cluster bootstrap).

    Returns:
        ``(low, high)``.

    Raises:
        ValueError: empty or non-finite ``values``, ``groups`` of another length, a bad
            ``confidence`` or ``num_resamples``.

    Examples:
        >>> import numpy as np
        >>> houses = np.repeat(np.arange(10), 20)
        >>> scores = np.where(houses < 5, 1.0, 0.0)  # half the houses always succeed, half never
        >>> low, high = hierarchical_bootstrap_ci(scores, houses, num_resamples=2000)
        >>> bool(low < 0.3 and high > 0.7)  # wide: only 10 houses
        True
        >>> flat_low, flat_high = hierarchical_bootstrap_ci(scores, np.arange(200), num_resamples=2000)
        >>> bool(flat_high - flat_low < (high - low) / 2)  # episodes taken as independent: much narrower
        True
    """
    _check_bootstrap_options(confidence, num_resamples)
    pooled = _pooled(values, "values")
    codes = _group_codes(groups, pooled.size)
    means = _resampled_means(pooled, codes, num_resamples, np.random.default_rng(seed), within)
    return _percentile_interval(means, confidence)


def paired_bootstrap(
    a: Sequence | np.ndarray,
    b: Sequence | np.ndarray,
    groups: Sequence | np.ndarray,
    confidence: float = DEFAULT_CONFIDENCE,
    num_resamples: int = DEFAULT_NUM_RESAMPLES,
    seed: int = 0,
    within: bool = True,
) -> PairedResult:
    """Paired, hierarchical bootstrap of mean(a) - mean(b) on shared episodes, pooled over seeds.

    ``a`` and ``b`` hold per-episode scores of two policies on the *same* episodes (same
    order): the statistic is the mean over seeds and episodes of ``a`` minus that of
    ``b``. Each resample draws houses, then episodes within them, as
    :func:`hierarchical_bootstrap_ci` does, and takes the same episodes for ``a`` and
    ``b``, which keeps the pairing. The number of seeds may differ between ``a`` and
    ``b`` (each episode counts with its mean over each side's seeds), e.g. against
    open-loop replay, which has no training seed.

    Args:
        a, b: shape ``(episodes,)`` or ``(seeds, episodes)`` (or a list of per-seed arrays).
        groups: the group (house) of each episode, shape ``(episodes,)``.
        confidence: interval level, in (0, 1).
        num_resamples: bootstrap resamples (>= 1).
        seed: seed of the resampling.
        within: resample episodes within the drawn houses (see :func:`hierarchical_bootstrap_ci`).

    Returns:
        a :class:`PairedResult`: the difference, its interval, the one-sided p-value of
        "a > b" (fraction of resamples with a difference <= 0) and a two-sided one.

    Raises:
        ValueError: empty or non-finite ``a`` or ``b``, a different number of episodes in
            ``a``, ``b`` or ``groups``, a bad ``confidence`` or ``num_resamples``.

    Examples:
        >>> import numpy as np
        >>> rng = np.random.default_rng(0)
        >>> houses = np.repeat(np.arange(18), 50)
        >>> b = rng.random((3, 900))
        >>> result = paired_bootstrap(b + 0.1, b, houses, num_resamples=2000)
        >>> round(result.difference, 6), [round(x, 6) for x in result.ci], result.p_greater
        (0.1, [0.1, 0.1], 0.0)
        >>> paired_bootstrap(b, b, houses, num_resamples=2000).p_two_sided
        1.0
    """
    _check_bootstrap_options(confidence, num_resamples)
    pooled_a, pooled_b = _pooled(a, "a"), _pooled(b, "b")
    if pooled_a.size != pooled_b.size:
        raise ValueError(
            f"a and b must hold the same episodes: a has {pooled_a.size} episodes per seed, b has {pooled_b.size}."
        )
    codes = _group_codes(groups, pooled_a.size)
    difference = pooled_a - pooled_b
    means = _resampled_means(difference, codes, num_resamples, np.random.default_rng(seed), within)
    at_most_zero, at_least_zero = float(np.mean(means <= 0.0)), float(np.mean(means >= 0.0))
    result = PairedResult(
        difference=float(difference.mean()),
        ci=_percentile_interval(means, confidence),
        p_greater=at_most_zero,
        p_two_sided=min(1.0, 2.0 * min(at_most_zero, at_least_zero)),
        num_resamples=int(num_resamples),
        num_episodes=int(difference.size),
        num_groups=int(codes.max()) + 1,
    )
    logger.debug("paired bootstrap: %s", result)
    return result


# ---------------------------------------------------------------------------- helpers
def _finite_array(values: Sequence | np.ndarray, name: str) -> np.ndarray:
    try:
        x = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as err:  # ragged lists, strings
        raise ValueError(f"{name} must be numbers of one shape (seeds, episodes): {err}") from err
    if x.size == 0:
        raise ValueError(f"{name} is empty: it needs at least one value.")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name} holds {int(np.sum(~np.isfinite(x)))} non-finite values (NaN or inf).")
    return x


def _pooled(values: Sequence | np.ndarray, name: str) -> np.ndarray:
    """``(episodes,)`` means over seeds of ``(seeds, episodes)`` (or ``(episodes,)``) values."""
    x = _finite_array(values, name)
    if x.ndim == 1:
        return x
    if x.ndim == 2:
        return x.mean(axis=0)
    raise ValueError(f"{name} must have shape (episodes,) or (seeds, episodes), got {x.shape}.")


def _group_codes(groups: Sequence | np.ndarray, num_episodes: int) -> np.ndarray:
    """The group of each episode as a code ``0 .. G - 1`` (labels in sorted order)."""
    labels = np.asarray(groups)
    if labels.ndim != 1 or labels.size != num_episodes:
        raise ValueError(f"groups must give one group per episode ({num_episodes}), got shape {labels.shape}.")
    return np.unique(labels, return_inverse=True)[1].reshape(-1)


def _check_bootstrap_options(confidence: float, num_resamples: int) -> None:
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence!r}.")
    if isinstance(num_resamples, bool) or not isinstance(num_resamples, (int, np.integer)) or num_resamples < 1:
        raise ValueError(f"num_resamples must be an int >= 1, got {num_resamples!r}.")


def _percentile_interval(means: np.ndarray, confidence: float) -> tuple[float, float]:
    alpha = (1.0 - confidence) / 2.0
    low, high = np.quantile(means, [alpha, 1.0 - alpha])
    return float(low), float(high)


def _resampled_means(
    values: np.ndarray, codes: np.ndarray, num_resamples: int, rng: np.random.Generator, within: bool = True
) -> np.ndarray:
    """Means of ``num_resamples`` two-level resamples of ``values`` (groups ``codes``), vectorised.

    Per resample: ``G`` groups drawn with replacement; each drawn group ``g`` adds
    ``n_g`` members drawn with replacement from it (``within``), or all its members. The draws of a chunk of resamples
    are laid out flat (one entry per drawn member) and summed per resample with
    :func:`numpy.bincount`.
    """
    order = np.argsort(codes, kind="stable")
    sorted_values = values[order]
    sizes = np.bincount(codes)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    num_groups = sizes.size
    means = np.empty(num_resamples)
    for first in range(0, num_resamples, CHUNK_RESAMPLES):
        count = min(CHUNK_RESAMPLES, num_resamples - first)
        drawn = rng.integers(0, num_groups, size=(count, num_groups)).reshape(-1)
        drawn_sizes = sizes[drawn]
        member_sizes = np.repeat(drawn_sizes, drawn_sizes)
        if within:
            offsets = (rng.random(member_sizes.size) * member_sizes).astype(np.int64)  # uniform in 0 .. n_g - 1
            np.minimum(offsets, member_sizes - 1, out=offsets)  # (u * n may round up to n)
        else:  # 0 .. n_g - 1 in order: the drawn group as it is
            offsets = np.arange(member_sizes.size) - np.repeat(np.cumsum(drawn_sizes) - drawn_sizes, drawn_sizes)
        members = np.repeat(starts[drawn], drawn_sizes) + offsets
        totals = drawn_sizes.reshape(count, num_groups).sum(axis=1)
        sums = np.bincount(np.repeat(np.arange(count), totals), weights=sorted_values[members], minlength=count)
        means[first : first + count] = sums / totals
    return means
