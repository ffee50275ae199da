"""Which episode each agent plays next: a global episode number, and a seed that depends on it alone.

Agent ``i`` of a batched env of ``N`` agents plays, as its ``k``-th episode, episode
number ``offset + stride * (i + k * N)``; the episode's seed is a pure function of
the env seed and that number. So the set of episodes ``0 .. E - 1`` is the same
whatever the number of agents, and whatever the number of envs that share the
numbering (env ``w`` of ``W`` takes ``offset = w, stride = W``): an evaluation can
play a fixed, seed-determined set of episodes and count each exactly once.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from envs.follow import MAX_EPISODE_SEED

__all__ = ["EpisodeNumbering", "episode_seed", "seed_entropy"]


def seed_entropy(seed: int | None) -> int:
    """The entropy an env seed gives the episode numbering (``SeedSequence(seed).entropy``;
    ``None``: fresh entropy).

    Examples:
        >>> seed_entropy(7)
        7
    """
    return int(np.random.SeedSequence(seed).entropy)


def episode_seed(env_seed_entropy: int, number: int) -> int:
    """The seed of episode ``number`` under an env seed (its ``SeedSequence`` entropy)."""
    return int(np.random.default_rng([env_seed_entropy, number]).integers(MAX_EPISODE_SEED))


@dataclass
class EpisodeNumbering:
    """Episode numbers and seeds of the agents of one env.

    Args:
        num_agents: agents of the env (1 for an unbatched env).
        offset: number of this env's first episode (``w`` for env ``w`` of ``W`` sharing a numbering).
        stride: spacing of this env's episode numbers (``W``).

    Examples:
        >>> numbering = EpisodeNumbering(num_agents=2)
        >>> numbering.reset(seed=0)
        >>> [numbering.next(agent)[0] for agent in (0, 1, 0, 0)]
        [0, 1, 2, 4]
        >>> one = EpisodeNumbering(num_agents=1); one.reset(seed=0)
        >>> [one.next(0) for _ in range(3)][2] == (2, numbering.seed_of(2))
        True
    """

    num_agents: int
    offset: int = 0
    stride: int = 1
    _entropy: int = field(default=0, init=False, repr=False)
    _started: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64), init=False, repr=False)

    def __post_init__(self) -> None:
        for name, low in (("num_agents", 1), ("offset", 0), ("stride", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
                raise ValueError(f"episode {name} must be an int >= {low}, got {value!r}.")
        self.reset(None)

    def reset(self, seed: int | None) -> None:
        """Start again from each agent's first episode under env seed ``seed``."""
        self._entropy = seed_entropy(seed)
        self._started = np.zeros(self.num_agents, dtype=np.int64)

    def seed_of(self, number: int) -> int:
        """The seed of episode ``number`` under the current env seed."""
        return episode_seed(self._entropy, number)

    def next(self, agent: int) -> tuple[int, int]:
        """``(number, seed)`` of agent ``agent``'s next episode."""
        number = self.offset + self.stride * (agent + int(self._started[agent]) * self.num_agents)
        self._started[agent] += 1
        return number, self.seed_of(number)
