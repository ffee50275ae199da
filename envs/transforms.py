"""Environment-side transforms: actuation noise.

:class:`ActuationNoise` turns the discrete action the policy chose into the
physical motion the robot actually makes. It is an inverse transform: on the
way into the environment it writes ``"actuation"`` = (forward m, lateral m,
rotation rad) in the agent's frame, which :class:`~envs.nav_env.PathFollowEnv`
executes instead of the nominal step. The stored ``"action"`` stays the one the
policy chose.

The noise of a step is a pure function of ``(episode_seed, step_count, action)``
drawn with a counter-based Philox generator, so a seed fixes the realised noise
whatever the batching (single env, batched env, ``SerialEnv``/``ParallelEnv``).
Put the transform inside each worker's factory when using ``ParallelEnv``: the
``"actuation"`` key is not part of the batched env's input spec.

Presets (:data:`NOISE_PRESETS`):

* ``none``: the nominal step.
* ``paper``: the paper's N(0, 0.5^2) m forward and N(0, 1^2) rad rotation noise,
  with the realised step clipped to +-20% of the nominal one, as in the authors'
  lab code (forward steps become 0.24-0.36 m, turns 16-24 degrees).
* ``paper_unclipped``: the literal reading of the paper, no clipping (forward
  steps can be negative, turns anything).
* ``locobot``: habitat-sim's PyRobot LoCoBot ILQR model: truncated Gaussians
  (+-3 sigma) on forward/lateral translation and rotation for both linear and
  rotational motions, with the nominal step never reversed (truncated at -95%).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from scipy import special
from tensordict import TensorDictBase
from torchrl.envs.transforms import Transform

from envs.demos import nominal_motion
from envs.expert import FORWARD

#: Salt mixed into the Philox key so noise streams differ from other uses of the episode seed.
NOISE_STREAM_SALT = 0x5EED_0F_A0
#: Philox counter blocks reserved per step (each block gives 4 x 64-bit words).
COUNTER_BLOCKS_PER_STEP = 64
#: Truncation of the LoCoBot Gaussians, in standard deviations.
LOCOBOT_TRUNCATION_SIGMA = 3.0
#: The nominal step is never reversed by LoCoBot noise: truncation at -95% of it.
LOCOBOT_MIN_FRACTION = 0.95


@dataclass(frozen=True)
class GaussianMotionNoise:
    """Gaussian noise on one kind of motion (linear = forward, rotational = turns).

    Attributes:
        mean: (forward m, lateral m, rotation rad) means.
        std: (forward m, lateral m, rotation rad) standard deviations.
    """

    mean: tuple[float, float, float] = (0.0, 0.0, 0.0)
    std: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class NoiseModel:
    """Actuation noise model.

    Args:
        linear: noise of the forward action.
        rotational: noise of the turn actions.
        clip_fraction: if set, the realised forward step and turn are clipped to
            nominal * (1 +- clip_fraction), and the motion orthogonal to the
            commanded one is dropped (the ``paper`` preset).
        truncation_sigma: if set, Gaussians are truncated at this many standard
            deviations and the commanded step is never reversed (``locobot``).
        sign_follows_turn: flip rotation noise for right turns (habitat-sim: both
            turn directions overshoot on average).
    """

    linear: GaussianMotionNoise = field(default_factory=GaussianMotionNoise)
    rotational: GaussianMotionNoise = field(default_factory=GaussianMotionNoise)
    clip_fraction: float | None = None
    truncation_sigma: float | None = None
    sign_follows_turn: bool = False

    def __post_init__(self) -> None:
        for motion in (self.linear, self.rotational):
            if any(s < 0 for s in motion.std):
                raise ValueError(f"noise std must be >= 0, got {motion.std}.")
        if self.clip_fraction is not None and not 0 <= self.clip_fraction < 1:
            raise ValueError(f"clip_fraction must be in [0, 1), got {self.clip_fraction}.")
        if self.truncation_sigma is not None and self.truncation_sigma <= 0:
            raise ValueError(f"truncation_sigma must be > 0, got {self.truncation_sigma}.")

    @classmethod
    def custom(
        cls,
        forward_std_m: float = 0.0,
        rotation_std_rad: float = 0.0,
        lateral_std_m: float = 0.0,
        clip_fraction: float | None = None,
    ) -> NoiseModel:
        """Zero-mean Gaussian noise of the given standard deviations on every action."""
        motion = GaussianMotionNoise((0.0, 0.0, 0.0), (forward_std_m, lateral_std_m, rotation_std_rad))
        return cls(linear=motion, rotational=motion, clip_fraction=clip_fraction)

    def sample(self, action: np.ndarray, episode_seed: np.ndarray, step_count: np.ndarray) -> np.ndarray:
        """Realised (forward m, lateral m, rotation rad) for ``(N,)`` actions.

        Deterministic in ``(episode_seed, step_count, action)``.
        """
        action = np.asarray(action).reshape(-1)
        nominal = nominal_motion(action)
        uniforms = np.stack(
            [_philox_uniforms(int(seed), int(step), 3) for seed, step in zip(np.ravel(episode_seed), np.ravel(step_count))]
        ) if len(action) else np.zeros((0, 3))
        is_forward = action == FORWARD
        is_turn = (action == 1) | (action == 2)
        mean = np.where(is_forward[:, None], self.linear.mean, self.rotational.mean)
        std = np.where(is_forward[:, None], self.linear.std, self.rotational.std)
        if self.truncation_sigma is None:
            noise = mean + std * special.ndtri(uniforms)
        else:
            low = np.full_like(mean, -self.truncation_sigma)
            high = np.full_like(mean, self.truncation_sigma)
            # never reverse the commanded motion: forward >= -95% of the step, turns likewise
            commanded = np.where(is_forward, 0, 2)
            rows = np.arange(len(action))
            magnitude = np.abs(nominal[rows, commanded])
            safe_std = np.where(std[rows, commanded] > 0, std[rows, commanded], 1.0)
            floor = (-LOCOBOT_MIN_FRACTION * magnitude - mean[rows, commanded]) / safe_std
            low[rows, commanded] = np.where(magnitude > 0, np.maximum(low[rows, commanded], floor), low[rows, commanded])
            lo_cdf, hi_cdf = special.ndtr(low), special.ndtr(high)
            noise = mean + std * special.ndtri(lo_cdf + uniforms * (hi_cdf - lo_cdf))
        if self.sign_follows_turn:
            noise[:, 2] *= np.where(action == 2, -1.0, 1.0)
        active = is_forward | is_turn
        realised = nominal + np.where(active[:, None], noise, 0.0)
        if self.clip_fraction is not None:
            f = self.clip_fraction
            forward = np.clip(realised[:, 0], nominal[:, 0] * (1 - f), nominal[:, 0] * (1 + f))
            low_turn = np.minimum(nominal[:, 2] * (1 - f), nominal[:, 2] * (1 + f))
            high_turn = np.maximum(nominal[:, 2] * (1 - f), nominal[:, 2] * (1 + f))
            rotation = np.clip(realised[:, 2], low_turn, high_turn)
            realised = np.stack([forward, np.zeros_like(forward), rotation], axis=1)
        return realised


def _philox_uniforms(episode_seed: int, step: int, count: int) -> np.ndarray:
    """``count`` uniforms in (0, 1) from the Philox stream of (episode, step)."""
    key = (episode_seed & 0xFFFF_FFFF_FFFF_FFFF) | (NOISE_STREAM_SALT << 64)
    generator = np.random.Generator(np.random.Philox(key=key, counter=step * COUNTER_BLOCKS_PER_STEP))
    return generator.uniform(np.finfo(np.float64).tiny, 1.0, size=count)


_PAPER_MOTION = GaussianMotionNoise((0.0, 0.0, 0.0), (0.5, 0.0, 1.0))

#: Named noise models; see the module docstring.
NOISE_PRESETS: dict[str, NoiseModel] = {
    "none": NoiseModel(),
    "paper": NoiseModel(linear=_PAPER_MOTION, rotational=_PAPER_MOTION, clip_fraction=0.2),
    "paper_unclipped": NoiseModel(
        linear=GaussianMotionNoise((0.0, 0.0, 0.0), (0.5, 0.0, 0.0)),
        rotational=GaussianMotionNoise((0.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    ),
    # habitat-sim pyrobot_noisy_controls, LoCoBot / ILQR. Its covariances are
    # variances: std = sqrt(cov). Lateral is to the right there, to the left here.
    "locobot": NoiseModel(
        linear=GaussianMotionNoise((0.014, -0.009, 0.008), tuple(float(np.sqrt(v)) for v in (0.006, 0.005, 0.004))),
        rotational=GaussianMotionNoise((0.003, -0.003, 0.023), tuple(float(np.sqrt(v)) for v in (0.002, 0.003, 0.012))),
        truncation_sigma=LOCOBOT_TRUNCATION_SIGMA,
        sign_follows_turn=True,
    ),
}


def make_noise_model(noise: str | NoiseModel) -> NoiseModel:
    """A preset by name, or a :class:`NoiseModel` as it is."""
    if isinstance(noise, NoiseModel):
        return noise
    if noise not in NOISE_PRESETS:
        raise ValueError(f"noise must be one of {sorted(NOISE_PRESETS)} or a NoiseModel, got {noise!r}.")
    return NOISE_PRESETS[noise]


class ActuationNoise(Transform):
    """Actuation noise for :class:`~envs.nav_env.PathFollowEnv` as an inverse transform.

    Args:
        noise: a preset name from :data:`NOISE_PRESETS` or a :class:`NoiseModel`.
        action_key: the policy's action key.

    Examples:
        >>> from torchrl.envs import TransformedEnv
        >>> from envs.nav_env import PathFollowEnv
        >>> env = TransformedEnv(PathFollowEnv(num_houses=1, demo_length=5), ActuationNoise("paper"))
        >>> env.set_seed(0)
        0
        >>> td = env.rollout(3)
        >>> td["next", "pose"].shape
        torch.Size([3, 3])
    """

    def __init__(self, noise: str | NoiseModel = "paper", action_key: str = "action") -> None:
        super().__init__(in_keys_inv=[action_key], out_keys_inv=[action_key])
        self.noise_model = make_noise_model(noise)
        self.noise_name = noise if isinstance(noise, str) else "custom"
        self.action_key = action_key

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(self.action_key)
        batch_shape = tensordict.batch_size
        realised = self.noise_model.sample(
            action.reshape(-1).cpu().numpy(),
            tensordict.get("episode_seed").reshape(-1).cpu().numpy(),
            tensordict.get("step_count").reshape(-1).cpu().numpy(),
        )
        tensordict.set("actuation", torch.as_tensor(realised, dtype=torch.float32).reshape(*batch_shape, 3))
        return tensordict

    def __repr__(self) -> str:
        return f"{type(self).__name__}(noise={self.noise_name!r})"
