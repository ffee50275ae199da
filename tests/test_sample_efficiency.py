"""Tests for spf_rl.eval.sample_efficiency and recipes/sample_efficiency.py: the levers' configs, the report
from finished runs (pooled, worst seed, paired against the baseline on the same episodes) and bad options."""
from __future__ import annotations

import json

import numpy as np
import pytest
import sample_efficiency as recipe

from spf_rl.eval import sample_efficiency
from spf_rl.records_cache import TEST_EPISODES_FILE, write_records

HOUSES = np.repeat(np.arange(10), 20)  # 200 episodes in 10 houses


def fake_run(directory, rate: float, seed: int) -> None:
    """A finished run as recipes/bc.py leaves it: results.json and its test records."""
    rng = np.random.default_rng(seed)
    success = rng.random(HOUSES.size) < rate
    records = [{"episode_seed": i, "house_seed": int(h), "success": bool(s), "spl": 0.9 * float(s), "success_lab": bool(s)}
               for i, (h, s) in enumerate(zip(HOUSES, success))]
    directory.mkdir(parents=True)
    write_records(directory / TEST_EPISODES_FILE, {"policy_sha256": f"{directory.name}"}, records)
    history = [{"epoch": e, "step": 125 * e, "train_seconds": 10.0, "val_success": None if e % 3 else rate - 0.1 / e}
               for e in range(1, 13)]
    results = {"test": {"success": float(success.mean())}, "history": history, "wall_seconds_this_run": 250.0,
               "machine_this_run": {"cpu_model": "Some CPU"}, "pointer_restarts": []}
    (directory / "results.json").write_text(json.dumps(results))


def test_each_lever_is_the_main_job_with_its_overrides():
    base = sample_efficiency.lever_config(sample_efficiency.LEVER_BY_NAME["baseline"], 1)
    assert base.seed == 1 and base.output_dir == "runs/sample_efficiency/baseline-seed1"
    assert (base.optim.epochs, base.data.num_episodes, base.optim.batch_size) == (12, 2000, 16)  # the main job's budget
    pointer = sample_efficiency.lever_config(sample_efficiency.LEVER_BY_NAME["rpf_rule+pointer_loss"], 0)
    assert pointer.model.pointer_update == "rpf" and pointer.optim.pointer_coef == 0.1
    assert pointer.data.episodes.route_style == "planner=1.0"
    assert pointer.test.episodes == base.test.episodes and pointer.val.episodes == base.val.episodes  # paired episodes
    assert all(lever.source for lever in sample_efficiency.LEVERS)


def test_the_report_pools_seeds_and_pairs_against_the_baseline(tmp_path, monkeypatch):
    monkeypatch.setattr(sample_efficiency, "RUNS_DIR", tmp_path / "runs")
    for seed in (0, 1):
        fake_run(tmp_path / "runs" / f"baseline-seed{seed}", 0.5, seed)
        fake_run(tmp_path / "runs" / f"rpf_rule-seed{seed}", 0.8, seed)
    levers = [sample_efficiency.LEVER_BY_NAME[name] for name in ("baseline", "rpf_rule", "lr3e-3")]
    content = recipe.main(["--no-train", "--levers", "rpf_rule,lr3e-3", "--seeds", "0,1", "--num-resamples", "300",
                           "--out", str(tmp_path / "study.json")])
    assert content["missing"] == ["lr3e-3"] and list(content["levers"]) == ["baseline", "rpf_rule"]
    rpf = content["levers"]["rpf_rule"]
    assert rpf["test_success"] == pytest.approx(np.mean(list(rpf["test_success_per_seed"].values())))
    assert rpf["worst_seed"] == min(rpf["test_success_per_seed"].values())
    base = content["levers"]["baseline"]
    assert rpf["vs_baseline"]["difference"] == pytest.approx(rpf["test_success"] - base["test_success"])
    assert rpf["vs_baseline"]["ci95"][0] > 0 and "vs_baseline" not in base
    assert rpf["curves"]["0"]["steps"] == [375, 750, 1125, 1500] and rpf["curves"]["0"]["train_seconds"][-1] == 120.0
    assert json.loads((tmp_path / "study.json").read_text())["levers"]["rpf_rule"] == json.loads(json.dumps(rpf))
    assert (tmp_path / "study.png").stat().st_size > 10_000
    assert sample_efficiency.study(levers, [0, 1], 100)["levers"].keys() == content["levers"].keys()


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--levers", "rpf_rule,faster"], "argument --levers: unknown lever ['faster']; allowed: baseline, rpf_rule"),
        (["--seeds", "0,x"], "argument --seeds: seeds must be comma-separated integers >= 0"),
        (["--num-resamples", "0"], "argument --num-resamples: must be >= 1"),
    ],
)
def test_bad_options_are_refused_before_any_work(tmp_path, capsys, argv, message):
    with pytest.raises(SystemExit) as exit_info:
        recipe.main([*argv, "--out", str(tmp_path / "study.json")])
    assert exit_info.value.code == 2 and message in capsys.readouterr().err
    assert not any(tmp_path.iterdir())
