"""Keys and specs of :class:`~envs.nav_env.PathFollowEnv`, and the transform that hides privileged keys.

Frames follow TorchRL's pixel envs (``GymEnv``/``DMControlEnv`` with
``from_pixels=True``): ``pixels`` ``[*, H, W, 3]`` and ``demo_frames``
``[*, n, H, W, 3]``, uint8 (0-255), so that ``ToTensorImage``, ``Resize``,
``GrayScale`` and ``CatFrames`` work on them. The policy side converts them
(:class:`~spf_rl.modules.ImageEncoder` reads HWC).

Privileged keys (:data:`PRIVILEGED_KEYS`: the agent's pose, the geodesic distance
to the goal, the house's seed, the expert's action, the route step and the episode's metrics) are there for
metrics, plotting and labelling. A policy must not read them: append
:class:`HidePrivileged` to the env, and a policy input built from the
observation spec no longer contains them.
"""
from __future__ import annotations

import torch
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs.transforms import ExcludeTransform

from envs.conditions import CONDITIONS
from envs.transforms import ACTUATION_NOISE_KEY, actuation_noise_spec

#: Colour channels of a frame; frames are HWC uint8, as TorchRL's pixel envs emit them.
NUM_RGB_CHANNELS = 3
#: Number of demonstration action classes (forward, left, right).
NUM_DEMO_ACTIONS = 3
#: Keys for metrics, plotting and labelling only: a policy must not read them.
PRIVILEGED_KEYS: tuple[str, ...] = (
    "pose",
    "goal_distance",
    "house_seed",
    "path_length",
    "shortest_path_length",
    "expert_action",
    "route_step",
    "success",
    "success_lab",
    "spl",
    "ndtw",
    "sdtw",
    "path_length_ratio",
    "wall_hits",
    "condition",
    "condition_strength",
    "memory_mismatched",
)
#: Done keys: ``terminated`` = success (or STOP), ``truncated`` = step limit.
DONE_KEYS = ("done", "terminated", "truncated")


def path_follow_specs(
    batch_shape: torch.Size,
    *,
    image_size: int,
    demo_length: int,
    num_actions: int,
    emit_demo_frames: bool,
    with_demo_id: bool,
    with_expert: bool,
    device: torch.device | str | None,
    with_route_step: bool = False,
    with_conditions: bool = False,
    with_mismatch: bool = False,
) -> dict[str, Composite | Categorical | Unbounded]:
    """The specs of a :class:`~envs.nav_env.PathFollowEnv`: ``observation``, ``action``, ``state``, ``reward``, ``done``.

    ``with_route_step`` adds ``route_step`` (``[*, 1]``, 0 to ``demo_length``): the
    demonstration step the agent has come to along its route, by the route expert
    (:meth:`~envs.route_expert.RouteExpert.route_step`), a label for the policy's pointer.
    ``with_conditions`` adds the episode's repeat condition (:mod:`envs.conditions`):
    ``condition`` (its index in :data:`~envs.conditions.CONDITIONS`) and ``condition_strength``;
    ``with_mismatch`` adds ``memory_mismatched`` (the frames are another route's) and, with
    ``with_demo_id``, ``memory_id`` (the stored demonstration whose frames are shown).

    Examples:
        >>> specs = path_follow_specs(torch.Size([]), image_size=32, demo_length=5, num_actions=3,
        ...                           emit_demo_frames=True, with_demo_id=False, with_expert=False, device="cpu")
        >>> specs["observation"]["pixels"].shape, specs["observation"]["demo_frames"].shape
        (torch.Size([32, 32, 3]), torch.Size([5, 32, 32, 3]))
    """
    shape, size, n = tuple(batch_shape), image_size, demo_length

    def unbounded(*trailing: int, dtype: torch.dtype = torch.float32) -> Unbounded:
        return Unbounded(shape=(*shape, *trailing), dtype=dtype, device=device)

    def flag() -> Categorical:
        return Categorical(2, shape=(*shape, 1), dtype=torch.bool, device=device)

    observation = {
        # uint8 frames (0-255). Unbounded rather than Bounded: a Bounded spec stores
        # low/high tensors of the full frame-stack shape, which makes every spec
        # copy and check slow for batched envs.
        "pixels": unbounded(size, size, NUM_RGB_CHANNELS, dtype=torch.uint8),
        "demo_actions": Categorical(NUM_DEMO_ACTIONS, shape=(*shape, n), dtype=torch.int64, device=device),
        # the demonstration's own length, steps (1 to n): frames and actions after it are padding
        "demo_steps": Bounded(1, n, shape=(*shape, 1), dtype=torch.int64, device=device),
        "step_count": unbounded(1, dtype=torch.int64),
        "episode_seed": unbounded(1, dtype=torch.int64),
        "episode_index": unbounded(1, dtype=torch.int64),
        # the seed of the episode's house (envs.scenes.build_house), for per-house statistics
        "house_seed": unbounded(1, dtype=torch.int64),
        "pose": unbounded(3),
        "goal_distance": unbounded(1),
        "path_length": unbounded(1),
        "shortest_path_length": unbounded(1),
        "success": flag(),
        "success_lab": flag(),
        "spl": unbounded(1),
        # path fidelity (envs.path_fidelity), reported on an episode's last step (0 before it)
        "ndtw": unbounded(1),
        "sdtw": unbounded(1),
        "path_length_ratio": unbounded(1),
        # forward steps a wall has cut short since the episode's start
        "wall_hits": unbounded(1, dtype=torch.int64),
        # also an observation (always zero in outputs), so that batched envs carry the
        # state key to the root, as TorchRL's primers do for recurrent states
        ACTUATION_NOISE_KEY: actuation_noise_spec(shape, device),
    }
    if emit_demo_frames:
        observation["demo_frames"] = unbounded(n, size, size, NUM_RGB_CHANNELS, dtype=torch.uint8)
    if with_demo_id:
        observation["demo_id"] = unbounded(1, dtype=torch.int64)
    if with_expert:
        observation["expert_action"] = Categorical(num_actions, shape=shape, dtype=torch.int64, device=device)
    if with_route_step:
        observation["route_step"] = Bounded(0, n, shape=(*shape, 1), dtype=torch.int64, device=device)
    if with_conditions:
        observation["condition"] = Bounded(0, len(CONDITIONS) - 1, shape=(*shape, 1), dtype=torch.int64, device=device)
        observation["condition_strength"] = Bounded(0.0, 1.0, shape=(*shape, 1), dtype=torch.float32, device=device)
    if with_mismatch:
        observation["memory_mismatched"] = flag()
        if with_demo_id:
            observation["memory_id"] = unbounded(1, dtype=torch.int64)
    return {
        "observation": Composite(observation, shape=shape, device=device),
        "action": Categorical(num_actions, shape=shape, dtype=torch.int64, device=device),
        # written by ActuationNoise before a step; absent or zero means the nominal step
        "state": Composite({ACTUATION_NOISE_KEY: actuation_noise_spec(shape, device)}, shape=shape, device=device),
        "reward": unbounded(1),
        "done": Composite({key: flag() for key in DONE_KEYS}, shape=shape, device=device),
    }


class HidePrivileged(ExcludeTransform):
    """Removes the privileged keys (:data:`PRIVILEGED_KEYS`) from an env's outputs and specs.

    Append it to a :class:`~envs.nav_env.PathFollowEnv` (or a batched env of them)
    whose outputs feed a policy; keep a second env, or a copy of the data taken
    before this transform, for metrics. Keys the env does not emit are ignored.

    Examples:
        >>> from torchrl.envs import TransformedEnv
        >>> from envs.nav_env import PathFollowEnv
        >>> env = TransformedEnv(PathFollowEnv(num_houses=1, demo_length=5, render=False), HidePrivileged())
        >>> sorted(set(PRIVILEGED_KEYS) & set(env.observation_spec.keys()))
        []
        >>> "pixels" in env.reset().keys()
        True
    """

    def __init__(self) -> None:
        super().__init__(*PRIVILEGED_KEYS)

    def transform_output_spec(self, output_spec: Composite) -> Composite:
        # exclude what the env emits: expert_action, for one, exists only with with_expert=True
        present = set(output_spec["full_observation_spec"].keys())
        self.excluded_keys = [key for key in PRIVILEGED_KEYS if key in present]
        return super().transform_output_spec(output_spec)
