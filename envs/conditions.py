"""Repeat conditions: the world the agent repeats a route in differs from the one it was taught in.

A route is taught in a house as :func:`~envs.scenes.build_house` makes it, under the
teacher's camera and light; the demonstration (its frames, its stores) is always
rendered so. A *condition* changes what the repeating agent sees, and for
``furniture`` where it can go, with a strength ``s`` in [0, 1]:

* ``none``: nothing; every frame is byte-identical to an env without conditions.
* ``light``: the light scaled by ``1 - 0.7 s`` and tinted warm (red kept, green
  ``x (1 - 0.15 s)``, blue ``x (1 - 0.3 s)``); its direction turned from the view by
  an angle drawn in ``[-90 s, 90 s]`` degrees; at ``s >= 0.5``, with probability 1/2, one
  room the route passes through is lit by a lamp alone
  (:class:`~envs.render.RepeatView`: the headlight dimmed to ambient while the camera is
  in that room, a warm point light at the room's centre).
* ``paint``: a fraction ``s`` of the rooms (at least one when ``s > 0``; corridors are not
  rooms) get new wall and floor colours, each hue drawn anew
  (:func:`~envs.scenes.with_paint`; the textures' pattern and luminance stay).
* ``furniture``: a fraction ``s`` of the pieces (at least one when ``s > 0``) are each
  removed (probability 1/2) or moved by up to 1 m in a random direction, and
  ``round(2 s)`` new pieces stand at random navigable places, the demonstrated path
  included. No piece may cut the navigable space in two (as :func:`~envs.scenes.build_house`
  places them). The occupancy, the geodesic graph, the experts and the success rule all
  use the changed layout; nDTW is still measured against the demonstrated path. A change
  where the agent cannot stand at the route's start or end, or cannot reach its end, is redrawn.
* ``camera``: the repeating robot's camera ``0.3 s`` m lower or higher than the teacher's
  (sign drawn), pitched by an angle in ``[-10 s, 10 s]`` degrees, its vertical field of view
  ``90 + [-15 s, 15 s]`` degrees.
* ``sensor``: exposure ``x (1 + 0.5 s)`` or ``x (1 - 0.5 s)`` (sign drawn), a Gaussian blur of
  ``s`` pixels' standard deviation, and Gaussian pixel noise of ``8 s / 255`` (of the full
  range), new at every frame: each episode draws a bank of :data:`NOISE_BANK_FRAMES` frames'
  normals from a generator seeded by the episode, and each frame takes the window of it that
  starts at an offset drawn for that frame (every pixel's noise is a standard normal, independent
  of its neighbours'; a frame costs one offset instead of 12,288 normals).

Everything is drawn from the episode's seed (:func:`draw_repeat`), in streams of its own,
so the route, a collector's layout or a resume never change it, and ``none`` leaves the
episode as it was. Paint and furniture are drawn from :data:`VARIANTS_PER_HOUSE` seeded
variants of each house per strength (each compiled once, :func:`house_variant`, kept in a
cache of :data:`VARIANT_CACHE_SIZE`); furniture goes on to further variants when the
first drawn does not fit the route.

Mixtures are written like route styles: ``"light@0.5=1,furniture@1=1"`` (a condition
``name@strength``, then its weight after ``=``; ``"none"`` has no strength).

A *mismatched memory* (:func:`draws_mismatch`) is the other way the repeat may differ: the
demonstration's frames are another route's, its actions the episode's own.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from envs.demos import Demonstration
from envs.geodesic import DistanceField, count_components, navigable_beside
from envs.geometry import GEODESIC_RESOLUTION_M, OCCUPANCY_RESOLUTION_M
from envs.render import RepeatView
from envs.scenes import (
    CORRIDOR_LABEL,
    FIELD_OF_VIEW_DEG,
    WALL_CHAR,
    Furniture,
    House,
    build_house,
    furniture_footprint,
    random_furniture,
    with_furniture,
    with_paint,
)

#: The repeat conditions, by name.
CONDITIONS = ("none", "light", "paint", "furniture", "camera", "sensor")
#: Seeded variants of a house per condition and strength (paint, furniture).
VARIANTS_PER_HOUSE = 4
#: Compiled house variants kept per process.
VARIANT_CACHE_SIZE = 64
#: Furniture variants tried for one route before giving up (the first :data:`VARIANTS_PER_HOUSE` are cached ones).
MAX_FURNITURE_DRAWS = 32
#: Attempts at placing one moved or new piece.
PLACEMENT_TRIES = 12
#: Streams of the episode seed (``np.random.default_rng([episode_seed, stream])``).
CONDITION_STREAM = 61_001
MISMATCH_STREAM = 61_002
SENSOR_STREAM = 61_003
#: The light's scale and warm tint at strength s: ``1 - 0.7 s``; green ``1 - 0.15 s``, blue ``1 - 0.3 s``.
LIGHT_DIMMING = 0.7
LIGHT_TINT = (0.0, 0.15, 0.3)
#: The light's direction turns by up to this many degrees times s.
LIGHT_MAX_YAW_DEG = 90.0
#: From this strength, one room may be lit by a lamp alone (with this probability), the lamp this high, metres.
LAMP_MIN_STRENGTH = 0.5
LAMP_PROBABILITY = 0.5
LAMP_HEIGHT_M = 1.8
#: Camera: height change (metres), pitch and field-of-view change (degrees), times s.
CAMERA_HEIGHT_CHANGE_M = 0.3
CAMERA_MAX_PITCH_DEG = 10.0
CAMERA_MAX_FOV_CHANGE_DEG = 15.0
#: The sensor's noise bank: this many frames' normals per episode, a window of it per frame.
NOISE_BANK_FRAMES = 4
#: The sensor's blur kernel reaches this many standard deviations each side.
BLUR_TRUNCATE = 3.0
#: Sensor: exposure change, blur (pixels) and noise (of 255), times s.
SENSOR_EXPOSURE_CHANGE = 0.5
SENSOR_BLUR_PX = 1.0
SENSOR_NOISE = 8.0
#: Furniture: a moved piece goes up to this far, metres; s pieces x this many new ones.
FURNITURE_MAX_MOVE_M = 1.0
FURNITURE_NEW_PIECES = 2


def _check_strength(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) or not 0.0 <= float(value) <= 1.0:
        raise ValueError(f"{name} must be a number in [0, 1], got {value!r}.")
    return float(value)


@dataclass(frozen=True)
class Condition:
    """One repeat condition at one strength.

    Args:
        name: one of :data:`CONDITIONS`.
        strength: in [0, 1] (``none``: 0).

    Examples:
        >>> Condition("light", 0.5).spec
        'light@0.5'
        >>> Condition("fog", 1.0)
        Traceback (most recent call last):
        ...
        ValueError: conditions: unknown condition 'fog'; allowed names are none, light, paint, furniture, camera, sensor.
    """

    name: str
    strength: float = 0.0

    def __post_init__(self) -> None:
        if self.name not in CONDITIONS:
            raise ValueError(f"conditions: unknown condition {self.name!r}; allowed names are {', '.join(CONDITIONS)}.")
        strength = _check_strength(self.strength, f"conditions: the strength of {self.name!r}")
        if self.name == "none" and strength != 0.0:
            raise ValueError(f"conditions: 'none' has no strength (write 'none'), got {strength!r}.")
        object.__setattr__(self, "strength", strength)

    @property
    def spec(self) -> str:
        """``name@strength`` (``none`` alone)."""
        return "none" if self.name == "none" else f"{self.name}@{self.strength!r}"

    @property
    def index(self) -> int:
        """The condition's index in :data:`CONDITIONS` (the env's ``condition`` key)."""
        return CONDITIONS.index(self.name)


@dataclass(frozen=True)
class ConditionMixture:
    """Conditions drawn by weight, one per episode.

    Args:
        weights: :class:`Condition` -> weight (finite, >= 0, summing to more than 0).

    Examples:
        >>> mixture = parse_conditions("light@0.5=1,furniture@1=3")
        >>> mixture.spec, mixture.probabilities[Condition("furniture", 1.0)]
        ('light@0.5=1.0,furniture@1.0=3.0', 0.75)
    """

    weights: Mapping[Condition, float]
    _probabilities: np.ndarray = field(init=False, repr=False, compare=False)

    def __hash__(self) -> int:
        return hash(tuple(self.weights.items()))

    def __post_init__(self) -> None:
        if not isinstance(self.weights, Mapping) or not self.weights:
            raise ValueError(f"conditions must name at least one condition ({', '.join(CONDITIONS)}), got {self.weights!r}.")
        weights = {}
        for condition, weight in self.weights.items():
            if isinstance(weight, bool) or not isinstance(weight, (int, float, np.integer, np.floating)) or not 0 <= weight < math.inf:
                raise ValueError(f"conditions: the weight of {condition.spec!r} must be a finite number >= 0, got {weight!r}.")
            weights[condition] = float(weight)
        if sum(weights.values()) <= 0:
            raise ValueError(f"conditions: the weights must sum to more than 0, got {', '.join(f'{c.spec}={w}' for c, w in weights.items())}.")
        object.__setattr__(self, "weights", dict(weights))
        total = sum(weights.values())
        object.__setattr__(self, "_probabilities", np.array([w / total for w in weights.values()]))

    @property
    def spec(self) -> str:
        """The mixture as :func:`parse_conditions` reads it: ``"light@0.5=1.0,none=1.0"``."""
        return ",".join(f"{condition.spec}={weight!r}" for condition, weight in self.weights.items())

    @property
    def probabilities(self) -> dict[Condition, float]:
        """Condition -> probability of drawing it."""
        return dict(zip(self.weights, self._probabilities.tolist()))

    @property
    def conditions(self) -> tuple[Condition, ...]:
        return tuple(self.weights)

    def draw(self, rng: np.random.Generator) -> Condition:
        """One condition, by weight (one draw from ``rng`` when there are several)."""
        if len(self.weights) == 1:
            return next(iter(self.weights))
        return self.conditions[int(rng.choice(len(self._probabilities), p=self._probabilities))]


def parse_condition(text: str) -> Condition:
    """A :class:`Condition` from ``"name@strength"`` (``"none"`` alone).

    Examples:
        >>> parse_condition("camera@1"), parse_condition("none").spec
        (Condition(name='camera', strength=1.0), 'none')
        >>> parse_condition("light")
        Traceback (most recent call last):
        ...
        ValueError: conditions: 'light' needs a strength in [0, 1], written 'light@0.5'.
    """
    name, at, strength = str(text).strip().partition("@")
    name = name.strip()
    if not at:
        if name != "none":
            if name not in CONDITIONS:
                Condition(name)  # the unknown name's error
            raise ValueError(f"conditions: {name!r} needs a strength in [0, 1], written '{name}@0.5'.")
        return Condition("none")
    try:
        value = float(strength)
    except ValueError:
        raise ValueError(f"conditions: the strength of {name!r} must be a number in [0, 1], got {strength.strip()!r}.") from None
    return Condition(name, value)


def parse_conditions(value: str | Mapping[str, float] | ConditionMixture | None) -> ConditionMixture | None:
    """A :class:`ConditionMixture` from ``"light@0.5=1,furniture@1=1"`` (a weight after ``=``,
    1 where it is left out), a mapping of such names to weights, or a mixture; ``None`` stays ``None``.

    Examples:
        >>> parse_conditions("sensor@0.5").spec
        'sensor@0.5=1.0'
        >>> parse_conditions("light@1.5")
        Traceback (most recent call last):
        ...
        ValueError: conditions: the strength of 'light' must be a number in [0, 1], got 1.5.
        >>> parse_conditions("light@0.5=-1")
        Traceback (most recent call last):
        ...
        ValueError: conditions: the weight of 'light@0.5' must be a finite number >= 0, got -1.0.
    """
    if value is None or isinstance(value, ConditionMixture):
        return value
    if isinstance(value, Mapping):
        items = [(parse_condition(name), weight) for name, weight in value.items()]
    elif isinstance(value, str):
        items = []
        for part in value.split(","):
            if not part.strip():
                raise ValueError(f"conditions must be 'name@strength=weight,...' ({', '.join(CONDITIONS)}), got {value!r}.")
            text, eq, weight = part.partition("=")
            try:
                number = float(weight) if eq else 1.0
            except ValueError:
                raise ValueError(f"conditions: the weight of {text.strip()!r} must be a finite number >= 0, got {weight.strip()!r}.") from None
            items.append((parse_condition(text), number))
    else:
        raise ValueError(f"conditions must be a string like 'light@0.5=1,none=1', a mapping or None, got {type(value).__name__}.")
    weights: dict[Condition, float] = {}
    for condition, weight in items:
        if condition in weights:
            raise ValueError(f"conditions: {condition.spec!r} is named twice in {value!r}.")
        weights[condition] = weight
    return ConditionMixture(weights)


def check_mismatch(value: object) -> float | None:
    """A mismatched-memory fraction: ``None`` or a number in [0, 1].

    Examples:
        >>> check_mismatch(0.25), check_mismatch(None)
        (0.25, None)
    """
    return None if value is None else _check_strength(value, "memory_mismatch")


def draws_mismatch(fraction: float | None, episode_seed: int) -> bool:
    """Whether the episode of ``episode_seed`` gets a mismatched memory (probability ``fraction``)."""
    if not fraction:
        return False
    return bool(np.random.default_rng([int(episode_seed), MISMATCH_STREAM]).random() < fraction)


def mismatch_seed(episode_seed: int) -> int:
    """The seed of the route whose frames a mismatched episode of ``episode_seed`` is shown."""
    return int(np.random.default_rng([int(episode_seed), MISMATCH_STREAM, 1]).integers(2**62))


# ----------------------------------------------------------------------- layouts
def _rooms(house: House) -> list[str]:
    return sorted({str(x) for x in np.unique(house.room_labels)} - {WALL_CHAR, CORRIDOR_LABEL})


def _variant_rng(house_seed: int, name: str, strength: float, k: int) -> np.random.Generator:
    return np.random.default_rng([int(house_seed), CONDITIONS.index(name), int(round(strength * 1_000_000)), int(k)])


@functools.lru_cache(maxsize=VARIANT_CACHE_SIZE)
def house_variant(house_seed: int, name: str, strength: float, k: int) -> House:
    """Variant ``k`` of house ``house_seed`` under ``paint`` or ``furniture`` at ``strength``
    (cached: its model is compiled once, :func:`envs.house_mesh.house_model`).

    Examples:
        >>> house = house_variant(0, "paint", 0.5, 1)
        >>> len(house.paint) >= 1, house is house_variant(0, "paint", 0.5, 1)
        (True, True)
    """
    house = build_house(house_seed)
    rng = _variant_rng(house_seed, name, strength, k)
    if name == "paint":
        rooms = _rooms(house)
        count = 0 if strength == 0 or not rooms else max(1, int(round(strength * len(rooms))))
        chosen = sorted(rng.choice(len(rooms), size=count, replace=False).tolist())
        return with_paint(house, {rooms[i]: (float(rng.random()), float(rng.random())) for i in chosen})
    if name == "furniture":
        return with_furniture(house, _changed_furniture(house, strength, rng))
    raise ValueError(f"house_variant: name must be 'paint' or 'furniture', got {name!r}.")


def _changed_furniture(house: House, strength: float, rng: np.random.Generator) -> list[Furniture]:
    """The furniture of a ``furniture`` variant (the module's rule), every piece kept only if the
    navigable space stays in as many pieces as the walls alone leave."""
    pieces = list(house.furniture)
    if strength == 0:
        return pieces
    bare = with_furniture(house, [])
    walls = bare.occupancy.occupied
    base_components = count_components(bare.graph.navigable)
    count = 0 if not pieces else max(1, int(round(strength * len(pieces))))
    changed = set(rng.choice(len(pieces), size=count, replace=False).tolist())
    kept = [piece for index, piece in enumerate(pieces) if index not in changed]
    navigable = bare.graph.navigable.copy()
    for piece in kept:
        navigable &= navigable_beside(furniture_footprint(house, piece), OCCUPANCY_RESOLUTION_M, GEODESIC_RESOLUTION_M)

    def place(piece: Furniture) -> bool:
        nonlocal navigable
        footprint = furniture_footprint(house, piece)
        if not footprint.any() or (footprint & walls).any():
            return False
        trial = navigable & navigable_beside(footprint, OCCUPANCY_RESOLUTION_M, GEODESIC_RESOLUTION_M)
        if count_components(trial) > base_components:
            return False
        kept.append(piece)
        navigable = trial
        return True

    for index in sorted(changed):
        if rng.random() < 0.5:
            continue  # removed
        piece = pieces[index]
        for _ in range(PLACEMENT_TRIES):
            angle, distance = rng.uniform(0, 2 * np.pi), rng.uniform(0, FURNITURE_MAX_MOVE_M)
            moved = dataclasses.replace(piece, centre_xy=piece.centre_xy + distance * np.array([np.cos(angle), np.sin(angle)]))
            if place(moved):
                break
    free = np.argwhere(bare.graph.navigable)
    for _ in range(int(round(FURNITURE_NEW_PIECES * strength))):
        for _ in range(PLACEMENT_TRIES):
            row, col = free[int(rng.integers(len(free)))]
            centre = (np.array([col, row]) + 0.5) * GEODESIC_RESOLUTION_M
            if place(random_furniture(rng, centre)):
                break
    return kept


def _route_field(house: House, demonstration: Demonstration) -> DistanceField | None:
    """The route end's distance field in ``house``, or ``None`` where the agent cannot stand at the
    route's start or end there, or cannot reach its end from its start."""
    start, end = demonstration.start_pose[:2], demonstration.end_xy
    if not (house.occupancy.is_free(start) and house.occupancy.is_free(end)):
        return None
    graph = house.graph
    if not graph.navigable.ravel()[graph.node(start)]:
        return None
    field = graph.distance_field(end)
    return field if np.isfinite(field.at(start)) else None


# ------------------------------------------------------------------------ repeat
@dataclass(frozen=True)
class SensorChange:
    """A camera sensor's change: exposure, blur and per-frame noise (see the module).

    The exposure and the blur are one linear map of each channel, ``rows @ channel @ columns``
    (banded matrices of the Gaussian, edges repeated, the exposure folded into ``rows``): two
    small matrix products cost less than a separable filter's line loop on a 64 px frame.

    Examples:
        >>> sensor = SensorChange(exposure=1.5, blur_px=1.0, noise=8.0)
        >>> frames = np.full((1, 16, 16, 3), 100, dtype=np.uint8)
        >>> sensor.apply(frames, sensor.noise_bank(frames.shape[1:], np.random.default_rng(0)), np.random.default_rng(1))
        >>> bool(130 < frames.mean() < 170), bool(frames.std() > 3)
        (True, True)
    """

    exposure: float
    blur_px: float
    noise: float

    def noise_bank(self, frame_shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
        """One episode's noise: :data:`NOISE_BANK_FRAMES` frames of ``frame_shape``'s normals
        times the noise, flat float32."""
        size = NOISE_BANK_FRAMES * math.prod(frame_shape)
        return rng.standard_normal(size, dtype=np.float32) * np.float32(self.noise)

    def apply(self, frames: np.ndarray, bank: np.ndarray, rng: np.random.Generator) -> None:
        """Change ``(k, H, W, 3)`` uint8 ``frames`` in place, one after another; each frame's
        noise is the window of ``bank`` (:meth:`noise_bank`) at an offset drawn from ``rng``."""
        height, width = frames.shape[1:3]
        rows, columns = _blur_matrices(height, self.blur_px, self.exposure), _blur_matrices(width, self.blur_px, 1.0).T
        size = height * width * 3
        for frame in frames:
            channels = rows @ np.ascontiguousarray(frame.transpose(2, 0, 1), dtype=np.float32) @ columns
            offset = int(rng.integers(len(bank) - size + 1))
            channels += bank[offset : offset + size].reshape(channels.shape)
            np.rint(channels, out=channels)
            np.clip(channels, 0, 255, out=channels)
            frame[...] = channels.transpose(1, 2, 0)


@functools.lru_cache(maxsize=32)
def _blur_matrices(size: int, sigma: float, scale: float) -> np.ndarray:
    """``scale`` times the ``(size, size)`` matrix of a 1-d Gaussian blur of ``sigma`` pixels
    (reaching :data:`BLUR_TRUNCATE` sigma, the edge pixels repeated), float32, read-only."""
    radius = int(BLUR_TRUNCATE * sigma + 0.5)
    offsets = np.arange(-radius, radius + 1)
    kernel = np.exp(-0.5 * (offsets / sigma) ** 2) if sigma > 0 else (offsets == 0).astype(float)
    kernel *= scale / kernel.sum()
    matrix = np.zeros((size, size))
    for row in range(size):
        np.add.at(matrix[row], np.clip(row + offsets, 0, size - 1), kernel)
    matrix = matrix.astype(np.float32)
    matrix.flags.writeable = False
    return matrix


@dataclass
class Repeat:
    """The world one episode is repeated in.

    Attributes:
        condition: the condition drawn.
        house: the layout the agent moves and is seen in (the teaching house unless paint or
            furniture changed it).
        demonstration: the route, its end's distance field and shortest length in ``house``.
        view: the camera and light (``None``: the teacher's).
        sensor: the sensor's change (``None``: none).
        noise_rng: the sensor noise's generator, seeded by the episode.
        noise_bank: the sensor's noise bank (:meth:`SensorChange.noise_bank`), drawn at the first frame.
    """

    condition: Condition
    house: House
    demonstration: Demonstration
    view: RepeatView | None = None
    sensor: SensorChange | None = None
    noise_rng: np.random.Generator | None = None
    noise_bank: np.ndarray | None = None

    @property
    def changes_frames(self) -> bool:
        """Whether the agent's frames differ from the teaching world's at the same pose."""
        return self.condition.name != "none" and self.condition.strength > 0

    def sense(self, frames: np.ndarray) -> None:
        """Apply the sensor's change to the agent's ``(k, H, W, 3)`` frames in place."""
        if self.sensor is not None:
            if self.noise_bank is None:
                self.noise_bank = self.sensor.noise_bank(frames.shape[1:], self.noise_rng)
            self.sensor.apply(frames, self.noise_bank, self.noise_rng)


def draw_repeat(mixture: ConditionMixture, house: House, demonstration: Demonstration, episode_seed: int) -> Repeat:
    """The repeat of one episode: a condition drawn from ``mixture`` and its change, all from
    ``episode_seed`` (streams of their own: the route's draws are untouched).

    Examples:
        >>> from envs.route_styles import planner_route
        >>> house = build_house(0)
        >>> demo = planner_route(house, np.random.default_rng(0), 10)
        >>> repeat = draw_repeat(parse_conditions("camera@1"), house, demo, episode_seed=3)
        >>> abs(repeat.view.eye_offset_m), repeat.house is house
        (0.3, True)
    """
    rng = np.random.default_rng([int(episode_seed), CONDITION_STREAM])
    condition = mixture.draw(rng)
    name, s = condition.name, condition.strength
    repeat = Repeat(condition, house, demonstration)
    if name == "none" or s == 0:
        return repeat
    if name == "light":
        dim = 1.0 - LIGHT_DIMMING * s
        rgb = tuple(float(dim * (1.0 - t * s)) for t in LIGHT_TINT)
        yaw = float(rng.uniform(-LIGHT_MAX_YAW_DEG * s, LIGHT_MAX_YAW_DEG * s))
        lamp_room = lamp_xyz = None
        if s >= LAMP_MIN_STRENGTH and rng.random() < LAMP_PROBABILITY:
            rooms = sorted({house.room_at(xy) for xy in demonstration.poses[:, :2]} - {CORRIDOR_LABEL, WALL_CHAR})
            if rooms:
                lamp_room = rooms[int(rng.integers(len(rooms)))]
                rows, cols = np.nonzero(house.room_labels == lamp_room)
                centre = (np.array([cols.mean(), rows.mean()]) + 0.5) * house.cell_size_m
                lamp_xyz = (float(centre[0]), float(centre[1]), LAMP_HEIGHT_M)
        repeat.view = RepeatView(light_rgb=rgb, light_yaw_deg=yaw, lamp_room=lamp_room, lamp_xyz=lamp_xyz)
    elif name == "camera":
        sign = 1.0 if rng.random() < 0.5 else -1.0
        repeat.view = RepeatView(
            eye_offset_m=sign * CAMERA_HEIGHT_CHANGE_M * s,
            pitch_deg=float(rng.uniform(-CAMERA_MAX_PITCH_DEG * s, CAMERA_MAX_PITCH_DEG * s)),
            fovy_deg=float(FIELD_OF_VIEW_DEG + rng.uniform(-CAMERA_MAX_FOV_CHANGE_DEG * s, CAMERA_MAX_FOV_CHANGE_DEG * s)),
        )
    elif name == "sensor":
        sign = 1.0 if rng.random() < 0.5 else -1.0
        repeat.sensor = SensorChange(1.0 + sign * SENSOR_EXPOSURE_CHANGE * s, SENSOR_BLUR_PX * s, SENSOR_NOISE * s)
        repeat.noise_rng = np.random.default_rng([int(episode_seed), SENSOR_STREAM])
    elif name == "paint":
        repeat.house = house_variant(house.seed, "paint", s, int(rng.integers(VARIANTS_PER_HOUSE)))
    elif name == "furniture":
        first = int(rng.integers(VARIANTS_PER_HOUSE))
        order = [(first + j) % VARIANTS_PER_HOUSE for j in range(VARIANTS_PER_HOUSE)] + list(range(VARIANTS_PER_HOUSE, MAX_FURNITURE_DRAWS))
        for k in order:
            variant = house_variant(house.seed, "furniture", s, k)
            end_field = _route_field(variant, demonstration)
            if end_field is not None:
                break
        else:
            raise RuntimeError(
                f"no furniture change at strength {s} in {MAX_FURNITURE_DRAWS} draws leaves the route of episode seed "
                f"{episode_seed} in house {house.seed} feasible."
            )
        repeat.house = variant
        repeat.demonstration = dataclasses.replace(
            demonstration, end_field=end_field, shortest_length_m=float(end_field.at(demonstration.start_pose[:2]))
        )
    return repeat


__all__ = [
    "CONDITIONS",
    "Condition",
    "ConditionMixture",
    "Repeat",
    "SensorChange",
    "VARIANTS_PER_HOUSE",
    "check_mismatch",
    "draw_repeat",
    "draws_mismatch",
    "house_variant",
    "mismatch_seed",
    "parse_condition",
    "parse_conditions",
]
