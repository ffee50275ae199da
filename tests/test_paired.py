"""recipes/paired.py: paired comparisons of two evaluations of the same episodes."""
from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

RECIPE = Path(__file__).resolve().parents[1] / "recipes" / "paired.py"


def _module():
    spec = importlib.util.spec_from_file_location("paired_recipe", RECIPE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _evaluation(path: Path, successes: list[bool], seeds: list[int] | None = None) -> Path:
    seeds = seeds or list(range(len(successes)))
    records = [
        {"episode_seed": seed, "house_seed": seed % 3, "success": ok, "spl": 0.9 * ok, "success_lab": ok}
        for seed, ok in zip(seeds, successes)
    ]
    path.write_text(json.dumps({"checkpoint": path.stem, "episodes_records": records}))
    return path


def test_a_clearly_better_model_is_significantly_ahead(tmp_path):
    better = _evaluation(tmp_path / "a.json", [True] * 90 + [False] * 10)
    worse = _evaluation(tmp_path / "b.json", [True] * 30 + [False] * 70)
    result = _module().main([str(better), str(worse), "--out", str(tmp_path / "out" / "paired.json"), "--resamples", "500"])
    written = json.loads((tmp_path / "out" / "paired.json").read_text())
    assert written == json.loads(json.dumps(result))
    success = written["metrics"]["success"]
    assert (success["a"], success["b"]) == (0.9, 0.3)
    assert success["difference"] == pytest.approx(0.6)
    assert success["ci95"][0] > 0 and success["p_two_sided"] < 0.05
    assert written["episodes"] == 100 and written["houses"] == 3
    assert set(written["metrics"]) == {"success", "spl", "success_lab"}


def test_the_same_model_shows_no_difference(tmp_path):
    a = _evaluation(tmp_path / "a.json", [True, False] * 50)
    result = _module().compare(a, a, num_resamples=200, seed=0)
    assert result["metrics"]["success"]["difference"] == 0.0
    assert result["metrics"]["success"]["p_two_sided"] == 1.0


def test_different_episodes_are_refused(tmp_path):
    a = _evaluation(tmp_path / "a.json", [True] * 10)
    b = _evaluation(tmp_path / "b.json", [True] * 10, seeds=list(range(1, 11)))
    with pytest.raises(ValueError, match="hold different episodes"):
        _module().compare(a, b, num_resamples=10, seed=0)


def test_a_file_without_records_is_refused(tmp_path):
    empty = tmp_path / "empty.json"
    empty.write_text(json.dumps({"success": 0.5}))
    with pytest.raises(ValueError, match="no per-episode records"):
        _module().compare(empty, empty, num_resamples=10, seed=0)


def test_seeds_are_pooled_when_a_side_names_several_files(tmp_path):
    a0 = _evaluation(tmp_path / "a0.json", [True] * 80 + [False] * 20)
    a1 = _evaluation(tmp_path / "a1.json", [True] * 60 + [False] * 40)
    b = _evaluation(tmp_path / "b.json", [True] * 50 + [False] * 50)
    result = _module().compare(f"{a0},{a1}", b, num_resamples=200, seed=0)
    assert result["metrics"]["success"]["a"] == pytest.approx(0.7)
    assert result["metrics"]["success"]["difference"] == pytest.approx(0.2)
    assert result["a"] == [str(a0), str(a1)]


def test_a_training_runs_test_records_compare_with_path_fidelity(tmp_path):
    """recipes/bc.py's test_episodes.json (a result-cache file: key and columns, with nDTW and SDTW) pairs as
    evaluate.py's JSONs do."""
    from spf_rl.records_cache import write_records

    def run_records(path: Path, successes: list[bool]) -> Path:
        records = [
            {"episode_seed": seed, "house_seed": seed % 4, "success": ok, "spl": 0.8 * ok, "success_lab": ok,
             "ndtw": 0.3 + 0.5 * ok, "sdtw": 0.8 * ok}
            for seed, ok in enumerate(successes)
        ]
        write_records(path, {"policy_sha256": path.stem}, records, checkpoint=str(path.with_suffix(".pt")))
        return path

    a = run_records(tmp_path / "a.json", [True] * 70 + [False] * 30)
    b = run_records(tmp_path / "b.json", [True] * 40 + [False] * 60)
    result = _module().compare(a, b, num_resamples=300, seed=0)
    assert set(result["metrics"]) == {"success", "spl", "success_lab", "ndtw", "sdtw"}
    assert result["metrics"]["ndtw"]["difference"] == pytest.approx(0.5 * 0.3)
    assert result["metrics"]["sdtw"]["ci95"][0] > 0


def test_table1s_per_episode_cache_pairs_with_an_evaluation(tmp_path):
    """recipes/table1.py's cache files (only some fields of each record) pair with an evaluation."""
    from spf_rl.eval.table1 import CACHED_FIELDS
    from spf_rl.records_cache import write_records

    successes = [True] * 30 + [False] * 70
    records = [{"episode_index": i, "episode_seed": i, "house_seed": i % 3, "success": ok, "success_lab": ok,
                "spl": 0.9 * ok, "steps": 20} for i, ok in enumerate(successes)]
    write_records(tmp_path / "cache.json", {"policy_sha256": "x"}, records, CACHED_FIELDS, line="x", seed=0,
                  checkpoint="ckpt/x-seed0.pt")
    a = _evaluation(tmp_path / "a.json", [True] * 80 + [False] * 20)
    result = _module().compare(a, tmp_path / "cache.json", num_resamples=200, seed=0)
    assert result["metrics"]["success"]["b"] == pytest.approx(0.3)
    assert result["metrics"]["success"]["difference"] == pytest.approx(0.5)
    assert result["b_checkpoints"] == ["ckpt/x-seed0.pt"] and result["a_checkpoints"] == ["a"]


def test_the_cli_refuses_files_without_records_with_status_2(tmp_path, capsys):
    empty = tmp_path / "empty.json"
    empty.write_text(json.dumps({"episodes": []}))
    with pytest.raises(SystemExit) as exit_info:
        _module().main([str(empty), str(empty), "--out", str(tmp_path / "out.json")])
    assert exit_info.value.code == 2
    assert "no per-episode records" in capsys.readouterr().err
    assert not (tmp_path / "out.json").exists()
