"""Scripted policies: the expert, the expert with random actions, open-loop replay, and their coins.

:class:`ExpertPolicy`, :class:`EpsilonExpertPolicy` and :class:`OpenLoopReplay` are
TensorDict policies: they can drive :class:`~envs.nav_env.PathFollowEnv` in
``env.rollout`` or a TorchRL collector (:mod:`envs.episodes` plays numbered episodes
with them). :func:`behaviour_coins` is the one rule for a behaviour policy's random
choices, shared with DAgger's mixture of expert and learner.
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from envs.expert import TURN_LEFT
from envs.specs import NUM_DEMO_ACTIONS
from envs.transforms import philox_uniforms

#: Mixed into the episode seed so the behaviour policy's coins are independent of the actuation noise.
BEHAVIOUR_STREAM_SALT = 0xE5B1


def behaviour_coins(tensordict: TensorDictBase, salt: int, count: int) -> torch.Tensor:
    """``(rows, count)`` uniform coins in ``[0, 1)`` of a behaviour policy's steps: Philox draws
    of ``(episode_seed ^ salt, step_count)``.

    The one rule by which behaviour policies mix actions (:class:`EpsilonExpertPolicy`,
    DAgger's :class:`~spf_rl.train.dagger.ExpertMixturePolicy`): an episode draws the same
    coins in any batch layout, process or number of agents, and each policy's ``salt``
    keeps its coins apart from the actuation noise's.

    Examples:
        >>> from tensordict import TensorDict
        >>> td = TensorDict({"episode_seed": torch.tensor([[7], [7]]), "step_count": torch.tensor([[0], [1]])}, [2])
        >>> coins = behaviour_coins(td, BEHAVIOUR_STREAM_SALT, 2)
        >>> coins.shape, bool(((coins >= 0) & (coins < 1)).all()), torch.equal(coins, behaviour_coins(td, BEHAVIOUR_STREAM_SALT, 2))
        (torch.Size([2, 2]), True, True)
    """
    seeds = tensordict.get("episode_seed").reshape(-1).cpu().numpy() ^ salt
    steps = tensordict.get("step_count").reshape(-1).cpu().numpy()
    return torch.from_numpy(philox_uniforms(seeds, steps, count))


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


class EpsilonExpertPolicy(TensorDictModuleBase):
    """The expert, except that with probability ``random_action_prob`` a step takes a
    uniformly random action (forward, left or right): the behaviour policy of BC
    datasets, which then see states off the expert's path (their labels stay the
    expert's ``expert_action``).

    The coins of a step are Philox draws of ``(episode_seed, step_count)``, so an
    episode gets the same actions in any batch layout, process or number of agents.

    Args:
        random_action_prob: probability of a random action, in ``[0, 1]``.

    Examples:
        >>> from tensordict import TensorDict
        >>> td = TensorDict({"expert_action": torch.full((4,), 2), "episode_seed": torch.arange(4)[:, None],
        ...     "step_count": torch.zeros(4, 1, dtype=torch.long)}, [4])
        >>> EpsilonExpertPolicy(0.0)(td)["action"].tolist()
        [2, 2, 2, 2]
        >>> actions = EpsilonExpertPolicy(1.0)(td.clone())["action"]
        >>> bool(((actions >= 0) & (actions < 3)).all())
        True
    """

    in_keys = ["expert_action", "episode_seed", "step_count"]
    out_keys = ["action"]

    def __init__(self, random_action_prob: float) -> None:
        super().__init__()
        if not 0.0 <= float(random_action_prob) <= 1.0:
            raise ValueError(f"random_action_prob must be in [0, 1], got {random_action_prob!r}.")
        self.random_action_prob = float(random_action_prob)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if "expert_action" not in tensordict.keys():
            raise KeyError("EpsilonExpertPolicy needs 'expert_action': build the env with with_expert=True.")
        expert = tensordict.get("expert_action")
        if self.random_action_prob > 0.0:
            coins = behaviour_coins(tensordict, BEHAVIOUR_STREAM_SALT, 2).to(expert.device)
            random_action = (coins[:, 1] * NUM_DEMO_ACTIONS).long().clamp(max=NUM_DEMO_ACTIONS - 1)
            take_random = coins[:, 0] < self.random_action_prob
            expert = torch.where(take_random.reshape(expert.shape), random_action.reshape(expert.shape).to(expert.dtype), expert)
        return tensordict.set("action", expert.clone())


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


__all__ = ["EpsilonExpertPolicy", "ExpertPolicy", "OpenLoopReplay", "behaviour_coins"]
