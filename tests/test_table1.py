"""Tests for recipes/table1.py and spf_rl/eval/table1.py: the table over seeds from cached
per-episode records (no env, no policy), bad options, the cache, and a real open-loop smoke run."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import table1

from spf_rl.config import load_config
from spf_rl.eval import table1 as table1_report
from spf_rl.eval import table1_rows
from spf_rl.eval.table1 import build_table, load_cached, write_cached
from spf_rl.hub import read_manifest, write_manifest

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


def options(tmp_path: Path, *more: str) -> list[str]:
    return ["--quick", "--checkpoints", str(tmp_path / "ckpt"), "--eval-dir", str(tmp_path / "eval"),
            "--out", str(tmp_path / "out"), "--num-resamples", "300", *more]


def cache_fake_evaluations(tmp_path: Path, plan: dict[str, tuple[float, list]]) -> None:
    """Fake checkpoints and cached records, exactly where and as table1.py looks for them."""
    sets = table1_rows.eval_sets([], quick=True)
    lines = {line.name: line for line in table1_rows.table_lines(list(table1_rows.ROWS), 30, 64)}
    for name, (rate, seeds) in plan.items():
        line = lines[name]
        for seed in seeds:
            checkpoint = None
            if seed is not None:
                checkpoint = table1_rows.seed_checkpoint(tmp_path / "ckpt", line.checkpoint_stem, seed)
                checkpoint.parent.mkdir(parents=True, exist_ok=True)
                checkpoint.write_bytes(f"weights of {line.checkpoint_stem} {seed}".encode())
            config = table1_rows.eval_config(sets["test"], line)
            path, meta = table1_rows.cache_entry(line.name, seed, "test", config, checkpoint, tmp_path / "eval")
            write_cached(path, meta, fake_records(rate, seed or 0))


def test_table_from_cached_records_counts_seeds_and_tests_the_claims(tmp_path, monkeypatch):
    cache_fake_evaluations(tmp_path, {
        "spf-s0.8": (0.8, [0, 1, 2]),
        "action_only-s0": (0.5, [0, 1]),  # seed 2 has no checkpoint: listed as missing
        "open_loop": (0.5, [None]),
        "dagger-spf-s0.8": (0.9, [0]),
    })
    monkeypatch.setattr(table1_rows, "evaluate_line", lambda *a: pytest.fail("everything is cached: nothing to evaluate"))
    # the checkpoints have no run results: each is scored on validation (here a stub) and the best one shipped
    monkeypatch.setattr(table1_rows, "cached_validation", lambda eval_dir, device: lambda line, seed, path, config: (seed / 10, 0.0))
    table = table1.main(options(tmp_path, "--from-checkpoints", "--rows", ROWS, "--sets", "test"))
    assert table["shipped"]["spf-s0.8"]["seed"] == 2 and table["shipped"]["action_only-s0"]["seed"] == 1

    saved = json.loads((tmp_path / "out" / "table1.json").read_text())
    assert saved["seeds"] == [0, 1, 2] and saved["claims"] == json.loads(json.dumps(table["claims"]))
    rows = {row["name"]: row for row in saved["rows"]}
    assert rows["spf-s0.8"]["seeds"] == [0, 1, 2] and rows["spf-s0.8"]["missing_seeds"] == []
    assert rows["action_only-s0"]["seeds"] == [0, 1] and rows["action_only-s0"]["missing_seeds"] == [2]
    assert rows["dagger-spf-s0.8"]["dagger_of"] == "spf-s0.8" and rows["dagger-spf-s0.8"]["missing_seeds"] == [1, 2]
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
    assert "| SPF sparsity 0.8 | 3 of 3 |" in text
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


def test_the_cache_is_used_only_for_the_same_evaluation(tmp_path):
    meta = {"line": "spf-s0.8", "seed": 0, "eval": {"num_episodes": 120}, "checkpoint_sha256": "abc"}
    path = tmp_path / "test" / "spf-s0.8-seed0.json"
    write_cached(path, meta, fake_records(0.7, 0))
    assert load_cached(path, meta) == fake_records(0.7, 0)
    assert load_cached(path, {**meta, "checkpoint_sha256": "other"}) is None  # a new checkpoint
    assert load_cached(path, {**meta, "eval": {"num_episodes": 1000}}) is None
    assert load_cached(tmp_path / "absent.json", meta) is None
    assert not list(path.parent.glob(".*"))  # no temporary file left behind


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
    records = load_cached(*table1_rows.cache_entry(line.name, None, "extended", config, None, tmp_path / "eval"))
    assert len(records) == table1_rows.QUICK_EPISODES and not config.render
    assert {r["house_seed"] for r in records} <= set(split_seeds("test", table1_rows.EXTENDED_HOUSES))
    monkeypatch.setattr(table1_rows, "evaluate_line", lambda *a: pytest.fail("a rerun must read the cache"))
    again = table1.main(options(tmp_path, "--from-checkpoints", "--rows", "open_loop"))
    assert again["rows"] == table["rows"]


def test_training_copies_each_finished_seed_and_ships_the_best_by_validation(tmp_path, monkeypatch):
    """train_bc is replaced by a fake that writes what a finished run leaves: best.pt and results.json."""
    monkeypatch.chdir(tmp_path)
    trained = []

    def fake_train_bc(config):
        run = Path(config.output_dir)
        run.mkdir(parents=True)
        (run / "best.pt").write_text(f"seed {config.seed}")
        val = {0: 0.70, 1: 0.76, 2: 0.73}[config.seed]
        (run / "results.json").write_text(json.dumps({"val_best": {"success": val, "spl": val - 0.1, "epoch": 3}}))
        trained.append((config.model.name, config.model.sparsity, config.seed, config.optim.epochs, config.output_dir))

    monkeypatch.setattr("spf_rl.train.bc.train_bc", fake_train_bc)
    checkpoints = tmp_path / "checkpoints"
    shipped = table1_rows.train_missing([table1_rows.ROW_BY_NAME["spf-s0.8"], table1_rows.ROW_BY_NAME["rpf-s1"]], [0, 1, 2], [], checkpoints, False)
    assert [t[:4] for t in trained] == [("spf", 0.8, s, 40) for s in (0, 1, 2)] + [("rpf", 1.0, s, 20) for s in (0, 1, 2)]
    assert trained[0][4] == "runs/bc_long/spf-s0.8-seed0" and trained[3][4] == "runs/bc_row/rpf-s1.0-seed0"
    assert (checkpoints / "table1" / "spf-s0.8-seed2.pt").read_text() == "seed 2"
    assert shipped_file(checkpoints, "spf-s0.8").read_text() == "seed 1" and shipped["spf-s0.8"]["seed"] == 1
    trained.clear()
    table1_rows.train_missing([table1_rows.ROW_BY_NAME["spf-s0.8"]], [0, 1, 2], [], checkpoints, False)
    assert trained == []  # finished runs are not trained again


def test_from_checkpoints_trains_nothing_but_ships_finished_bc_and_dagger_runs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr("spf_rl.train.bc.train_bc", lambda config: pytest.fail("--from-checkpoints must not train"))
    for seed, val in ((0, 0.81), (2, 0.84)):  # seed 1 has no finished run
        run = Path(f"runs/bc_long/spf-s0.8-seed{seed}")
        run.mkdir(parents=True)
        (run / "best.pt").write_text(f"bc seed {seed}")
        (run / "results.json").write_text(json.dumps({"val_best": {"success": val, "spl": val, "epoch": 3}}))
        dagger = Path(f"runs/dagger_long/spf-s0.8-seed{seed}")
        dagger.mkdir(parents=True)
        (dagger / "best.pt").write_text(f"dagger seed {seed}")
        dagger_val = 0.9 - val / 10  # seed 0 is DAgger's best
        (dagger / "results.json").write_text(json.dumps({"best": {"round": 2, "val_success": dagger_val, "val_spl": 0.5}}))
    checkpoints = tmp_path / "checkpoints"
    shipped = table1_rows.train_missing([table1_rows.ROW_BY_NAME["spf-s0.8"]], [0, 1, 2], [], checkpoints, False, train=False)
    assert shipped["spf-s0.8"]["seed"] == 2 and shipped_file(checkpoints, "spf-s0.8").read_text() == "bc seed 2"
    assert shipped["dagger-spf-s0.8"]["seed"] == 0
    assert shipped_file(checkpoints, "dagger-spf-s0.8").read_text() == "dagger seed 0"
    assert (checkpoints / "table1" / "dagger-spf-s0.8-seed2.pt").read_text() == "dagger seed 2"
    assert not (checkpoints / "table1" / "spf-s0.8-seed1.pt").exists()


def test_dagger_column_reads_the_dagger_presets_run_directories():
    assert table1_rows.dagger_run_dir(table1_rows.ROW_BY_NAME["spf-s0.8"], 2) == Path("runs/dagger_long/spf-s0.8-seed2")
    assert table1_rows.dagger_run_dir(table1_rows.ROW_BY_NAME["rpf-s1"], 0) == Path("runs/dagger_rpf/rpf-s1.0-seed0")
    assert table1_rows.dagger_run_dir(table1_rows.ROW_BY_NAME["spf-s0.4"], 0) is None
    # each DAgger preset starts from the BC run of its row's schedule
    from spf_rl.train.dagger import DAggerConfig

    for name in ("spf-s0.8", "rpf-s1"):
        row = table1_rows.ROW_BY_NAME[name]
        dagger = load_config(DAggerConfig, "dagger", ["seed=1"], preset=row.dagger_preset)
        bc = table1_rows.row_config(row, 1, [], quick=False)
        assert Path(dagger.checkpoint) == Path(bc.output_dir) / "best.pt" and dagger.bc_data == bc.data


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


@pytest.mark.parametrize("row", [row for row in table1_rows.ROWS if row.dagger_preset], ids=lambda row: row.name)
def test_every_dagger_preset_starts_from_its_rows_run(row):
    """A row's DAgger preset starts from that row's own BC run (per seed), so the DAgger column is the row's."""
    from spf_rl.train.dagger import DAggerConfig

    for seed in (0, 2):
        dagger = load_config(DAggerConfig, "dagger", [f"seed={seed}"], preset=row.dagger_preset)
        bc = table1_rows.row_config(row, seed, [], quick=False)
        assert Path(dagger.checkpoint) == Path(bc.output_dir) / "best.pt"
        assert dagger.bc_data.num_episodes == bc.data.num_episodes


def test_the_pointer_row_trains_spf_with_rpfs_pointer_rule():
    config = table1_rows.row_config(table1_rows.ROW_BY_NAME["spf_rpf_pointer-s0.8"], 1, [], quick=False)
    assert (config.model.name, config.model.sparsity, config.model.pointer_update) == ("spf", 0.8, "rpf")
    assert config.output_dir.endswith("spf_rpf_pointer-s0.8-seed1")


def test_the_long_pointer_row_is_the_bc_pointer_long_preset():
    """The row trains exactly what ``python recipes/bc.py --preset bc_pointer_long`` trains (one schedule, one run dir)."""
    from spf_rl.train.bc import BCConfig

    row = table1_rows.row_config(table1_rows.ROW_BY_NAME["spf_rpf_pointer_long-s0.8"], 1, [], quick=False)
    assert row == load_config(BCConfig, "bc", ["seed=1"], preset="bc_pointer_long")
    assert table1_rows.row_config(table1_rows.ROW_BY_NAME["spf-s0.8"], 1, [], quick=False).optim == row.optim


def _lost_dagger_seed(tmp_path: Path) -> Path:
    """Checkpoints and runs of the original RPF: BC seeds 0 and 1 finished, DAgger seed 1 finished, and a
    per-seed DAgger checkpoint of seed 0 (also the shipped one) whose run directory is gone."""
    checkpoints = tmp_path / "checkpoints"
    (checkpoints / "table1").mkdir(parents=True)
    (checkpoints / "table1" / "dagger-rpf_original-s1-seed0.pt").write_text("dagger seed 0, run lost")
    write_manifest(checkpoints, {"dagger-rpf_original-s1": "table1/dagger-rpf_original-s1-seed0.pt"})  # shipped
    for seed in (0, 1):
        run = Path(f"runs/bc_row/rpf_original-s1.0-seed{seed}")
        run.mkdir(parents=True)
        (run / "best.pt").write_text(f"bc seed {seed}")
        (run / "results.json").write_text(json.dumps({"val_best": {"success": 0.8 + seed / 100, "spl": 0.8, "epoch": 3}}))
    dagger = Path("runs/dagger_rpf_original/rpf_original-s1.0-seed1")
    dagger.mkdir(parents=True)
    (dagger / "best.pt").write_text("dagger seed 1")
    (dagger / "results.json").write_text(json.dumps({"best": {"round": 4, "val_success": 0.88, "val_spl": 0.87}}))
    return checkpoints


@pytest.mark.parametrize("lost_seed_val, shipped_seed", [(0.95, 0), (0.50, 1)])
def test_a_seed_without_run_results_is_scored_on_its_runs_validation_episodes(
    tmp_path, monkeypatch, lost_seed_val, shipped_seed
):
    monkeypatch.chdir(tmp_path)
    checkpoints = _lost_dagger_seed(tmp_path)
    calls = []

    def validate(line, seed, checkpoint, config):
        calls.append((line, seed, checkpoint.name, config.split, config.num_episodes, config.seed))
        return lost_seed_val, lost_seed_val

    shipped = table1_rows.train_missing([table1_rows.ROW_BY_NAME["rpf_original-s1"]], [0, 1, 2], [], checkpoints, False,
                                   train=False, validate=validate)
    assert calls == [("dagger-rpf_original-s1", 0, "dagger-rpf_original-s1-seed0.pt", "val", 300, 1)]
    assert shipped["dagger-rpf_original-s1"] == {"seed": shipped_seed, "val_success": [lost_seed_val, 0.88][shipped_seed],
                                                 "val_spl": [lost_seed_val, 0.87][shipped_seed]}
    expected = "dagger seed 0, run lost" if shipped_seed == 0 else "dagger seed 1"
    assert shipped_file(checkpoints, "dagger-rpf_original-s1").read_text() == expected


def test_cached_validation_scores_once_and_rereads_the_cache(tmp_path, monkeypatch):
    import spf_rl.hub
    import spf_rl.train.evaluation
    from spf_rl.train.bc import default_val_config

    checkpoint = tmp_path / "ckpt.pt"
    checkpoint.write_bytes(b"weights")
    episodes = [{key: 0 for key in table1_report.RECORD_KEYS} | {"success": s, "spl": s / 2} for s in (1, 0, 1, 1)]
    monkeypatch.setattr(spf_rl.hub, "policy_from_checkpoint", lambda path, device: ("policy", None))
    monkeypatch.setattr(spf_rl.train.evaluation, "evaluate_policy", lambda policy, config, progress: ({}, episodes))
    validate = table1_rows.cached_validation(tmp_path / "eval", "cpu")
    assert validate("dagger-x", 0, checkpoint, default_val_config()) == (0.75, 0.375)
    monkeypatch.setattr(spf_rl.train.evaluation, "evaluate_policy", lambda *a, **k: pytest.fail("must read the cache"))
    assert validate("dagger-x", 0, checkpoint, default_val_config()) == (0.75, 0.375)
    assert (tmp_path / "eval" / "val" / "dagger-x-seed0.json").exists()


def test_a_seed_without_run_results_blocks_reshipping_its_line(tmp_path, monkeypatch):
    """Without ``validate``, a per-seed DAgger checkpoint whose run directory is gone has no validation
    score: the shipped file stays."""
    monkeypatch.chdir(tmp_path)
    checkpoints = _lost_dagger_seed(tmp_path)
    shipped = table1_rows.train_missing([table1_rows.ROW_BY_NAME["rpf_original-s1"]], [0, 1, 2], [], checkpoints, False, train=False)
    assert shipped["rpf_original-s1"]["seed"] == 1
    assert "dagger-rpf_original-s1" not in shipped
    assert shipped_file(checkpoints, "dagger-rpf_original-s1").read_text() == "dagger seed 0, run lost"
    assert (checkpoints / "table1" / "dagger-rpf_original-s1-seed1.pt").read_text() == "dagger seed 1"
