"""Tests for recipes/evaluate.py: reproducible JSON, confidence intervals, model-type checks."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

from spf_rl.checkpoint import save_checkpoint
from spf_rl.modules.policy import SPFConfig
from spf_rl.modules.registry import build_policy

RECIPE = Path(__file__).resolve().parents[1] / "recipes" / "evaluate.py"
CONFIG = SPFConfig(demo_length=6, sparsity=0.5, feature_dim=8, hidden_size=8, image_size=(32, 32))


def _evaluate_module():
    spec = importlib.util.spec_from_file_location("evaluate_recipe", RECIPE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture()
def checkpoint(tmp_path):
    path = tmp_path / "spf.pt"
    save_checkpoint(path, "spf", CONFIG, {"model": build_policy("spf", CONFIG).state_dict()})
    return path


def _run(module, checkpoint, out, *extra):
    args = [str(checkpoint), "--split", "val", "--episodes", "4", "--num-agents", "2", "--max-steps", "8", "--seed", "5", "--out", str(out), "--no-progress", *extra]
    return module.main(args)


def test_same_seed_gives_identical_json(checkpoint, tmp_path):
    module = _evaluate_module()
    _run(module, checkpoint, tmp_path / "a")
    _run(module, checkpoint, tmp_path / "b")
    (first,) = list((tmp_path / "a").glob("*.json"))
    (second,) = list((tmp_path / "b").glob("*.json"))
    a, b = json.loads(first.read_text()), json.loads(second.read_text())
    assert a == b
    assert len(a["episodes_records"]) == 4
    for metric in ("success", "spl"):
        low, high = a[f"{metric}_ci"]
        assert low <= a[metric] <= high
    assert a["memory_bytes"] == 3 * 3 * 32 * 32 + 6


def test_other_model_type_is_refused_before_any_work(checkpoint, tmp_path, capsys):
    module = _evaluate_module()
    with pytest.raises(SystemExit) as exit_info:
        _run(module, checkpoint, tmp_path / "c", "--model-type", "rpf")
    assert exit_info.value.code == 2
    assert "argument paths: " in (err := capsys.readouterr().err) and "holds a 'spf' model, but a 'rpf' model" in err
    assert not (tmp_path / "c").exists()


def test_random_sparsity_model_is_evaluated_at_the_requested_sparsity(tmp_path):
    import dataclasses

    config = dataclasses.replace(CONFIG, sparsity_range=(0.2, 1.0))
    path = tmp_path / "spf_random.pt"
    save_checkpoint(path, "spf_random", config, {"model": build_policy("spf_random", config).state_dict()})
    module = _evaluate_module()
    (result,) = _run(module, path, tmp_path / "d", "--sparsity", "1.0")
    assert result["sparsity"] == 1.0
    assert result["memory_bytes"] == 6 * 3 * 32 * 32 + 6  # all six frames kept at sparsity 1
    assert list((tmp_path / "d").glob("*-at1-*.json"))


def test_sparsity_flag_is_refused_for_fixed_sparsity_models_before_any_work(checkpoint, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        _run(_evaluate_module(), checkpoint, tmp_path / "e", "--sparsity", "0.4")
    assert exit_info.value.code == 2
    assert "argument --sparsity: applies to random-sparsity models" in capsys.readouterr().err
    assert not (tmp_path / "e").exists()


def test_worker_processes_write_the_scores_of_one_process(checkpoint, tmp_path):
    module = _evaluate_module()
    (one,) = _run(module, checkpoint, tmp_path / "one")
    (two,) = _run(module, checkpoint, tmp_path / "two", "--num-collectors", "2")
    assert two["episodes_records"] == one["episodes_records"]
    assert two["eval"]["num_collectors"] == 2


def test_num_collectors_is_checked_before_any_work(checkpoint, tmp_path, capsys):
    with pytest.raises(SystemExit):
        _run(_evaluate_module(), checkpoint, tmp_path / "f", "--num-collectors", "0")
    assert "--num-collectors must be a positive int" in capsys.readouterr().err
    assert not (tmp_path / "f").exists()


def test_a_checkpoint_follows_routes_of_another_length_with_its_own_weights(checkpoint, tmp_path):
    """--demo-length plays routes of that length with the same weights; the step limit follows (ceil(5/3 n))."""
    module = _evaluate_module()
    args = [str(checkpoint), "--split", "val", "--episodes", "2", "--num-agents", "2", "--seed", "5", "--no-progress"]
    (own,) = module.main([*args, "--out", str(tmp_path / "own")])
    (longer,) = module.main([*args, "--out", str(tmp_path / "longer"), "--demo-length", "9"])
    assert (own["eval"]["demo_length"], own["eval"]["max_steps"]) == (6, 10)  # the checkpoint's own length
    assert (longer["eval"]["demo_length"], longer["eval"]["max_steps"]) == (9, 15)
    from spf_rl.modules.views import model_memory_bytes

    assert longer["memory_bytes"] == model_memory_bytes("spf", 9, 0.5, 32) > own["memory_bytes"]  # the memory of 9 steps
    assert max(r["steps"] for r in longer["episodes_records"]) <= 15


@pytest.mark.parametrize("flag", ["--demo-length", "--max-steps"])
def test_lengths_are_checked_before_any_work(checkpoint, tmp_path, capsys, flag):
    with pytest.raises(SystemExit) as exit_info:
        _run(_evaluate_module(), checkpoint, tmp_path / "g", flag, "0")
    assert exit_info.value.code == 2
    assert f"{flag} must be a positive number of steps, got 0" in capsys.readouterr().err
    assert not (tmp_path / "g").exists()
