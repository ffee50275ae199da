"""Scripted policies (the expert, open-loop replay) and episode statistics for them.

:class:`ExpertPolicy` and :class:`OpenLoopReplay` are TensorDict policies: they
can drive :class:`~envs.nav_env.PathFollowEnv` in ``env.rollout`` or a TorchRL
collector. :func:`run_episodes` plays a fixed number of episodes on a batched env
and returns one record per episode (success, SPL, distances); it is how the
expert and open-loop figures of docs/results.md are measured (``recipes/expert_stats.py``).
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tqdm.auto import tqdm

from envs.expert import TURN_LEFT


class ExpertPolicy(TensorDictModuleBase):
    """Copies the env's privileged ``expert_action`` into ``action``.

    Needs an env built with ``with_expert=True``.

    Examples:
        >>> from envs.nav_env import PathFollowEnv
        >>> env = PathFollowEnv(num_houses=1, demo_length=5, with_expert=True, render=False)
        >>> td = env.rollout(3, ExpertPolicy())
        >>> td["action"].shape
        torch.Size([3])
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
        >>> td = env.rollout(3, OpenLoopReplay())
        >>> bool((td["action"] == td["demo_actions"][0, :3]).all())
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
        steps, episode_seed, as Python scalars.
    """
    return {
        "success": bool(final["success"].item()),
        "spl": float(final["spl"].item()),
        "goal_distance": float(final["goal_distance"].item()),
        "path_length": float(final["path_length"].item()),
        "shortest_path_length": float(final["shortest_path_length"].item()),
        "steps": int(final["step_count"].item()),
        "episode_seed": int(final["episode_seed"].item()),
    }


def run_episodes(env, policy, num_episodes: int, progress: bool = False) -> list[dict]:
    """Play a fixed set of episodes with ``policy`` and record how each ended.

    Agent ``i`` of the batched env plays its first ``ceil(num_episodes / N)``
    episodes (its k-th episode depends only on the env seed, ``i`` and ``k``), so
    every policy is scored on the same episodes.

    Args:
        env: a seeded batched :class:`~envs.nav_env.PathFollowEnv` (``num_agents`` set),
            possibly wrapped in transforms (actuation noise, primers, ...).
        policy: a TensorDict policy writing ``"action"``.
        num_episodes: number of episodes (> 0).
        progress: show a progress bar.

    Returns:
        one dict per episode, ordered by (agent, episode): success, spl,
        goal_distance, path_length, shortest_path_length, steps, episode_seed.
    """
    if num_episodes <= 0:
        raise ValueError(f"num_episodes must be > 0, got {num_episodes}.")
    if len(env.batch_size) != 1:
        raise ValueError(f"run_episodes needs a batched env (batch_size [N]), got {list(env.batch_size)}.")
    num_agents = env.batch_size[0]
    quota = [len(range(agent, num_episodes, num_agents)) for agent in range(num_agents)]
    per_agent: list[list[dict]] = [[] for _ in range(num_agents)]
    bar = tqdm(total=num_episodes, disable=not progress, desc="episodes")
    tensordict = env.reset()
    with torch.no_grad():
        while any(len(done) < q for done, q in zip(per_agent, quota)):
            tensordict, next_tensordict = env.step_and_maybe_reset(policy(tensordict))
            finished = tensordict.get(("next", "done")).reshape(-1)
            for index in torch.nonzero(finished).reshape(-1).tolist():
                if len(per_agent[index]) >= quota[index]:
                    continue
                per_agent[index].append(episode_record(tensordict.get("next")[index]))
                bar.update(1)
            tensordict = next_tensordict
    bar.close()
    return [record for records in per_agent for record in records]


__all__ = ["ExpertPolicy", "OpenLoopReplay", "episode_record", "run_episodes"]
