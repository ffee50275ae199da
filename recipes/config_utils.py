"""Config loading for the recipes: YAML defaults + a preset + ``key=value`` overrides.

Built on OmegaConf: the YAML is merged into the dataclass schema (so unknown keys
and wrong types are refused), then command-line ``dotted.key=value`` overrides are
applied. Shorthands: ``model=NAME``, ``sparsity=X``, ``noise=PRESET`` and
``task=follow|homing`` (training data, validation and test), ``epochs=N``.
"""
from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

CONFIG_DIR = Path(__file__).resolve().parent / "configs"
SHORTHANDS = {
    "model": ["model.name"],
    "sparsity": ["model.sparsity"],
    "pointer": ["model.pointer_update"],
    "noise": ["data.noise", "val.noise", "test.noise"],
    "epochs": ["optim.epochs"],
    "task": ["data.task", "val.task", "test.task"],
}


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


def load_config(schema_cls, name: str, overrides: list[str], preset: str | None = None):
    """Merge ``configs/<name>.yaml`` (+ ``configs/<preset>.yaml``) and overrides into ``schema_cls``.

    Raises:
        ValueError: for an override that is not ``key=value`` or names an unknown key.
    """
    schema = OmegaConf.structured(schema_cls)
    layers = [schema, OmegaConf.load(CONFIG_DIR / f"{name}.yaml")]
    if preset:
        layers.extend(preset_layers(preset))
    expanded = []
    for item in overrides:
        if "=" not in item:
            raise ValueError(f"override {item!r} must look like key=value (e.g. model=rpf, optim.epochs=4).")
        key, value = item.split("=", 1)
        for target in SHORTHANDS.get(key, [key]):
            expanded.append(f"{target}={value}")
    try:
        merged = OmegaConf.merge(*layers, OmegaConf.from_dotlist(expanded))
        OmegaConf.resolve(merged)
        return OmegaConf.to_object(merged)
    except Exception as err:  # omegaconf raises several error types; report them uniformly
        raise ValueError(f"invalid configuration: {err}") from err
