"""A resumed run keeps the settings it was started with (spf_rl/train/run_config.py)."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from spf_rl.train.bc import BCConfig, train_bc
from spf_rl.train.dagger import DAGGER_RESUME_FREE, DAggerConfig, default_dagger_val_config, train_dagger
from spf_rl.train.ppo import train_ppo
from spf_rl.train.ppo_config import PPO_RESUME_FREE, PPOConfig
from spf_rl.train.run import OptimConfig
from spf_rl.train.run_config import BC_RESUME_FREE, EXECUTION_KEYS, changed_settings, config_dict, write_run_config


def started_run(directory: Path, config) -> Path:
    """A run directory as a run leaves it after its first checkpoint: its config and a ``last.pt``."""
    write_run_config(directory, config)
    (directory / "last.pt").write_bytes(b"")
    return directory


def test_a_fresh_directory_takes_any_config(tmp_path):
    write_run_config(tmp_path / "run", DAggerConfig(seed=1))
    write_run_config(tmp_path / "run", DAggerConfig(seed=2))  # no last.pt: a run that never checkpointed starts over
    assert json.loads((tmp_path / "run" / "config.json").read_text())["seed"] == 2


def test_a_resume_with_another_validation_set_is_refused_and_keeps_the_config(tmp_path):
    val = default_dagger_val_config()
    old = DAggerConfig(val=dataclasses.replace(val, episodes=val.episodes.replace(seed=1)))
    run = started_run(tmp_path / "run", old)
    before = (run / "config.json").read_text()
    with pytest.raises(ValueError, match=r"val\.seed: 1 -> 3.*new output_dir"):
        write_run_config(run, DAggerConfig(), free=DAGGER_RESUME_FREE)
    assert (run / "config.json").read_text() == before


def test_a_resume_may_change_how_it_runs_but_not_what(tmp_path):
    run = started_run(tmp_path / "run", DAggerConfig())
    write_run_config(run, DAggerConfig(progress=False, num_workers=1, rounds=20, device="cpu"), free=DAGGER_RESUME_FREE)
    assert json.loads((run / "config.json").read_text())["rounds"] == 20
    with pytest.raises(ValueError, match=r"optim\.lr: 0\.0003 -> 0\.001.*seed: 0 -> 1"):
        write_run_config(run, DAggerConfig(seed=1, optim=OptimConfig(lr=1e-3, cosine_schedule=False)))


def test_changed_settings_compares_nested_keys_both_configs_have():
    old = config_dict(BCConfig())
    new = config_dict(dataclasses.replace(BCConfig(), seed=4))
    del old["keep_epochs"]  # a setting added after the old run was written is not compared
    new["keep_epochs"] = True
    assert changed_settings(old, new) == ["seed"]
    assert changed_settings(old, new, free=["seed"]) == []


def test_training_entry_points_refuse_before_any_work(tmp_path):
    """Each check runs before the start checkpoint or dataset is read (both are missing here)."""
    missing = str(tmp_path / "missing.pt")
    run = started_run(tmp_path / "dagger", DAggerConfig(checkpoint=missing, output_dir=str(tmp_path / "dagger"), device="cpu"))
    with pytest.raises(ValueError, match=r"beta0"):
        train_dagger(DAggerConfig(checkpoint=missing, output_dir=str(run), device="cpu", beta0=0.5))
    run = started_run(tmp_path / "bc", BCConfig(output_dir=str(tmp_path / "bc"), data_dir=str(tmp_path / "no_data")))
    with pytest.raises(ValueError, match=r"model\.sparsity"):
        bad = BCConfig(output_dir=str(run), data_dir=str(tmp_path / "no_data"))
        train_bc(dataclasses.replace(bad, model=dataclasses.replace(bad.model, sparsity=0.4)))
    assert not (tmp_path / "no_data").exists()
    run = started_run(tmp_path / "ppo", PPOConfig(checkpoint=missing, output_dir=str(tmp_path / "ppo"), device="cpu"))
    with pytest.raises(ValueError, match=r"lr: 0\.0001 -> 0\.001"):
        train_ppo(PPOConfig(checkpoint=missing, output_dir=str(run), device="cpu", lr=1e-3))


def has_setting(settings: dict, name: str) -> bool:
    for part in name.split("."):
        if not isinstance(settings, dict) or part not in settings:
            return False
        settings = settings[part]
    return True


def test_free_settings_name_real_config_fields():
    recipes = ((BCConfig(), BC_RESUME_FREE), (DAggerConfig(), DAGGER_RESUME_FREE), (PPOConfig(), PPO_RESUME_FREE))
    for config, free in recipes:
        settings = config_dict(config)
        for name in free:
            assert has_setting(settings, name), f"{type(config).__name__} has no setting {name}"
    for name in EXECUTION_KEYS:
        assert any(has_setting(config_dict(config), name) for config, _ in recipes), name
