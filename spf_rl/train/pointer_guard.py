"""The pointer-collapse guard of every BC and DAgger run.

With the paper's pointer rule (``eta_{t+1} = eta_t + tanh(b)``), behaviour cloning can drive
``tanh(b)`` to -1 in a run's first epochs: the pointer then runs backwards out of the memory and
the policy follows routes worse than open-loop replay (Table 1's SPF 0.4 seed 2 and the
random-sparsity model's seed 1; :mod:`spf_rl.pointer_pace` found them after the runs).

The guard measures the pointer's pace (:func:`~spf_rl.pointer_pace.pointer_pace`: demonstration
steps per step, teacher-forced, eval mode) after every epoch or round on a fixed handful of training
episodes (:data:`GUARD_EPISODES`, the first of the run's data), logs it (``pointer_pace`` in each
record), and calls a pace below :data:`COLLAPSE_PACE` a collapse. Then:

- **BC** (and the lengths run's BC) starts again from a fresh initialisation drawn from
  :func:`restart_seed` (the run's seed and the restart's number), with a fresh optimiser and
  schedule, on the same data in the same order; the run's ``results.json`` lists each restart
  (``pointer_restarts``: the epoch, the pace, the seed). After :data:`MAX_RESTARTS` restarts it
  trains on, logged as an error.
- **DAgger** sets the round's weights aside: the round can never be the best (its record says
  ``pointer_collapsed``), and the next round starts from the best round's weights (``best.pt``), with
  fresh optimiser moments.

Measuring changes nothing else (no random draw, no training state), so a run that never collapses
trains exactly as it would without the guard. Policies without a pointer have no guard. In a data-parallel
run the ranks' paces are averaged, so that every rank takes the same decision.
"""
from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np
import torch
from tensordict import TensorDictBase

from spf_rl.pointer_pace import BACKWARD_PACE, pointer_pace

logger = logging.getLogger(__name__)

#: A pace (demonstration steps per step) below this after an epoch or round is a collapse: the
#: pointer runs backwards. Healthy runs keep 0.8-1.0 (Table 1's checkpoints); the two collapsed ones, -0.6 to -0.8.
COLLAPSE_PACE = BACKWARD_PACE
#: Training episodes the pace is measured on (the first of the run's data).
GUARD_EPISODES = 16
#: Restarts of one BC run at most.
MAX_RESTARTS = 3
#: Separates the restart seeds from the run's other streams.
RESTART_STREAM = 0x5EED9


def restart_seed(seed: int, restart: int) -> int:
    """The seed of the fresh initialisation of a BC run's ``restart``-th restart (from 1).

    Examples:
        >>> restart_seed(0, 1) == restart_seed(0, 1) != restart_seed(0, 2)
        True
    """
    return int(np.random.SeedSequence([seed, restart, RESTART_STREAM]).generate_state(1)[0] % (2**31))


def has_pointer(policy: torch.nn.Module) -> bool:
    """Whether ``policy`` has an attention pointer (writes ``eta_used`` and ``("next", "eta")``)."""
    return {"eta_used", ("next", "eta")} <= set(getattr(policy, "out_keys", ()))


class PointerGuard:
    """Measures a policy's pointer pace on fixed episodes and says whether it collapsed.

    Args:
        episodes: the episodes the pace is measured on (the layout training reads).

    Examples:
        >>> guard = PointerGuard(None)
        >>> guard.collapsed(-0.7), guard.collapsed(0.9), guard.collapsed(None)
        (True, False, False)
    """

    def __init__(self, episodes: TensorDictBase | None) -> None:
        self.episodes = episodes

    @classmethod
    def of(cls, policy: torch.nn.Module, source) -> PointerGuard | None:
        """The guard of ``policy`` on the first :data:`GUARD_EPISODES` episodes of a training
        source (a dataset or a DAgger round's store); ``None`` for a policy without a pointer."""
        from spf_rl.train.dagger_rounds import source_rows

        if not has_pointer(policy):
            return None
        return cls(source_rows(source, torch.arange(min(GUARD_EPISODES, len(source)))))

    def pace(self, policy: torch.nn.Module, ranks=None) -> float:
        """The policy's mean pointer pace on the guard's episodes (the policy is left in eval mode); in a
        data-parallel run (``ranks``), the ranks' mean, so that every rank takes the same decision."""
        from spf_rl.train.distributed import all_ranks_sum

        pace = pointer_pace(policy, self.episodes)
        if ranks is not None and ranks.distributed:
            device = next(policy.parameters()).device
            pace = all_ranks_sum(pace, ranks, device) / ranks.world_size
        return pace

    @staticmethod
    def collapsed(pace: float | None) -> bool:
        """Whether a measured pace is a collapse (below :data:`COLLAPSE_PACE`)."""
        return pace is not None and pace < COLLAPSE_PACE


#: The entry of a BC run's ``last.pt`` (:attr:`~spf_rl.train.run.TrainingRun.state`) and ``results.json``
#: that lists its restarts.
RESTARTS_KEY = "pointer_restarts"


def restart_run(run, new_run: Callable[[], object], seed: int, epoch: int, pace: float):
    """After a collapse at the end of epoch ``epoch`` (from 1): the policy re-initialised in place from
    :func:`restart_seed` (torch seeded with it), a fresh run from ``new_run()`` (optimiser, schedule,
    history) that remembers every restart so far, ``best.pt`` removed and ``last.pt`` written at epoch 0,
    so that an interrupted run resumes the restarted one. ``None`` (logged) after :data:`MAX_RESTARTS`.
    """
    from spf_rl.modules.registry import build_policy

    restarts = list(run.state.get(RESTARTS_KEY, []))
    if len(restarts) >= MAX_RESTARTS:
        logger.error("pointer collapse after epoch %d (pace %.3f), but the run restarted %d times already: "
                     "training on", epoch, pace, len(restarts))
        return None
    init_seed = restart_seed(seed, len(restarts) + 1)
    restarts.append({"epoch": epoch, "pointer_pace": pace, "seed": init_seed})
    logger.warning("pointer collapse after epoch %d (pace %.3f < %g): restart %d of at most %d, from a fresh "
                   "initialisation with seed %d", epoch, pace, COLLAPSE_PACE, len(restarts), MAX_RESTARTS, init_seed)
    torch.manual_seed(init_seed)
    fresh = build_policy(run.model_type, run.policy_config)
    run.policy.load_state_dict(fresh.state_dict())
    restarted = new_run()
    restarted.state = {RESTARTS_KEY: restarts}
    if restarted.ranks.is_main:
        restarted.best_path.unlink(missing_ok=True)
        restarted.save_last(0)
    return restarted


__all__ = [
    "COLLAPSE_PACE", "GUARD_EPISODES", "MAX_RESTARTS", "RESTARTS_KEY", "PointerGuard", "has_pointer", "restart_run",
    "restart_seed",
]
