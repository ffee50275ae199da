"""The description of a set of episodes: one frozen dataclass that every config holds.

Habitat's ``NavigationEpisode`` is shared by its dataset, sensors and measures; here
:class:`EpisodeSpec` plays that part. It says *which* episodes are played: the houses
(a split, or explicit house seeds), the actuation noise, the demonstrations' length,
the episode's step limit, the frame size, the task, the routes' style and lengths, and
the seed of the episode stream. Episode ``j`` of a spec depends only on the spec and ``j``.

What the episodes are used for (how many, how many agents step them, where their
demonstrations are stored) belongs to the config that holds a spec: the demonstration
store (:class:`~envs.demo_store.DemoStoreConfig`), a BC dataset, an evaluation, a
collector, a DAgger round. The env is built from a spec by :func:`envs.factory.make_env`
(or :meth:`envs.nav_env.PathFollowEnv.from_spec`).

A new property of an episode is added here, once: a field, its check in
:meth:`EpisodeSpec.__post_init__`, and (when it is set) its entry in
:meth:`EpisodeSpec.identity`.

Configs that hold a spec are written flat in JSON and YAML (``split: val`` beside
``num_episodes: 300``): :func:`flat_dict` and :func:`from_flat` convert, and
:func:`nest_flat_keys` lets YAML files and ``key=value`` overrides keep their flat keys.
"""
from __future__ import annotations

import dataclasses
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

from envs.conditions import check_mismatch, parse_conditions
from envs.follow import default_max_steps
from envs.homing import FOLLOW, check_task
from envs.house_grid import check_demo_length
from envs.route_styles import RouteMixture, route_mixture_for
from envs.scenes import split_seeds
from envs.transforms import DEFAULT_NOISE, make_noise_model

#: The name of the field under which a config holds its :class:`EpisodeSpec`.
EPISODES_FIELD = "episodes"
#: Fields of :class:`EpisodeSpec` written only when set (``None`` is the default every
#: earlier record was made with, so records without them keep their identity).
OPTIONAL_FIELDS = ("house_seeds", "route_style", "route_lengths", "conditions", "memory_mismatch")

Config = TypeVar("Config")


def _check_int(name: str, value: object, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name} must be an int >= {minimum}, got {value!r}.")


@dataclass(frozen=True)
class EpisodeSpec:
    """Which episodes are played: the one description that stores, datasets, evaluations,
    collectors, DAgger rounds and the env share.

    Args:
        split: house split (``"train"``, ``"val"`` or ``"test"``).
        num_houses: houses of the split (``None``: the split's default).
        noise: actuation-noise preset (:data:`~envs.transforms.NOISE_PRESETS`).
        demo_length: demonstration length n, steps (with ``route_lengths``: the longest,
            to which shorter demonstrations are padded).
        max_steps: the episode's step limit; ``None``: each demonstration's own,
            ``ceil(5/3 n)`` (:func:`~envs.follow.default_max_steps`).
        image_size: frame side, pixels.
        task: ``"follow"`` or ``"homing"`` (:mod:`envs.homing`).
        route_style: the routes' style (:mod:`envs.route_styles`: a style name or
            ``"style=weight,..."``); ``None``: the planner's routes, as the paper samples them.
        route_lengths: ``(shortest, longest)`` steps of routes with ``route_style``
            (``None``: ``demo_length``).
        seed: seed of the episode stream (episode ``j`` depends only on it and ``j``).
        house_seeds: explicit houses instead of the split's (``None``: the split's).
        conditions: how the world of the repeat differs from the teaching's (:mod:`envs.conditions`:
            ``"light@0.5"``, or a mixture ``"light@0.5=1,furniture@1=1"``), drawn per episode;
            ``None``: the teaching world itself.
        memory_mismatch: the fraction of episodes shown another route's frames with their own
            actions (:func:`~envs.conditions.draws_mismatch`); ``None``: none.

    Examples:
        >>> spec = EpisodeSpec(split="val", demo_length=40, max_steps=None, route_style="tour")
        >>> spec.step_limit, spec.route_lengths, spec.route_style
        (67, (40, 40), 'tour=1.0')
        >>> EpisodeSpec(noise="lol")
        Traceback (most recent call last):
        ...
        ValueError: noise must be one of ['locobot', 'none', 'paper', 'paper_symmetric', 'paper_unclipped'] or a NoiseModel, got 'lol'.
    """

    split: str = "train"
    num_houses: int | None = None
    noise: str = DEFAULT_NOISE
    demo_length: int = 30
    max_steps: int | None = None
    image_size: int = 64
    task: str = FOLLOW
    route_style: str | None = None
    route_lengths: tuple[int, int] | None = None
    seed: int = 0
    house_seeds: tuple[int, ...] | None = None
    conditions: str | None = None
    memory_mismatch: float | None = None

    def __post_init__(self) -> None:
        check_task(self.task)
        make_noise_model(self.noise)
        check_demo_length(self.demo_length)
        _check_int("image_size", self.image_size, 1)
        if self.max_steps is not None:
            _check_int("max_steps", self.max_steps, 1)
        _check_int("seed", self.seed, 0)
        if self.house_seeds is not None:
            seeds = tuple(self.house_seeds)
            if not seeds or any(isinstance(s, bool) or not isinstance(s, int) or s < 0 for s in seeds):
                raise ValueError(f"house_seeds must be None or a non-empty list of non-negative ints, got {self.house_seeds!r}.")
            if self.num_houses is not None:
                raise ValueError("house_seeds cannot be combined with num_houses: give the houses or their number.")
            object.__setattr__(self, "house_seeds", seeds)
        else:
            split_seeds(self.split, self.num_houses)  # validates split and num_houses
        if self.route_lengths is not None and not isinstance(self.route_lengths, str):
            object.__setattr__(self, "route_lengths", tuple(self.route_lengths))  # a list in YAML and JSON
        conditions = parse_conditions(self.conditions)
        if conditions is not None:  # one spelling of each mixture
            object.__setattr__(self, "conditions", conditions.spec)
        object.__setattr__(self, "memory_mismatch", check_mismatch(self.memory_mismatch))
        mixture = route_mixture_for(self.route_style, self.route_lengths, self.demo_length)
        if mixture is not None:  # one spelling of each mixture, as stores, names and records write it
            object.__setattr__(self, "route_style", mixture.spec)
            object.__setattr__(self, "route_lengths", (mixture.min_length, mixture.max_length))

    @property
    def step_limit(self) -> int:
        """The longest an episode may be, steps: ``max_steps``, or the rule's for ``demo_length``."""
        return default_max_steps(self.demo_length) if self.max_steps is None else self.max_steps

    @property
    def mixture(self) -> RouteMixture | None:
        """The routes' :class:`~envs.route_styles.RouteMixture` (``None``: the planner's, of ``demo_length`` steps)."""
        return route_mixture_for(self.route_style, self.route_lengths, self.demo_length)

    @property
    def frames_id_key(self) -> str:
        """The key of the stored demonstration whose frames an env of a demo store shows: ``demo_id``,
        or with ``memory_mismatch`` set ``memory_id`` (``demo_id`` stays the episode's own route).

        Examples:
            >>> EpisodeSpec().frames_id_key, EpisodeSpec(memory_mismatch=0.5).frames_id_key
            ('demo_id', 'memory_id')
        """
        return "demo_id" if self.memory_mismatch is None else "memory_id"

    @property
    def conditions_tag(self) -> str:
        """The repeat's world in a directory name: ``""`` for the teaching world, else
        ``"-<conditions>"`` and ``"-mismatch<fraction>"``.

        Examples:
            >>> EpisodeSpec(conditions="light@0.5=1,furniture@1=1", memory_mismatch=0.25).conditions_tag
            '-light0.5x1.0+furniture1.0x1.0-mismatch0.25'
        """
        tag = ""
        if self.conditions is not None:
            tag += "-" + self.conditions.replace("@", "").replace("=", "x").replace(",", "+")
        if self.memory_mismatch is not None:
            tag += f"-mismatch{self.memory_mismatch!r}"
        return tag

    @property
    def routes_tag(self) -> str:
        """The routes in a directory name: ``""`` for the planner's, else ``"-<style>-<shortest>to<longest>"``.

        Examples:
            >>> EpisodeSpec(demo_length=40, route_style="planner=1,driven=1", route_lengths=(10, 40)).routes_tag
            '-planner1.0+driven1.0-10to40'
        """
        if self.route_style is None:
            return ""
        return f"-{self.route_style.replace('=', '').replace(',', '+')}-{self.route_lengths[0]}to{self.route_lengths[1]}"

    @property
    def house_seeds_tag(self) -> str:
        """Explicit houses in a directory name: ``""`` for a split's, else ``"-houses<seed>+<seed>..."``."""
        return "" if self.house_seeds is None else "-houses" + "+".join(map(str, self.house_seeds))

    def identity(self) -> dict:
        """The fields that fix the episodes, as JSON writes them: the optional fields
        (:data:`OPTIONAL_FIELDS`) only when set, so the identity of the planner's episodes
        is what it was before those fields existed.

        Examples:
            >>> sorted(EpisodeSpec().identity())
            ['demo_length', 'image_size', 'max_steps', 'noise', 'num_houses', 'seed', 'split', 'task']
            >>> EpisodeSpec(route_style="driven").identity()["route_lengths"]
            [30, 30]
        """
        fields = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        out = {key: value for key, value in fields.items() if not (key in OPTIONAL_FIELDS and value is None)}
        return {key: list(value) if isinstance(value, tuple) else value for key, value in out.items()}

    def replace(self, **changes: Any) -> EpisodeSpec:
        """A copy with ``changes`` (checked and normalised again).

        Examples:
            >>> EpisodeSpec().replace(split="test").split
            'test'
        """
        return dataclasses.replace(self, **changes)


#: The fields of :class:`EpisodeSpec`, in order.
SPEC_FIELDS = tuple(f.name for f in dataclasses.fields(EpisodeSpec))
#: Fields of :class:`EpisodeSpec` that fix a policy's inputs: a policy is evaluated on episodes
#: that agree with its training episodes in these.
POLICY_SIZE_FIELDS = ("demo_length", "image_size")
#: Fields in which a recipe's evaluation episodes follow its training episodes unless a YAML
#: file or an override sets them (:func:`spf_rl.config.load_config`).
SIZE_FIELDS = ("demo_length", "max_steps", "image_size", "route_style", "route_lengths")


def check_sizes_match(trained: EpisodeSpec, trained_name: str, **evaluations: EpisodeSpec) -> None:
    """Raise ``ValueError`` where an evaluation's episodes differ from the training episodes in
    :data:`POLICY_SIZE_FIELDS` (the policy is built for the training episodes' sizes).

    Examples:
        >>> check_sizes_match(EpisodeSpec(demo_length=40), "data", val=EpisodeSpec(demo_length=30))
        Traceback (most recent call last):
        ...
        ValueError: val.demo_length=30 differs from data.demo_length=40: the policy is built for its training episodes; set both alike.
    """
    for name, spec in evaluations.items():
        for key in POLICY_SIZE_FIELDS:
            if getattr(spec, key) != getattr(trained, key):
                raise ValueError(
                    f"{name}.{key}={getattr(spec, key)!r} differs from {trained_name}.{key}={getattr(trained, key)!r}: "
                    "the policy is built for its training episodes; set both alike."
                )


def flat_dict(config: Any) -> dict:
    """A config that holds an :class:`EpisodeSpec` (in its ``episodes`` field) as one flat
    dict, as JSON files and YAML write it: its own fields, then the spec's
    :meth:`~EpisodeSpec.identity` in place of ``episodes``. Nested configs are flattened too.

    Examples:
        >>> @dataclass(frozen=True)
        ... class Store:
        ...     num_demos: int = 10
        ...     episodes: EpisodeSpec = EpisodeSpec()
        >>> flat_dict(Store())["split"], "episodes" in flat_dict(Store())
        ('train', False)
    """
    out: dict = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if isinstance(value, EpisodeSpec):
            out.update(value.identity())
        elif dataclasses.is_dataclass(value):
            out[f.name] = flat_dict(value)
        else:
            out[f.name] = list(value) if isinstance(value, tuple) else value
    return out


def from_flat(cls: type[Config], values: Mapping[str, Any]) -> Config:
    """``cls`` (a config with an ``episodes`` field) from a flat dict of :func:`flat_dict`:
    the keys of :data:`SPEC_FIELDS` change ``cls``'s default :class:`EpisodeSpec` (a nested
    ``episodes`` mapping is read too), as the keys of a YAML file do.

    Examples:
        >>> @dataclass(frozen=True)
        ... class Store:
        ...     num_demos: int = 10
        ...     episodes: EpisodeSpec = EpisodeSpec()
        >>> from_flat(Store, {"num_demos": 3, "split": "val"}).episodes.split
        'val'
    """
    values = dict(values)
    spec = dict(values.pop(EPISODES_FIELD, None) or {})
    spec.update({key: values.pop(key) for key in SPEC_FIELDS if key in values})
    return cls(**values, episodes=_default_episodes(cls).replace(**spec))


def _default_episodes(cls: type) -> EpisodeSpec:
    """The default :class:`EpisodeSpec` of config class ``cls`` (``EpisodeSpec()`` where it has none)."""
    field = next((f for f in dataclasses.fields(cls) if f.name == EPISODES_FIELD), None)
    if field is not None and field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    if field is not None and isinstance(field.default, EpisodeSpec):
        return field.default
    return EpisodeSpec()


def nest_flat_keys(node: Any, schema: Any) -> Any:
    """``node`` (a YAML mapping, or the dotted keys of overrides) with the flat episode keys of
    every config in ``schema`` moved under its ``episodes`` key: ``data.split`` becomes
    ``data.episodes.split``. Both spellings are accepted; the flat one is documented.

    Args:
        node: a mapping (a YAML layer), or a sequence of ``key=value`` overrides.
        schema: the dataclass type the node configures.

    Examples:
        >>> from envs.demo_store import DemoStoreConfig
        >>> nest_flat_keys({"num_demos": 3, "split": "val"}, DemoStoreConfig)
        {'num_demos': 3, 'episodes': {'split': 'val'}}
        >>> nest_flat_keys(["noise=none", "num_demos=3", "episodes.seed=2"], DemoStoreConfig)
        ['episodes.noise=none', 'num_demos=3', 'episodes.seed=2']
    """
    if isinstance(node, Sequence) and not isinstance(node, (str, Mapping)):
        return [_nest_override(item, schema) for item in node]
    return _nest_mapping(node, schema)


def _field_types(schema: Any) -> dict[str, Any]:
    if not (isinstance(schema, type) and dataclasses.is_dataclass(schema)):
        return {}
    return typing.get_type_hints(schema)


def _holds_spec(schema: Any) -> bool:
    return _field_types(schema).get(EPISODES_FIELD) is EpisodeSpec


def _nest_mapping(node: Any, schema: Any) -> Any:
    if not isinstance(node, Mapping):
        return node
    types = _field_types(schema)
    out: dict = {}
    moved: dict = {}
    for key, value in node.items():
        if _holds_spec(schema) and key in SPEC_FIELDS:
            moved[key] = value
        elif key in types:
            out[key] = _nest_mapping(value, types[key])
        else:
            out[key] = value
    if moved:
        out[EPISODES_FIELD] = {**dict(out.get(EPISODES_FIELD) or {}), **moved}
    return out


def _nest_override(item: str, schema: Any) -> str:
    if "=" not in item:
        return item
    key, value = item.split("=", 1)
    parts, node = key.split("."), schema
    for index, part in enumerate(parts):
        if _holds_spec(node) and part in SPEC_FIELDS and index == len(parts) - 1:
            parts.insert(index, EPISODES_FIELD)
            break
        node = _field_types(node).get(part)
        if node is None:
            break
    return ".".join(parts) + "=" + value


__all__ = ["EPISODES_FIELD", "OPTIONAL_FIELDS", "POLICY_SIZE_FIELDS", "SIZE_FIELDS", "SPEC_FIELDS", "check_sizes_match", "EpisodeSpec", "flat_dict", "from_flat", "nest_flat_keys"]
