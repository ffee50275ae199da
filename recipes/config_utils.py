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


def load_config(schema_cls, name: str, overrides: list[str], preset: str | None = None):
    """Merge ``configs/<name>.yaml`` (+ ``configs/<preset>.yaml``) and overrides into ``schema_cls``.

    Raises:
        ValueError: for an override that is not ``key=value`` or names an unknown key.
    """
    schema = OmegaConf.structured(schema_cls)
    layers = [schema, OmegaConf.load(CONFIG_DIR / f"{name}.yaml")]
    if preset:
        layers.append(OmegaConf.load(CONFIG_DIR / f"{preset}.yaml"))
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
