"""Scripted policies (the expert, open-loop replay) and episode statistics for them.

:class:`ExpertPolicy` and :class:`OpenLoopReplay` are TensorDict policies: they
can drive :class:`~envs.nav_env.PathFollowEnv` in ``env.rollout`` or a TorchRL
collector. :func:`run_episodes` plays a fixed, seed-determined set of episodes
through a TorchRL :class:`~torchrl.collectors.Collector` and returns one record per episode (success, SPL,
distances); the evaluation of trained policies and the expert and open-loop
figures (``recipes/expert_stats.py``) use it.
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.collectors import Collector
from torchrl.envs.utils import ExplorationType
from tqdm.auto import tqdm

from envs.expert import TURN_LEFT


class ExpertPolicy(TensorDictModuleBase):
    """Copies the env's privileged ``expert_action`` into ``action``.

    Needs an env built with ``with_expert=True``.

    Examples:
        >>> from envs.nav_env import PathFollowEnv
        >>> env = PathFollowEnv(num_houses=1, demo_length=5, with_expert=True, render=False)
        >>> td = env.rollout(3, ExpertPolicy(), break_when_any_done=False)
        >>> td["action"].shape, bool((td["action"] == td["expert_action"]).all())
        (torch.Size([3]), True)
    """

    in_keys = ["expert_action"]
    out_keys = ["action"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if "expert_action" not in tensordict.keys():
            raise KeyError("ExpertPolicy needs 'expert_action': build the env with with_expert=True.")
        return tensordict.set("action", tensordict.get("expert_action").clone())


class OpenLoopReplay(TensorDictModuleBase):
    """Replays the demonstration's actions, ignoring what the camera sees.

    At step t it plays ``demo_actions[t]``; after the demonstration it plays
    ``action_after_demo`` (turn left by default, STOP where the env has it).

    Args:
        action_after_demo: the action once the demonstration is exhausted.

    Examples:
        >>> from envs.nav_env import PathFollowEnv
        >>> env = PathFollowEnv(num_houses=1, demo_length=5, render=False)
        >>> td = env.rollout(3, OpenLoopReplay())  # at most 3 steps: it stops early if the agent arrives
        >>> bool((td["action"] == td["demo_actions"][0, : td.shape[0]]).all())
        True
    """

    in_keys = ["demo_actions", "step_count"]
    out_keys = ["action"]

    def __init__(self, action_after_demo: int = TURN_LEFT) -> None:
        super().__init__()
        self.action_after_demo = action_after_demo

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        demo_actions = tensordict.get("demo_actions")
        step = tensordict.get("step_count")[..., 0]
        length = demo_actions.shape[-1]
        index = step.clamp(max=length - 1).unsqueeze(-1)
        action = torch.gather(demo_actions, -1, index).squeeze(-1)
        action = torch.where(step >= length, torch.full_like(action, self.action_after_demo), action)
        return tensordict.set("action", action)


def episode_record(final: TensorDictBase) -> dict:
    """How an episode ended, from one agent's last ``"next"`` tensordict.

    Returns:
        success, spl, goal_distance (m), path_length (m), shortest_path_length (m),
        steps, episode_seed and house_seed (the house the episode was played in, the key
        of per-house statistics such as :func:`spf_rl.stats.hierarchical_bootstrap_ci`),
        as Python scalars.
    """
    return {
        "success": bool(final["success"].item()),
        "success_lab": bool(final["success_lab"].item()),
        "spl": float(final["spl"].item()),
        "goal_distance": float(final["goal_distance"].item()),
        "path_length": float(final["path_length"].item()),
        "shortest_path_length": float(final["shortest_path_length"].item()),
        "steps": int(final["step_count"].item()),
        "episode_seed": int(final["episode_seed"].item()),
        "house_seed": int(final["house_seed"].item()),
    }


#: Steps each agent takes per collector batch in :func:`run_episodes` (at most this many
#: minus one steps are taken past an agent's last recorded episode).
STEPS_PER_BATCH = 5


def run_episodes(env, policy, num_episodes: int, progress: bool = False) -> list[dict]:
    """Play episodes ``0 .. num_episodes - 1`` of a seeded batched env with ``policy``, through a TorchRL collector.

    The env numbers its episodes (:mod:`envs.episode_numbering`): agent ``i`` of ``N``
    plays episodes ``i, i + N, i + 2N, ...``, and episode ``j`` depends only on the env
    seed and ``j``. A :class:`~torchrl.collectors.Collector` steps the env (auto-reset,
    preallocated buffers, deterministic exploration) in batches of
    :data:`STEPS_PER_BATCH` steps per agent until every episode below ``num_episodes``
    has ended; each is recorded once, by its number, and later ones are ignored. So
    every policy is scored on the same episodes, whatever ``N``, and short episodes are
    not over-represented.

    Args:
        env: a seeded batched :class:`~envs.nav_env.PathFollowEnv` (``num_agents`` set),
            possibly wrapped in transforms (actuation noise, primers, ...). The
            collector resets it first; it is left open.
        policy: a TensorDict policy (or callable) writing ``"action"``.
        num_episodes: number of episodes (> 0).
        progress: show a progress bar.

    Returns:
        one dict per episode, ordered by episode number: ``episode_index``, success,
        spl, goal_distance, path_length, shortest_path_length, steps, episode_seed, house_seed.
    """
    if isinstance(num_episodes, bool) or not isinstance(num_episodes, int) or num_episodes <= 0:
        raise ValueError(f"num_episodes must be an int > 0, got {num_episodes!r}.")
    if len(env.batch_size) != 1:
        raise ValueError(f"run_episodes needs a batched env (batch_size [N]), got {list(env.batch_size)}.")
    collector = Collector(
        env,
        policy,
        frames_per_batch=env.batch_size[0] * STEPS_PER_BATCH,
        total_frames=-1,
        exploration_type=ExplorationType.DETERMINISTIC,
        use_buffers=True,
        auto_register_policy_transforms=False,
    )
    records: dict[int, dict] = {}
    bar = tqdm(total=num_episodes, disable=not progress, desc="episodes")
    try:
        for batch in collector:
            final_steps = batch.get("next")[batch.get(("next", "done")).squeeze(-1)]
            for final in final_steps.unbind(0):
                number = int(final["episode_index"].item())
                if number < num_episodes and number not in records:
                    records[number] = {"episode_index": number, **episode_record(final)}
                    bar.update(1)
            if len(records) == num_episodes:
                break
    finally:
        collector.shutdown(close_env=False)
        bar.close()
    return [records[number] for number in range(num_episodes)]


__all__ = ["ExpertPolicy", "OpenLoopReplay", "episode_record", "run_episodes"]
