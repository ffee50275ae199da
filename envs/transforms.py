"""Environment-side transforms: actuation noise.

:class:`ActuationNoise` turns the discrete action the policy chose into the
physical motion the robot actually makes. It is an inverse transform: on the way
into the environment it writes ``"actuation_noise"`` = (forward m, lateral m,
rotation rad), the realised motion minus the nominal step, in the agent's frame,
which :class:`~envs.nav_env.PathFollowEnv` adds to the nominal step. The stored
``"action"`` stays the one the policy chose.

``"actuation_noise"`` is declared in the env's state spec (zero when absent:
noise-free), so it crosses process boundaries: the transform works inside each
worker's factory and around a ``SerialEnv``/``ParallelEnv`` or a collector alike.

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

Presets (:data:`NOISE_PRESETS`); in all of them the agent translates along its
current heading, then rotates, and translation and rotation noise are drawn
independently:

* ``none``: the nominal step (forward 0.3 m, turns 20 degrees).
* ``paper``: the first author's ``NoisyAction.py`` (``Hwiyeon/RPF``, repository
  root, clip ratio 0.2). With s = N(0, 1) rad (sd about 57 degrees):

  - forward: translation clip(0.3 + N(0.3, 0.5^2), 0.24, 0.36) m (that code draws
    the noise with mean 0.3 and adds it to the nominal 0.3, so the mean counts
    twice: about two thirds of forward steps are 0.36 m), rotation
    clip(s, -4, +4) degrees;
  - left turn: translation clip(N(0, 0.5^2), 0, 0.06) m forward, rotation
    clip(20 + s, 16, 24) degrees; right turn: the same translation, rotation
    clip(-20 + s, -24, -16) degrees.
* ``paper_symmetric``: N(0, 0.5^2) m forward and N(0, 1^2) rad rotation with the
  realised step clipped to +-20% of the nominal one and no cross terms (forward
  steps 0.24-0.36 m with no rotation, turns 16-24 degrees with no translation).
  This was ``paper`` before the first author's code was followed; the checkpoints
  and results made before that change were made under it.
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
from tensordict import NestedKey, TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

from envs.demos import nominal_motion
from envs.expert import FORWARD, TURN_LEFT, TURN_RIGHT

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
        mean: (forward m, lateral m, rotation rad) means, added to the nominal step.
        std: (forward m, lateral m, rotation rad) standard deviations.
        forward_bounds_m: if set, the realised forward translation is clipped to
            ``(low, high)`` metres and the lateral one is dropped.
        rotation_bounds_rad: if set, the realised rotation is clipped to
            ``(low, high)`` radians (for a left turn; a right turn uses the mirror
            ``(-high, -low)``) and the lateral translation is dropped.
    """

    mean: tuple[float, float, float] = (0.0, 0.0, 0.0)
    std: tuple[float, float, float] = (0.0, 0.0, 0.0)
    forward_bounds_m: tuple[float, float] | None = None
    rotation_bounds_rad: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if any(s < 0 for s in self.std):
            raise ValueError(f"noise std must be >= 0, got {self.std}.")
        for name in ("forward_bounds_m", "rotation_bounds_rad"):
            bounds = getattr(self, name)
            if bounds is not None and (len(bounds) != 2 or not bounds[0] <= bounds[1]):
                raise ValueError(f"{name} must be a (low, high) pair with low <= high, got {bounds!r}.")

    @property
    def bounded(self) -> bool:
        """True when the realised motion is clipped to explicit bounds."""
        return self.forward_bounds_m is not None or self.rotation_bounds_rad is not None


@dataclass(frozen=True)
class NoiseModel:
    """Actuation noise model.

    Args:
        linear: noise of the forward action.
        rotational: noise of the turn actions.
        clip_fraction: if set, the realised forward step and turn are clipped to
            nominal * (1 +- clip_fraction), and the motion orthogonal to the
            commanded one is dropped (the ``paper_symmetric`` preset).
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
        if self.clip_fraction is not None and (self.linear.bounded or self.rotational.bounded):
            raise ValueError("clip_fraction and explicit motion bounds cannot be combined; give one of them.")
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
        if "clip" in tables:
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
        elif self.linear.bounded or self.rotational.bounded:
            tables["clip"] = self._bounds_table(action)
        for value in tables.values():
            value.setflags(write=False)
        object.__setattr__(self, "_cached_tables", tables)  # frozen dataclass: not a field
        return tables

    def _bounds_table(self, action: np.ndarray) -> np.ndarray:
        """``(len(action), 4)`` clip bounds (forward low/high m, rotation low/high rad) per action row.

        Unbounded parts of a motion are left free (+-inf); STOP and unknown actions
        are pinned to no motion.
        """
        table = np.tile(np.array([-np.inf, np.inf, -np.inf, np.inf]), (len(action), 1))
        for row, act in enumerate(action):
            motion = self.linear if act == FORWARD else self.rotational
            if act not in (FORWARD, TURN_LEFT, TURN_RIGHT):
                table[row] = 0.0
                continue
            if motion.forward_bounds_m is not None:
                table[row, 0:2] = motion.forward_bounds_m
            if motion.rotation_bounds_rad is not None:
                low, high = motion.rotation_bounds_rad
                table[row, 2:4] = (-high, -low) if act == TURN_RIGHT else (low, high)
        return table


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


#: The first author's NoisyAction.py: forward translation clip(0.3 + N(0.3, 0.5^2), 0.24, 0.36) m.
PAPER_FORWARD_NOISE_MEAN_M = 0.3
PAPER_FORWARD_BOUNDS_M = (0.24, 0.36)
#: ... and rotation clip(N(0, 1 rad), -4, 4) degrees on a forward step.
PAPER_FORWARD_ROTATION_BOUND_DEG = 4.0
#: Turns: translation clip(N(0, 0.5^2), 0, 0.06) m forward, rotation clip(20 + s, 16, 24) degrees.
PAPER_TURN_FORWARD_BOUNDS_M = (0.0, 0.06)
PAPER_TURN_BOUNDS_DEG = (16.0, 24.0)
#: Standard deviations of the paper's noise: 0.5 m translation, 1 rad rotation.
PAPER_TRANSLATION_STD_M = 0.5
PAPER_ROTATION_STD_RAD = 1.0
_PAPER_STD = (PAPER_TRANSLATION_STD_M, 0.0, PAPER_ROTATION_STD_RAD)
_PAPER_SYMMETRIC_MOTION = GaussianMotionNoise((0.0, 0.0, 0.0), _PAPER_STD)

#: Named noise models; see the module docstring.
NOISE_PRESETS: dict[str, NoiseModel] = {
    "none": NoiseModel(),
    "paper": NoiseModel(
        linear=GaussianMotionNoise(
            (PAPER_FORWARD_NOISE_MEAN_M, 0.0, 0.0),
            _PAPER_STD,
            forward_bounds_m=PAPER_FORWARD_BOUNDS_M,
            rotation_bounds_rad=(
                -np.deg2rad(PAPER_FORWARD_ROTATION_BOUND_DEG),
                np.deg2rad(PAPER_FORWARD_ROTATION_BOUND_DEG),
            ),
        ),
        rotational=GaussianMotionNoise(
            (0.0, 0.0, 0.0),
            _PAPER_STD,
            forward_bounds_m=PAPER_TURN_FORWARD_BOUNDS_M,
            rotation_bounds_rad=tuple(float(np.deg2rad(b)) for b in PAPER_TURN_BOUNDS_DEG),
        ),
    ),
    "paper_symmetric": NoiseModel(linear=_PAPER_SYMMETRIC_MOTION, rotational=_PAPER_SYMMETRIC_MOTION, clip_fraction=0.2),
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


#: The noise every recipe and config uses unless told otherwise.
DEFAULT_NOISE = "paper"


def make_noise_model(noise: str | NoiseModel) -> NoiseModel:
    """A preset by name, or a :class:`NoiseModel` as it is."""
    if isinstance(noise, NoiseModel):
        return noise
    if noise not in NOISE_PRESETS:
        raise ValueError(f"noise must be one of {sorted(NOISE_PRESETS)} or a NoiseModel, got {noise!r}.")
    return NOISE_PRESETS[noise]


#: Key of the realised-minus-nominal motion the transform writes and the env reads.
ACTUATION_NOISE_KEY = "actuation_noise"


def actuation_noise_spec(batch_shape: torch.Size | tuple[int, ...] = (), device: torch.device | str | None = None) -> Unbounded:
    """Spec of ``"actuation_noise"``: (forward m, lateral m, rotation rad) float32 per agent."""
    return Unbounded(shape=(*batch_shape, 3), dtype=torch.float32, device=device)


class ActuationNoise(Transform):
    """Actuation noise for :class:`~envs.nav_env.PathFollowEnv` as an inverse transform.

    Before each step it writes ``"actuation_noise"``: the realised motion of the
    chosen action (see :class:`NoiseModel`) minus its nominal step, which the env
    adds to the nominal step. The key is declared in the input (state) spec, so a
    batched env (``SerialEnv``/``ParallelEnv``) sends it to its workers: the
    transform may sit inside each worker's factory or around the batched env.

    Args:
        noise: a preset name from :data:`NOISE_PRESETS` or a :class:`NoiseModel`.
        action_key: the policy's action key.

    Examples:
        >>> from torchrl.envs import TransformedEnv
        >>> from envs.nav_env import PathFollowEnv
        >>> env = TransformedEnv(PathFollowEnv(num_houses=1, demo_length=5, render=False), ActuationNoise("paper"))
        >>> "actuation_noise" in env.state_spec.keys()
        True
        >>> td = env.rollout(3)  # at most 3 steps: it stops early if the agent arrives
        >>> td["next", "pose"].shape[-1], td["action"].dtype
        (3, torch.int64)
    """

    def __init__(self, noise: str | NoiseModel = "paper", action_key: NestedKey = "action") -> None:
        super().__init__(in_keys_inv=[action_key], out_keys_inv=[action_key])
        self.noise_model = make_noise_model(noise)
        self.noise_name = noise if isinstance(noise, str) else "custom"
        self.action_key = action_key

    def transform_input_spec(self, input_spec: Composite) -> Composite:
        """Declare ``"actuation_noise"`` in the state spec (a no-op when the env already does)."""
        state_spec = input_spec["full_state_spec"]
        if ACTUATION_NOISE_KEY not in state_spec.keys():
            state_spec[ACTUATION_NOISE_KEY] = actuation_noise_spec(state_spec.shape, state_spec.device)
        return input_spec

    def _inv_call(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(self.action_key)
        batch_shape = tensordict.batch_size
        flat_action = action.reshape(-1).cpu().numpy()
        realised = self.noise_model.sample(
            flat_action,
            tensordict.get("episode_seed").reshape(-1).cpu().numpy(),
            tensordict.get("step_count").reshape(-1).cpu().numpy(),
        )
        noise = realised - nominal_motion(flat_action)
        tensordict.set(
            ACTUATION_NOISE_KEY,
            torch.from_numpy(noise.astype(np.float32)).reshape(*batch_shape, 3).to(action.device),
        )
        return tensordict

    def __repr__(self) -> str:
        return f"{type(self).__name__}(noise={self.noise_name!r})"
