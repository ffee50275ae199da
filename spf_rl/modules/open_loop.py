"""Open-loop baseline: replays the demonstration's actions, ignoring what the agent sees."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torchrl.data import Unbounded
from torchrl.envs import TensorDictPrimer

from spf_rl.modules.config import ALLOWED_NUM_ACTIONS, NUM_PAPER_ACTIONS, STOP_ACTION, TURN_LEFT_ACTION
from spf_rl.modules.td_utils import DEMO_STEPS_KEY, demo_lengths

__all__ = ["OpenLoopPolicy"]

#: Logit given to non-replayed actions by :class:`OpenLoopPolicy`.
OPEN_LOOP_OFF_LOGIT = -1.0e4


class OpenLoopPolicy(TensorDictModuleBase):
    """Open-loop baseline: replays ``demo_actions[step]``, ignoring the observations.

    Keeps its own step counter in the recurrent state (reset to 0 where ``is_init``).
    After the demonstration ends it outputs ``action_after_demo``: after ``n`` steps,
    or after ``n_i`` where the optional ``demo_steps`` input gives a demonstration's
    own length (its actions padded to ``n``).

    Args:
        num_actions (int, optional): number of actions (3, or 4 with STOP). Defaults to 3.
        action_after_demo (int, optional): action once the demo is exhausted. Defaults
            to STOP (3) when ``num_actions == 4``, else turn left (1), which keeps the
            agent's position.

    Keyword Args:
        demo_actions_key, is_init_key, step_key, action_key, logits_key (NestedKey):
            keys. Defaults ``"demo_actions"``, ``"is_init"``, ``"open_loop_step"``
            (``[1]`` int64), ``"action"``, ``"logits"``.
        demo_steps_key (NestedKey, optional): optional input, each demonstration's length
            ``n_i`` (int64 ``[1]``); ``None``: never read. Defaults ``"demo_steps"``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> policy = OpenLoopPolicy()
        >>> td = TensorDict({"demo_actions": torch.tensor([[2, 0, 1]]),
        ...                  "is_init": torch.ones(1, 1, dtype=torch.bool)}, batch_size=[1])
        >>> policy(td)["action"].tolist(), td["next", "open_loop_step"].tolist()
        ([2], [[1]])
        >>> _ = td.update({"demo_steps": torch.tensor([[1]]), "open_loop_step": torch.tensor([[1]]),
        ...            "is_init": torch.zeros(1, 1, dtype=torch.bool)})  # a 1-step demo, padded to 3
        >>> policy(td)["action"].tolist()  # its after-demo action, turn left
        [1]
    """

    def __init__(
        self,
        num_actions: int = NUM_PAPER_ACTIONS,
        action_after_demo: int | None = None,
        *,
        demo_actions_key: NestedKey = "demo_actions",
        is_init_key: NestedKey = "is_init",
        step_key: NestedKey = "open_loop_step",
        action_key: NestedKey = "action",
        logits_key: NestedKey = "logits",
        demo_steps_key: NestedKey | None = DEMO_STEPS_KEY,
    ) -> None:
        super().__init__()
        if num_actions not in ALLOWED_NUM_ACTIONS:
            raise ValueError(
                f"num_actions must be one of {ALLOWED_NUM_ACTIONS}, got {num_actions!r}."
            )
        if action_after_demo is None:
            action_after_demo = STOP_ACTION if num_actions > NUM_PAPER_ACTIONS else TURN_LEFT_ACTION
        if not 0 <= action_after_demo < num_actions:
            raise ValueError(
                f"action_after_demo must be in range(num_actions={num_actions}), got {action_after_demo!r}."
            )
        self.num_actions = num_actions
        self.action_after_demo = action_after_demo
        self.demo_actions_key = demo_actions_key
        self.is_init_key = is_init_key
        self.step_key = step_key
        self.action_key = action_key
        self.logits_key = logits_key
        self.demo_steps_key = demo_steps_key
        self.in_keys = [demo_actions_key, is_init_key, step_key] + ([demo_steps_key] if demo_steps_key is not None else [])
        step_next = ("next", *((step_key,) if isinstance(step_key, str) else tuple(step_key)))
        self.out_keys = [action_key, logits_key, step_next]

    def make_tensordict_primer(self) -> TensorDictPrimer:
        """Primer for the step counter key (int64 ``[1]``, zeroed at reset)."""
        return TensorDictPrimer(
            {self.step_key: Unbounded(shape=(1,), dtype=torch.int64)}, expand_specs=True
        )

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Write the replayed action, one-hot-like logits and the next step counter."""
        demo_actions = tensordict.get(self.demo_actions_key).long()
        bs = demo_actions.shape[:-1]
        n = demo_actions.shape[-1]
        lengths = demo_lengths(tensordict, self.demo_steps_key, n, bs)
        step = tensordict.get(self.step_key, None)
        step = (
            torch.zeros(*bs, 1, dtype=torch.long, device=demo_actions.device)
            if step is None
            else step.reshape(*bs, 1).long()
        )
        is_init = tensordict.get(self.is_init_key, None)
        if is_init is not None:
            step = torch.where(is_init.reshape(*bs, 1), torch.zeros_like(step), step)
        action = demo_actions.gather(-1, step.clamp(0, n - 1))
        end = n if lengths is None else lengths.to(step.device)
        action = torch.where(step >= end, torch.full_like(action, self.action_after_demo), action)
        action = action.squeeze(-1)
        logits = torch.full((*bs, self.num_actions), OPEN_LOOP_OFF_LOGIT, device=action.device)
        logits = logits.scatter(-1, action.unsqueeze(-1), 0.0)
        tensordict.set(self.action_key, action)
        tensordict.set(self.logits_key, logits)
        tensordict.set(self.out_keys[-1], step + 1)
        return tensordict
