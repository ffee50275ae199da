"""Tests for recipes/table1.py and spf_rl/eval/table1.py: the table over seeds from cached
per-episode records (no env, no policy), bad options, the cache, and a real open-loop smoke run."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import table1

from spf_rl.config import load_config
from spf_rl.eval import table1 as table1_report
from spf_rl.eval import table1_rows
from spf_rl.eval.table1 import CACHED_FIELDS, build_table
from spf_rl.hub import read_manifest, write_manifest
from spf_rl.records_cache import TEST_EPISODES_FILE, read_records, records_key, write_records

ROWS = "spf-s0.8,action_only-s0,open_loop"
HOUSES = np.repeat(np.arange(12), 10) + 400  # 120 episodes in 12 houses



def shipped_file(checkpoints: Path, name: str) -> Path:
    """The file a shipped name stands for in a checkpoint directory's manifest."""
    return checkpoints / read_manifest(checkpoints)["names"][name]

def fake_records(rate: float, seed: int) -> list[dict]:
    """Episodes with a shared difficulty (the same uniforms for every line), a rate per line, a little seed noise."""
    difficulty = np.random.default_rng(0).random(HOUSES.size)
    noise = np.random.default_rng(seed + 1).normal(0, 0.02, HOUSES.size)
    success = difficulty + noise < rate
    return [
        {"episode_index": i, "episode_seed": 10_000 + i, "house_seed": int(h), "success": bool(s),
         "success_lab": bool(s or d < rate + 0.05), "spl": 0.9 * float(s), "steps": 20}
        for i, (h, s, d) in enumerate(zip(HOUSES, success, difficulty))
    ]


def tiny_checkpoint(path: Path, model_type: str, seed: int = 0) -> Path:
    """A real checkpoint of a small policy of ``model_type`` (its weights drawn from ``seed``) at ``path``."""
    import torch

    from spf_rl.checkpoint import save_checkpoint
    from spf_rl.modules import SPFConfig
    from spf_rl.modules.registry import build_policy

    torch.manual_seed(seed)
    config = SPFConfig(demo_length=30, feature_dim=8, hidden_size=8, image_size=(64, 64),
                       sparsity_range=(0.2, 1.0) if model_type == "spf_random" else None)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_checkpoint(path, model_type, config, {"model": build_policy(model_type, config).state_dict()})
    return path


def options(tmp_path: Path, *more: str) -> list[str]:
    return ["--quick", "--checkpoints", str(tmp_path / "ckpt"), "--eval-dir", str(tmp_path / "eval"),
            "--out", str(tmp_path / "out"), "--num-resamples", "300", *more]


def cache_fake_evaluations(tmp_path: Path, plan: dict[str, tuple[float, list]]) -> None:
    """Small checkpoints and cached records, exactly where and as table1.py looks for them."""
    sets = table1_rows.eval_sets([], quick=True)
    lines = {line.name: line for line in table1_rows.table_lines(list(table1_rows.ROWS), 30, 64)}
    for name, (rate, seeds) in plan.items():
        line = lines[name]
        for seed in seeds:
            checkpoint = None
            if seed is not None:
                checkpoint = table1_rows.seed_checkpoint(tmp_path / "ckpt", line.checkpoint_stem, seed)
                tiny_checkpoint(checkpoint, line.model, seed)
            config = table1_rows.eval_config(sets["test"], line)
            key = records_key(config, table1_rows.line_policy(line, checkpoint, "cpu"))
            path = table1_rows.cache_path(tmp_path / "eval", "test", line.name, seed)
            write_records(path, key, fake_records(rate, seed or 0), CACHED_FIELDS)


def test_table_from_cached_records_counts_seeds_and_tests_the_claims(tmp_path, monkeypatch):
    cache_fake_evaluations(tmp_path, {
        "spf-s0.8": (0.8, [0, 1, 2]),
        "action_only-s0": (0.5, [0, 1]),  # seed 2 has no checkpoint: listed as missing
        "open_loop": (0.5, [None]),
        "dagger-spf-s0.8": (0.9, [0]),
    })
    monkeypatch.setattr(table1_rows, "evaluate_line", lambda *a: pytest.fail("everything is cached: nothing to evaluate"))
    paces = {"spf-s0.8": {"0": 0.9, "1": 0.85, "2": -0.8}, "action_only-s0": {"0": 0.99, "1": 0.98}}
    monkeypatch.setattr(table1_rows, "pointer_paces", lambda lines, seeds, *a: (paces, {"episodes": 8}))
    table = table1.main(options(tmp_path, "--from-checkpoints", "--rows", ROWS, "--sets", "test"))
    # the checkpoints are no finished runs of this recipe: scored as they are, nothing re-shipped
    assert table["shipped"] == {}

    saved = json.loads((tmp_path / "out" / "table1.json").read_text())
    assert saved["seeds"] == [0, 1, 2] and saved["claims"] == json.loads(json.dumps(table["claims"]))
    rows = {row["name"]: row for row in saved["rows"]}
    assert rows["spf-s0.8"]["seeds"] == [0, 1, 2] and rows["spf-s0.8"]["missing_seeds"] == []
    assert rows["action_only-s0"]["seeds"] == [0, 1] and rows["action_only-s0"]["missing_seeds"] == [2]
    assert rows["dagger-spf-s0.8"]["dagger_of"] == "spf-s0.8" and rows["dagger-spf-s0.8"]["missing_seeds"] == [1, 2]
    assert rows["spf-s0.8"]["trained_on"] == {} and rows["dagger-spf-s0.8"]["trained_on"] == {}  # no run of this recipe
    assert "earlier_seeds" not in rows["spf-s0.8"] and saved["budget"] == {"preset": "bc_quick"}
    test = rows["spf-s0.8"]["sets"]["test"]
    per_seed = [test["per_seed"][str(s)]["success"] for s in (0, 1, 2)]
    assert test["success"]["mean"] == pytest.approx(np.mean(per_seed))
    assert test["success"]["sd"] == pytest.approx(np.std(per_seed, ddof=1))
    assert test["success"]["ci"][0] < test["success"]["mean"] < test["success"]["ci"][1]
    assert test["houses"] == 12 and test["episodes"] == 120
    assert list(rows["spf-s0.8"]["sets"]) == ["test"]  # --sets test
    assert rows["open_loop"]["sets"]["test"]["success"]["sd"] is None  # one evaluation, no seeds

    claims = {(c["a"], c["b"], c.get("metric")): c for c in saved["claims"]}
    beats = claims[("spf-s0.8", "action_only-s0", "success")]
    assert beats["holds"] and beats["p_greater"] < 0.05 and beats["seeds_a"] == 3 and beats["seeds_b"] == 2
    assert beats["difference"] == pytest.approx(test["success"]["mean"] - rows["action_only-s0"]["sets"]["test"]["success"]["mean"])
    assert not claims[("action_only-s0", "open_loop", "success")]["holds"]  # the same success rate
    assert claims[("dagger-spf-s0.8", "spf-s0.8", "success")]["seeds_a"] == 1
    assert claims[("spf-s0.6", "spf-s0.4", None)]["skipped"].startswith("no records of spf-s0.6")
    assert {c["metric"] for c in saved["claims"] if "metric" in c} == {"success", "spl", "success_lab"}

    text = (tmp_path / "out" / "table1.md").read_text()
    assert "| SPF sparsity 0.8 ‡ | 3 of 3 |" in text and "†" not in text
    assert "‡ pointer runs backwards (SPF sparsity 0.8: seed 2; `pointer_pace`)" in text  # its pace below 0
    assert rows["spf-s0.8"]["pointer_pace"]["2"] == -0.8 and saved["pointer_pace"] == {"episodes": 8}
    assert "| RPF action only | 2 of 3 (missing: 2) |" in text
    assert "| open-loop replay | - (not trained) |" in text
    assert "(1 of 3 (missing: 1, 2) seeds)" in text  # the DAgger column
    assert "| SPF 0.8 beats action-only | test | success |" in text and "| yes |" in text
    assert "action_only-s0 seed 2: no `" in text
    assert (tmp_path / "out" / "table1.png").stat().st_size > 10_000


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--rows", "spf-s0.8,spf-s0.9"], "argument --rows: unknown row ['spf-s0.9']; allowed: spf-s0.4, spf-s0.6"),
        (["--seeds", "0,x"], "argument --seeds: seeds must be comma-separated integers >= 0"),
        (["--seeds", "-1"], "argument --seeds: seeds must be comma-separated integers >= 0"),
        (["--sets", "test,val"], "argument --sets: unknown set ['val']; allowed: test, extended"),
        (["seed=3"], "seed=... is not allowed: choose the training seeds with --seeds"),
        (["optim.no_such_key=1"], "overrides: invalid configuration"),
        (["--num-resamples", "0"], "argument --num-resamples: must be >= 1"),
    ],
)
def test_bad_options_are_refused_before_any_work(tmp_path, capsys, argv, message):
    with pytest.raises(SystemExit) as exit_info:
        table1.main(options(tmp_path, *argv))
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # nothing written


def test_a_runs_own_test_records_of_the_same_weights_and_episodes_are_reused(tmp_path, monkeypatch):
    """A finished run tested its best weights on the table's test episodes: the table takes those records
    (and caches them) instead of playing the episodes again, also from the per-seed copy of the file, but not
    for other weights or a random-sparsity line played at another sparsity than the run tested."""
    from spf_rl.hub import policy_from_checkpoint

    monkeypatch.chdir(tmp_path)
    sets = table1_rows.eval_sets([], quick=True)
    checkpoints = tmp_path / "ckpt"
    lines = {line.name: line for line in table1_rows.table_lines(list(table1_rows.ROWS), 30, 64)}
    for stem, model in (("spf-s0.8", "spf"), ("spf_random-s0.2-1", "spf_random")):
        run = table1_rows.run_dir(stem, 0)
        tiny_checkpoint(run / "best.pt", model)
        table1_rows.copy_atomic(run / "best.pt", table1_rows.seed_checkpoint(checkpoints, stem, 0))
        records = [{**record, "goal_distance": 0.4} for record in fake_records(0.7, 0)]  # a run's records hold more keys
        key = records_key(sets["test"], policy_from_checkpoint(run / "best.pt")[0])  # as trained: sparsity 0.8
        write_records(run / TEST_EPISODES_FILE, key, records, checkpoint=str(run / "best.pt"))
    played = []
    monkeypatch.setattr(table1_rows, "evaluate_line", lambda line, *a: played.append(line.name) or fake_records(0.5, 1))
    chosen = [lines["spf-s0.8"], lines["spf_random-s0.2-1@0.4"], lines["spf_random-s0.2-1@0.8"]]
    evaluations, missing = table1_rows.evaluate_all(chosen, [0], {"test": sets["test"]}, checkpoints, tmp_path / "eval", "cpu")
    assert missing == [] and played == ["spf_random-s0.2-1@0.4"]
    reused = evaluations["spf-s0.8"]["test"][0]
    assert [{key: r[key] for key in CACHED_FIELDS} for r in reused] == fake_records(0.7, 0)
    assert [{key: r[key] for key in CACHED_FIELDS} for r in evaluations["spf_random-s0.2-1@0.8"]["test"][0]] == fake_records(0.7, 0)
    cached = table1_rows.cache_path(tmp_path / "eval", "test", "spf-s0.8", 0)
    policy = table1_rows.line_policy(lines["spf-s0.8"], table1_rows.seed_checkpoint(checkpoints, "spf-s0.8", 0), "cpu")
    assert read_records(cached, records_key(sets["test"], policy)) == fake_records(0.7, 0)  # now cached too
    assert json.loads(cached.read_text())["checkpoint"] == str(table1_rows.seed_checkpoint(checkpoints, "spf-s0.8", 0))
    cached.unlink()
    tiny_checkpoint(table1_rows.seed_checkpoint(checkpoints, "spf-s0.8", 0), "spf", seed=1)  # not what the run tested
    evaluations, _ = table1_rows.evaluate_all(chosen[:1], [0], {"test": sets["test"]}, checkpoints, tmp_path / "eval", "cpu")
    assert played[-1] == "spf-s0.8" and evaluations["spf-s0.8"]["test"][0] == fake_records(0.5, 1)


def test_evaluations_of_other_episodes_cannot_be_compared(tmp_path):
    line = table1_rows.table_lines([table1_rows.ROW_BY_NAME["spf-s0.8"]], 30, 64)[0]
    shifted = [{**r, "episode_seed": r["episode_seed"] + 1} for r in fake_records(0.5, 1)]
    with pytest.raises(ValueError, match="did not play the same test episodes"):
        build_table([line], {line.name: {"test": {0: fake_records(0.5, 0), 1: shifted}}}, {"test": None}, [0, 1], [], [], 100)


def test_quick_open_loop_run_plays_real_episodes_once(tmp_path, monkeypatch):
    """The smoke run: open-loop replay needs no checkpoint; 8 episodes per set, no rendering; a rerun reads the cache."""
    from envs.scenes import split_seeds

    table = table1.main(options(tmp_path, "--from-checkpoints", "--rows", "open_loop"))
    row = table["rows"][0]
    assert row["sets"]["test"]["episodes"] == table1_rows.QUICK_EPISODES
    line = table1_rows.table_lines([table1_rows.ROW_BY_NAME["open_loop"]], 30, 64)[0]
    config = table1_rows.eval_config(table1_rows.eval_sets([], quick=True)["extended"], line)
    from spf_rl.modules import OpenLoopPolicy

    records = read_records(table1_rows.cache_path(tmp_path / "eval", "extended", line.name, None),
                           records_key(config, OpenLoopPolicy()))
    assert len(records) == table1_rows.QUICK_EPISODES and not config.render
    assert {r["house_seed"] for r in records} <= set(split_seeds("test", table1_rows.EXTENDED_HOUSES))
    monkeypatch.setattr(table1_rows, "evaluate_line", lambda *a: pytest.fail("a rerun must read the cache"))
    again = table1.main(options(tmp_path, "--from-checkpoints", "--rows", "open_loop"))
    assert again["rows"] == table["rows"]


def fake_runs(monkeypatch, val: dict[int, float], dagger_val: dict[int, float]) -> list[tuple]:
    """``train_bc`` and ``train_dagger`` replaced by fakes that leave what a finished run leaves (best.pt,
    results.json); returns the list of (kind, config) they were called with, in order."""
    calls: list[tuple] = []

    def finish(config, kind: str, results: dict) -> None:
        run = Path(config.output_dir)
        run.mkdir(parents=True)
        (run / "best.pt").write_text(f"{kind} {run.name}")
        (run / "results.json").write_text(json.dumps(results))
        calls.append((kind, config))

    monkeypatch.setattr("spf_rl.train.bc.train_bc", lambda config: finish(
        config, "bc", {"val_best": {"success": val[config.seed], "spl": val[config.seed] - 0.1, "epoch": 3}}))
    monkeypatch.setattr("spf_rl.train.dagger.train_dagger", lambda config: finish(
        config, "dagger", {"best": {"round": 2, "val_success": dagger_val[config.seed], "val_spl": 0.5}}))
    return calls


def test_training_runs_seed_0_of_every_row_first_each_dagger_after_its_row_and_ships_the_best(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    calls = fake_runs(monkeypatch, val={0: 0.70, 1: 0.76, 2: 0.73}, dagger_val={0: 0.9, 1: 0.8, 2: 0.85})
    rows = [table1_rows.ROW_BY_NAME["spf-s0.8"], table1_rows.ROW_BY_NAME["spf-s0.4"]]
    checkpoints = tmp_path / "checkpoints"
    shipped = table1_rows.train_missing(rows, [0, 1, 2], [], checkpoints, False)
    assert [(kind, config.output_dir) for kind, config in calls] == [
        (kind, f"runs/table1/{line}-seed{seed}") for seed in (0, 1, 2)
        for kind, line in (("bc", "spf-s0.8"), ("dagger", "dagger-spf-s0.8"), ("bc", "spf-s0.4"))
    ]
    bc_runs = [config for kind, config in calls if kind == "bc"]
    assert {(c.optim.epochs, c.data.num_episodes, c.optim.batch_size) for c in bc_runs} == {(40, 8000, 16)}  # one budget
    for kind, config in calls:
        if kind == "dagger":  # from its row's own BC run, on that run's data
            bc = table1_rows.row_config(rows[0], config.seed, [], quick=False)
            assert config.checkpoint == f"runs/table1/spf-s0.8-seed{config.seed}/best.pt" and config.bc_data == bc.data
    assert (checkpoints / "table1" / "spf-s0.4-seed2.pt").read_text() == "bc spf-s0.4-seed2"
    assert shipped["spf-s0.8"]["seed"] == 1 and shipped_file(checkpoints, "spf-s0.8").read_text() == "bc spf-s0.8-seed1"
    assert shipped["dagger-spf-s0.8"]["seed"] == 0
    assert shipped_file(checkpoints, "dagger-spf-s0.8").read_text() == "dagger dagger-spf-s0.8-seed0"
    calls.clear()
    assert table1_rows.train_missing(rows, [0, 1, 2], [], checkpoints, False) == shipped
    assert calls == []  # finished runs are not trained again


def test_training_one_seed_ships_the_best_of_every_seed_not_that_seed_alone(tmp_path, monkeypatch):
    """``--seeds 2`` trains seed 2 only; the name ships from seeds 0, 1 and 2 once all three are finished runs."""
    monkeypatch.chdir(tmp_path)
    calls = fake_runs(monkeypatch, val={0: 0.70, 1: 0.76, 2: 0.73}, dagger_val={})
    row = table1_rows.ROW_BY_NAME["action_only-s0"]
    checkpoints = tmp_path / "checkpoints"
    assert table1_rows.train_missing([row], [2], [], checkpoints, False) == {}  # seeds 0 and 1 have not run
    assert [config.seed for _, config in calls] == [2] and not table1_rows.shipped_names(checkpoints)
    assert table1_rows.train_missing([row], [0, 1], [], checkpoints, False)["action_only-s0"]["seed"] == 1
    shutil.rmtree("runs/table1/action_only-s0-seed2")  # seed 2 trained again, better: it ships from a --seeds 2 run
    fake_runs(monkeypatch, val={2: 0.9}, dagger_val={})
    assert table1_rows.train_missing([row], [2], [], checkpoints, False)["action_only-s0"]["seed"] == 2
    assert shipped_file(checkpoints, "action_only-s0").read_text() == "bc action_only-s0-seed2"


def test_a_finished_run_replaces_an_earlier_runs_file_and_ships_once_every_seed_is_this_recipes(tmp_path, monkeypatch):
    """Per-seed files of earlier runs (another budget) are scored until this recipe's runs replace them; the
    shipped name moves only once every seed of the line is this recipe's."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("spf_rl.train.bc.train_bc", lambda config: pytest.fail("--from-checkpoints must not train"))
    monkeypatch.setattr("spf_rl.train.dagger.train_dagger", lambda config: pytest.fail("--from-checkpoints must not train"))
    checkpoints = tmp_path / "checkpoints"
    (checkpoints / "table1").mkdir(parents=True)
    for seed in (0, 1, 2):
        (checkpoints / "table1" / f"spf-s0.4-seed{seed}.pt").write_text(f"earlier {seed}")
    write_manifest(checkpoints, {"spf-s0.4": "table1/spf-s0.4-seed2.pt"})
    run = Path("runs/table1/spf-s0.4-seed0")
    run.mkdir(parents=True)
    (run / "best.pt").write_text("this recipe's seed 0")
    machine = {"cpu_model": "Some CPU", "cpu_count": 2}
    (run / "results.json").write_text(json.dumps({"val_best": {"success": 0.9, "spl": 0.9, "epoch": 30}, "machine_this_run": machine}))
    row = table1_rows.ROW_BY_NAME["spf-s0.4"]
    assert table1_rows.keep_run(checkpoints, "spf-s0.4", 0, run, "val_best") == (0.9, 0.9)
    from spf_rl.checkpoint import file_sha256
    from spf_rl.hub import read_manifest

    manifest = read_manifest(checkpoints)  # lists the copy's hash at once, shipping nothing new
    assert manifest["files"]["table1/spf-s0.4-seed0.pt"] == file_sha256(run / "best.pt")
    assert manifest["names"] == {"spf-s0.4": "table1/spf-s0.4-seed2.pt"}
    assert table1_rows.train_missing([row], [0, 1, 2], [], checkpoints, False, train=False) == {}
    assert (checkpoints / "table1" / "spf-s0.4-seed0.pt").read_text() == "this recipe's seed 0"
    assert shipped_file(checkpoints, "spf-s0.4").read_text() == "earlier 2"  # not every seed is this recipe's yet
    lines = table1_rows.table_lines([row], 30, 64)
    assert table1_rows.trained_on(lines, [0, 1, 2], checkpoints, False) == {"spf-s0.4": {"0": "Some CPU"}}  # not 1, 2
    (run / "results.json").write_text(json.dumps({"val_best": {"success": 0.9, "spl": 0.9, "epoch": 30}}))  # an older run
    assert table1_rows.trained_on(lines, [0, 1, 2], checkpoints, False)["spf-s0.4"] == {"0": None}


def test_a_clean_clone_finds_a_finished_runs_weights_in_its_per_seed_checkpoint(tmp_path, monkeypatch):
    """A finished run is committed without its ``.pt`` files: its weights are the per-seed checkpoint, whose
    weights its test records are keyed by. A clone gets ``best.pt`` back from there (its DAgger column starts
    from it), counts the seed as this recipe's, and refuses, naming both files, where the per-seed file holds
    other weights."""
    from spf_rl.hub import policy_from_checkpoint

    monkeypatch.chdir(tmp_path)
    checkpoints = tmp_path / "checkpoints"
    target = tiny_checkpoint(checkpoints / "table1" / "spf-s0.8-seed0.pt", "spf", seed=0)
    weights = target.read_bytes()
    run = Path("runs/table1/spf-s0.8-seed0")
    run.mkdir(parents=True)
    (run / "results.json").write_text(json.dumps({"val_best": {"success": 0.8, "spl": 0.7, "epoch": 30}}))
    sets = table1_rows.eval_sets([], quick=True)
    write_records(run / TEST_EPISODES_FILE, records_key(sets["test"], policy_from_checkpoint(target)[0]), fake_records(0.7, 0))
    assert table1_rows.keep_run(checkpoints, "spf-s0.8", 0, run, "val_best") == (0.8, 0.7)
    assert (run / "best.pt").read_bytes() == weights and target.read_bytes() == weights
    lines = table1_rows.table_lines([table1_rows.ROW_BY_NAME["spf-s0.8"]], 30, 64)
    (run / "best.pt").unlink()
    assert list(table1_rows.trained_on(lines, [0], checkpoints, False)["spf-s0.8"]) == ["0"]
    tiny_checkpoint(target, "spf", seed=1)  # an earlier run's weights
    assert table1_rows.trained_on(lines, [0], checkpoints, False)["spf-s0.8"] == {}
    with pytest.raises(FileNotFoundError, match=r"spf-s0\.8-seed0 finished, but its weights are neither in .*best\.pt nor in .*spf-s0\.8-seed0\.pt"):
        table1_rows.keep_run(checkpoints, "spf-s0.8", 0, run, "val_best")
    assert target.read_bytes() != weights and not (run / "best.pt").exists()  # nothing overwritten


def test_every_row_trains_on_one_budget_and_every_dagger_column_by_one_rule():
    from spf_rl.train.dagger import DAGGER_VAL_SEED

    trained = [row for row in table1_rows.ROWS if row.trained]
    assert len(trained) == 8 and {row.name for row in table1_rows.ROWS if row.dagger} == {
        "spf-s0.8", "rpf-s1", "rpf_original-s1", "spf_rpf_pointer-s0.8"}
    reference = table1_rows.row_config(table1_rows.ROW_BY_NAME["spf-s0.8"], 1, [], quick=False)
    for row in trained:
        config = table1_rows.row_config(row, 1, [], quick=False)
        assert (config.optim, config.data, config.val, config.test) == (reference.optim, reference.data, reference.val, reference.test)
        assert config.output_dir == f"runs/table1/{row.name}-seed1"
        dagger = table1_rows.dagger_config(row, 1)
        if dagger is None:
            continue
        rule = (dagger.rounds, dagger.episodes_per_round, dagger.beta0, dagger.steps_per_round, dagger.window_rounds)
        assert rule == (10, 256, 0.0, 500, 4) and dagger.val.episodes.seed == DAGGER_VAL_SEED != config.val.episodes.seed
        assert dagger.bc_data == config.data and dagger.test == config.test
        assert dagger.output_dir == f"runs/table1/dagger-{row.name}-seed1" and dagger.checkpoint == f"runs/table1/{row.name}-seed1/best.pt"
    assert table1_rows.budgets() == {
        "bc": {"preset": "bc_table1", "gradient_steps": 20_000, "episodes": 8_000, "batch_episodes": 16},
        "dagger": {"preset": "dagger_table1", "rounds": 10, "episodes_per_round": 256, "gradient_steps": 5_000,
                   "val_seed": DAGGER_VAL_SEED},
    }


def test_the_table1_presets_are_what_the_table_trains():
    """``python recipes/bc.py --preset bc_table1`` and ``dagger.py --preset dagger_table1`` train SPF 0.8's runs."""
    from spf_rl.train.bc import BCConfig
    from spf_rl.train.dagger import DAggerConfig

    row = table1_rows.ROW_BY_NAME["spf-s0.8"]
    assert table1_rows.row_config(row, 2, [], quick=False) == load_config(BCConfig, "bc", ["seed=2", "model=spf", "sparsity=0.8"],
                                                                          preset="bc_table1")
    assert table1_rows.dagger_config(row, 2) == load_config(DAggerConfig, "dagger", ["seed=2"], preset="dagger_table1")


def test_only_device_and_amp_overrides_reach_the_dagger_runs():
    row = table1_rows.ROW_BY_NAME["rpf-s1"]
    bc = table1_rows.row_config(row, 0, ["optim.epochs=2", "device=cpu", "optim.amp=true"], quick=False)
    dagger = table1_rows.dagger_config(row, 0, ["optim.epochs=2", "device=cpu", "optim.amp=true"])
    assert (bc.optim.epochs, bc.device, bc.optim.amp) == (2, "cpu", True)
    assert (dagger.device, dagger.optim.amp) == ("cpu", True) and dagger.bc_data == bc.data


def test_summary_names_unscored_rows_once_and_leaves_claims_to_the_full_table():
    from spf_rl.eval.table1 import summary_markdown

    stats = {"success": {"mean": 0.8, "sd": 0.01}, "spl": {"mean": 0.7, "sd": 0.02}}
    base = {"model": "spf", "dagger_of": None, "seeds": [0, 1], "seeds_expected": [0, 1, 2], "missing_seeds": [2],
            "paper_success": None, "paper_spl": None}
    rows = [
        {**base, "name": "spf-s0.8", "row": "spf-s0.8", "checkpoint_stem": "spf-s0.8", "label": "SPF 0.8", "sets": {"test": stats}},
        {**base, "name": "dagger-spf-s0.8", "row": "dagger-spf-s0.8", "checkpoint_stem": "dagger-spf-s0.8",
         "label": "DAgger", "dagger_of": "spf-s0.8", "seeds": [0], "sets": {"test": stats}},
        *({**base, "name": f"r@{s}", "row": "r", "checkpoint_stem": "r", "label": f"Random, at {s}", "seeds": [], "sets": {}}
          for s in (0.4, 0.8)),
    ]
    claim = {"claim": "a beats b", "set": "test", "metric": "success", "difference": 0.1, "ci": [0.05, 0.15],
             "p_greater": 0.0, "holds": True}
    text = summary_markdown({"rows": rows, "claims": [claim, {**claim, "metric": "spl"}, {**claim, "set": "extended"}]})
    assert "| SPF 0.8 | `spf-s0.8` | 2 of 3 | 0.800 ± 0.010 | 0.700 ± 0.020 | 0.800 ± 0.010 (1 of 3) | - |" in text
    assert text.count("Random") == 1 and "Not scored yet (no checkpoint of this noise model): Random." in text
    assert "a beats b" not in text  # one results table: the claims are in table1.md


def test_summary_puts_a_model_scored_at_several_sparsities_on_one_line():
    from spf_rl.eval.table1 import summary_markdown

    base = {"model": "spf_random", "dagger_of": None, "seeds": [0, 1], "seeds_expected": [0, 1, 2], "missing_seeds": [2],
            "paper_success": None, "paper_spl": None, "row": "r", "checkpoint_stem": "r"}
    rows = [
        {**base, "name": f"r@{s:g}", "label": f"Random, at {s:g}", "sparsity": s,
         "sets": {"test": {"success": {"mean": m, "sd": 0.01}, "spl": {"mean": m - 0.01, "sd": 0.01}}}}
        for s, m in ((0.4, 0.6), (1.0, 0.7))
    ]
    text = summary_markdown({"rows": rows, "claims": []})
    assert text.count("Random") == 1
    assert "| Random, at 0.4 / 1 | `r` | 2 of 3 | 0.600 / 0.700 | 0.590 / 0.690 | - | - |" in text


def test_the_pointer_row_trains_spf_with_rpfs_pointer_rule():
    config = table1_rows.row_config(table1_rows.ROW_BY_NAME["spf_rpf_pointer-s0.8"], 1, [], quick=False)
    assert (config.model.name, config.model.sparsity, config.model.pointer_update) == ("spf", 0.8, "rpf")
    assert config.output_dir.endswith("spf_rpf_pointer-s0.8-seed1")


def test_seed_by_seed_gives_each_seeds_success_pace_and_the_shipped_seed():
    from spf_rl.eval.table1 import seed_by_seed

    def row(name: str, label: str, per_seed: dict, paces: dict, model: str = "spf") -> dict:
        sets = {"test": {"per_seed": {str(s): {"success": v} for s, v in per_seed.items()}}}
        return {"name": name, "checkpoint_stem": name.split("@")[0], "label": label, "model": model, "sets": sets,
                "pointer_pace": paces}

    table = {
        "seeds": [0, 1, 2], "sets": {"test": {}},
        "rows": [
            row("spf-s0.4", "SPF 0.4", {0: 0.78, 1: 0.76}, {"0": 0.9, "1": -0.7}),
            row("r@0.4", "Random, at 0.4", {0: 0.7, 1: 0.4, 2: 0.71}, {}),
            row("open_loop", "open-loop", {"None": 0.5}, {}, model="open_loop"),
        ],
        "shipped": {"spf-s0.4": {"seed": 0, "val_success": 0.8}, "r": {"seed": 2, "val_success": 0.75}},
    }
    lines = seed_by_seed(table)
    assert "| line | test: seed 0 | test: seed 1 | test: seed 2 | pointer pace | ships |" in lines
    assert "| SPF 0.4 | 0.780 | 0.760 | - | +0.90 / -0.70 / - | seed 0 (0.800) |" in lines  # seed 2 not scored
    assert "| Random, at 0.4 | 0.700 | 0.400 | 0.710 | - | seed 2 (0.750) |" in lines  # its model's shipped seed
    assert not any("open-loop" in line for line in lines)  # not trained: no seeds
    table.pop("shipped")
    assert seed_by_seed(table)[-2].endswith("| +0.90 / -0.70 / - | - |")


@pytest.mark.parametrize(
    "kwargs, part",
    [({}, False), ({"seeds": (0, 1, 2, 3)}, False), ({"seeds": (2,)}, True), ({"rows": ("spf-s0.8",)}, True),
     ({"sets": ("test",)}, True)],
)
def test_a_part_of_the_table_never_overwrites_the_whole_one(kwargs, part):
    options = table1_rows.Table1Options(from_checkpoints=True, **kwargs)
    assert options.part is part
    assert options.out == (table1_rows.PART_DIR if part else Path("results"))
    assert table1_rows.Table1Options(from_checkpoints=True, out=Path("elsewhere"), **kwargs).out == Path("elsewhere")


def test_a_seed_the_guard_restarted_is_marked_and_named():
    """Table 1 says which seeds the pointer-collapse guard restarted (from their runs' results.json)."""
    restarted = {"label": "SPF sparsity 0.4", "dagger_of": None, "pointer_pace": {"2": 0.9},
                 "pointer_restarts": {"2": [{"epoch": 1, "pointer_pace": -0.7, "seed": 123}], "0": []}}
    plain = {"label": "SPF sparsity 0.8", "dagger_of": None, "pointer_pace": {"0": 0.8}}
    assert table1_report.marks(restarted) == " §" and table1_report.marks(plain) == ""
    notes = "\n".join(table1_report.footnotes({"rows": [restarted, plain]}))
    assert "§ restarted by the pointer-collapse guard (SPF sparsity 0.4: seed 2 after epoch 1)" in notes
    assert table1_report.footnotes({"rows": [plain]}) == []


def test_run_restarts_reads_a_runs_results(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    run = table1_rows.run_dir("spf-s0.4", 2)
    run.mkdir(parents=True)
    (run / "results.json").write_text(json.dumps({"pointer_restarts": [{"epoch": 1, "pointer_pace": -0.7, "seed": 5}]}))
    assert table1_rows.run_restarts("spf-s0.4", 2, False) == [{"epoch": 1, "pointer_pace": -0.7, "seed": 5}]
    assert table1_rows.run_restarts("spf-s0.4", 1, False) == []
