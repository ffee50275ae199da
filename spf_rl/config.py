"""Configs of the recipes: YAML defaults + a preset + ``key=value`` overrides.

Built on OmegaConf: the YAML is merged into the dataclass schema (so unknown keys
and wrong types are refused), then command-line ``dotted.key=value`` overrides are
applied. Shorthands: ``model=NAME``, ``sparsity=X``, ``noise=PRESET`` and
``task=follow|homing`` (training data, validation and test), ``epochs=N``.

The YAML files live in ``recipes/configs/`` of a clone, beside the recipes that read
them, and travel in the wheel as ``spf_rl/presets`` (:data:`CONFIG_DIR`).

Episodes are described by one :class:`~envs.episode_spec.EpisodeSpec` per config
(``data.episodes``, ``val.episodes``, ...); YAML files and overrides write its keys flat
(``data.split=val``, ``test.noise=none``), or nested (``data.episodes.split=val``).
The evaluation episodes of a recipe (``val``, ``test``) follow its training episodes
(``data`` for BC, ``env`` for DAgger and PPO) in
:data:`~envs.episode_spec.SIZE_FIELDS` unless a file or an override sets them.
"""
from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any, TypeVar

from omegaconf import OmegaConf

from envs.episode_spec import SIZE_FIELDS, nest_flat_keys

_PACKAGE = Path(__file__).resolve().parent
#: The YAML defaults and presets of the recipes: inside the package when it is installed from a
#: wheel (``spf_rl/presets``, setup.py), else ``recipes/configs/`` of the clone.
CONFIG_DIR = _PACKAGE / "presets" if (_PACKAGE / "presets").is_dir() else _PACKAGE.parent / "recipes" / "configs"
#: Command-line shorthands: one key that sets several config keys.
SHORTHANDS = {
    "model": ["model.name"],
    "sparsity": ["model.sparsity"],
    "pointer": ["model.pointer_update"],
    "noise": ["data.episodes.noise", "val.episodes.noise", "test.episodes.noise"],
    "epochs": ["optim.epochs"],
    "task": ["data.episodes.task", "val.episodes.task", "test.episodes.task"],
}
#: The configs whose episodes a recipe's evaluations (:data:`EVALUATIONS`) follow, first found first.
TRAINING_EPISODES = ("data", "env")
#: A recipe's evaluation configs.
EVALUATIONS = ("val", "test")

Config = TypeVar("Config")


def preset_layers(preset: str, _seen: tuple[str, ...] = ()) -> list:
    """``configs/<preset>.yaml``, after the presets its ``base:`` key names (base first).

    A preset may start from another one (``base: bc_row``) and change a few keys, so a
    schedule is written once.

    Raises:
        ValueError: for a missing preset file or a cycle of ``base:`` keys.
    """
    path = CONFIG_DIR / f"{preset}.yaml"
    if not path.is_file():
        raise ValueError(f"preset {preset!r}: no file {path}")
    if preset in _seen:
        raise ValueError(f"preset {preset!r}: its base: keys form a cycle ({' -> '.join((*_seen, preset))})")
    layer = OmegaConf.load(path)
    base = layer.pop("base", None)
    return (preset_layers(str(base), (*_seen, preset)) if base else []) + [layer]


def load_config(schema_cls: type[Config], name: str, overrides: list[str], preset: str | None = None) -> Config:
    """Merge ``configs/<name>.yaml`` (+ ``configs/<preset>.yaml``) and overrides into ``schema_cls``.

    Examples:
        >>> from spf_rl.train.bc import BCConfig
        >>> load_config(BCConfig, "bc", ["sparsity=0.4"]).model.sparsity
        0.4
        >>> load_config(BCConfig, "bc", ["modle=spf"])
        Traceback (most recent call last):
        ...
        ValueError: invalid configuration: Key 'modle' not in 'BCConfig'. Did you mean: 'model'?

    Raises:
        ValueError: for an override that is not ``key=value`` or names an unknown key.
    """
    schema = OmegaConf.structured(schema_cls)
    files = [OmegaConf.load(CONFIG_DIR / f"{name}.yaml")]
    if preset:
        files.extend(preset_layers(preset))
    layers = [schema, _sizing_layer(schema_cls)] + [
        OmegaConf.create(nest_flat_keys(OmegaConf.to_container(layer), schema_cls)) for layer in files
    ]
    expanded = []
    for item in overrides:
        if "=" not in item:
            raise ValueError(f"override {item!r} must look like key=value (e.g. model=rpf, optim.epochs=4).")
        key, value = item.split("=", 1)
        for target in SHORTHANDS.get(key, [key]):
            expanded.append(f"{target}={value}")
    expanded = nest_flat_keys(expanded, schema_cls)
    try:
        merged = OmegaConf.merge(*layers, OmegaConf.from_dotlist(expanded))
        # to_object resolves the interpolations (frozen dataclasses, EpisodeSpec, are read-only nodes)
        return OmegaConf.to_object(merged)
    except Exception as err:  # omegaconf raises several error types; report them uniformly
        # omegaconf appends full_key / object_type lines: keep the first, led by the key it names
        message, key = str(err).splitlines()[0], getattr(err, "full_key", None)
        if key and f"'{key}'" not in message:
            message = f"{key}: {message}"
        raise ValueError(f"invalid configuration: {message}") from err


def _sizing_layer(schema_cls: type) -> Any:
    """The layer under every YAML file: ``val`` and ``test`` episodes follow the training episodes
    (:data:`TRAINING_EPISODES`) in :data:`~envs.episode_spec.SIZE_FIELDS` (OmegaConf interpolations,
    so a file or an override that sets one of them wins)."""
    import typing

    hints = typing.get_type_hints(schema_cls) if dataclasses.is_dataclass(schema_cls) else {}
    source = next((name for name in TRAINING_EPISODES if name in hints), None)
    if source is None:
        return OmegaConf.create({})
    sized = {key: f"${{{source}.episodes.{key}}}" for key in SIZE_FIELDS}
    return OmegaConf.create({name: {"episodes": dict(sized)} for name in EVALUATIONS if name in hints})


def config_or_exit(parser: argparse.ArgumentParser, load: Any, *args: Any, **kwargs: Any) -> Any:
    """``load(*args, **kwargs)``, or the command line's error: ``prog: error: <message>`` alone
    on standard error and exit status 2, as argparse does for its own arguments.

    A recipe builds its config with it before any work, so a typo writes nothing.

    Examples:
        >>> import argparse
        >>> from spf_rl.train.bc import BCConfig
        >>> parser = argparse.ArgumentParser(prog="bc.py")
        >>> config_or_exit(parser, load_config, BCConfig, "bc", ["epochs=2"]).optim.epochs
        2
    """
    try:
        return load(*args, **kwargs)
    except ValueError as err:
        parser.error(str(err))
