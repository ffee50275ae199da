"""Environment-side transforms: actuation noise.

:class:`ActuationNoise` turns the discrete action the policy chose into the
physical motion the robot actually makes. It is an inverse transform: on the
way into the environment it writes ``"actuation"`` = (forward m, lateral m,
rotation rad) in the agent's frame, which :class:`~envs.nav_env.PathFollowEnv`
executes instead of the nominal step. The stored ``"action"`` stays the one the
policy chose.

The noise of a step is a pure function of ``(episode_seed, step_count, action)``
drawn with the counter-based Philox4x64-10 generator, so a seed fixes the realised
noise whatever the batching (single env, batched env, ``SerialEnv``/``ParallelEnv``):
the three uniforms of a step are the first three 64-bit words of the Philox block
with key ``(episode_seed mod 2**64, NOISE_STREAM_SALT)`` and counter
``step_count * COUNTER_BLOCKS_PER_STEP + 1``, each word ``w`` turned into the double
``(w >> 11) * 2**-53`` (0 replaced by the smallest positive double). These are
exactly the draws of ``np.random.Generator(np.random.Philox(key=..., counter=step *
COUNTER_BLOCKS_PER_STEP)).uniform(tiny, 1, 3)``; :func:`philox_uniforms` computes
them for a batch by resetting one cached bit generator per row (about 5 us a row)
instead of building a generator per agent per step.
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

import threading
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

        Deterministic in ``(episode_seed, step_count, action)``, row by row.
        """
        action = np.asarray(action).reshape(-1)
        # per-action constants (row 4: STOP and unknown actions, which get no noise)
        row = np.where((action >= 0) & (action < 4), action, 4)
        tables = self._tables()
        nominal = tables["nominal"][row]
        uniforms = philox_uniforms(episode_seed, step_count, 3)
        mean, std = tables["mean"][row], tables["std"][row]
        if self.truncation_sigma is None:
            noise = mean + std * special.ndtri(uniforms)
        else:
            lo_cdf, hi_cdf = tables["lo_cdf"][row], tables["hi_cdf"][row]
            noise = mean + std * special.ndtri(lo_cdf + uniforms * (hi_cdf - lo_cdf))
        if self.sign_follows_turn:
            noise[:, 2] *= tables["turn_sign"][row]
        realised = nominal + noise
        if self.clip_fraction is not None:
            bounds = tables["clip"][row]
            clipped = np.zeros_like(realised)
            clipped[:, 0] = np.minimum(np.maximum(realised[:, 0], bounds[:, 0]), bounds[:, 1])
            clipped[:, 2] = np.minimum(np.maximum(realised[:, 2], bounds[:, 2]), bounds[:, 3])
            realised = clipped
        return realised

    def _tables(self) -> dict[str, np.ndarray]:
        """Per-action constants of :meth:`sample`, rows: forward, left, right, STOP/unknown (twice)."""
        tables = self.__dict__.get("_cached_tables")
        if tables is not None:
            return tables
        action = np.arange(5)  # 3 (STOP) and 4 (unknown) both get no noise
        nominal = nominal_motion(action)
        is_forward = action == FORWARD
        active = (action == FORWARD) | (action == 1) | (action == 2)
        mean = np.where(is_forward[:, None], self.linear.mean, self.rotational.mean)
        std = np.where(is_forward[:, None], self.linear.std, self.rotational.std)
        tables = {"nominal": nominal}
        if self.truncation_sigma is not None:
            low = np.full_like(mean, -self.truncation_sigma)
            high = np.full_like(mean, self.truncation_sigma)
            # never reverse the commanded motion: forward >= -95% of the step, turns likewise
            commanded = np.where(is_forward, 0, 2)
            rows = np.arange(len(action))
            magnitude = np.abs(nominal[rows, commanded])
            safe_std = np.where(std[rows, commanded] > 0, std[rows, commanded], 1.0)
            floor = (-LOCOBOT_MIN_FRACTION * magnitude - mean[rows, commanded]) / safe_std
            low[rows, commanded] = np.where(magnitude > 0, np.maximum(low[rows, commanded], floor), low[rows, commanded])
            tables["lo_cdf"], tables["hi_cdf"] = special.ndtr(low), special.ndtr(high)
        tables["mean"] = np.where(active[:, None], mean, 0.0)
        tables["std"] = np.where(active[:, None], std, 0.0)
        tables["turn_sign"] = np.where(action == 2, -1.0, 1.0)
        if self.clip_fraction is not None:
            f = self.clip_fraction
            tables["clip"] = np.stack(
                [
                    nominal[:, 0] * (1 - f),
                    nominal[:, 0] * (1 + f),
                    np.minimum(nominal[:, 2] * (1 - f), nominal[:, 2] * (1 + f)),
                    np.maximum(nominal[:, 2] * (1 - f), nominal[:, 2] * (1 + f)),
                ],
                axis=1,
            )
        for value in tables.values():
            value.setflags(write=False)
        object.__setattr__(self, "_cached_tables", tables)  # frozen dataclass: not a field
        return tables


#: 2**-53: the spacing of the doubles numpy draws in [0, 1).
_DOUBLE_UNIT = 1.0 / 9007199254740992.0
_TINY = np.finfo(np.float64).tiny
_UINT64_MASK = 0xFFFF_FFFF_FFFF_FFFF
_thread_state = threading.local()


def philox_uniforms(episode_seed: np.ndarray, step: np.ndarray, count: int = 3) -> np.ndarray:
    """``(N, count)`` uniforms in (0, 1) from the Philox streams of ``(episode_seed[i], step[i])``.

    Row ``i`` depends only on ``(episode_seed[i], step[i])`` (see the module
    docstring for the exact function), so batching does not change the draws.
    ``count`` must be at most ``4 * COUNTER_BLOCKS_PER_STEP`` (the words reserved
    per step).
    """
    if count > 4 * COUNTER_BLOCKS_PER_STEP:
        raise ValueError(f"count must be <= {4 * COUNTER_BLOCKS_PER_STEP}, got {count}.")
    bit_generator = getattr(_thread_state, "philox", None)
    if bit_generator is None:
        bit_generator = _thread_state.philox = np.random.Philox(0)
    seeds = np.asarray(episode_seed).reshape(-1).tolist()
    steps = np.asarray(step).reshape(-1).tolist()
    words = np.empty((len(seeds), count), dtype=np.uint64)
    empty_buffer = np.zeros(4, dtype=np.uint64)
    for row, (seed, index) in enumerate(zip(seeds, steps)):
        # buffer_pos 4: the buffer is spent, so the next draw increments the counter first
        bit_generator.state = {
            "bit_generator": "Philox",
            "state": {
                "counter": np.array([index * COUNTER_BLOCKS_PER_STEP, 0, 0, 0], dtype=np.uint64),
                "key": np.array([int(seed) & _UINT64_MASK, NOISE_STREAM_SALT], dtype=np.uint64),
            },
            "buffer": empty_buffer,
            "buffer_pos": 4,
            "has_uint32": 0,
            "uinteger": 0,
        }
        words[row] = bit_generator.random_raw(count)
    doubles = (words >> np.uint64(11)).astype(np.float64) * _DOUBLE_UNIT
    return np.where(doubles > 0.0, doubles, _TINY)


def _philox_uniforms(episode_seed: int, step: int, count: int) -> np.ndarray:
    """Reference (slow) definition of :func:`philox_uniforms` for one ``(episode, step)``."""
    key = (episode_seed & _UINT64_MASK) | (NOISE_STREAM_SALT << 64)
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
        tensordict.set("actuation", torch.from_numpy(realised.astype(np.float32)).reshape(*batch_shape, 3))
        return tensordict

    def __repr__(self) -> str:
        return f"{type(self).__name__}(noise={self.noise_name!r})"
