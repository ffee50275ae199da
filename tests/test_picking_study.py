"""recipes/picking_study.py and BCConfig.keep_epochs: every epoch's weights, scored on test."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import picking_study
import pytest
import torch
from test_bc import tiny_config

from spf_rl.checkpoint import load_checkpoint
from spf_rl.eval import picking
from spf_rl.train.bc import train_bc
from spf_rl.train.run import epoch_checkpoint


@pytest.fixture(scope="module")
def kept_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("picking")
    config = dataclasses.replace(tiny_config(tmp, epochs=3), keep_epochs=True, val_every=1)
    train_bc(config)
    return Path(config.output_dir)


def test_every_epoch_is_kept_with_its_own_weights(kept_run):
    payloads = [load_checkpoint(epoch_checkpoint(kept_run, epoch)) for epoch in (1, 2, 3)]
    assert [p["epoch"] for p in payloads] == [1, 2, 3]
    first, last = payloads[0]["model"], payloads[-1]["model"]
    assert any(not torch.equal(first[k], last[k]) for k in first)  # training moved the weights
    final = load_checkpoint(kept_run / "last.pt")["model"]
    assert all(torch.equal(final[k], last[k]) for k in final)  # the last epoch's file holds the final weights


def test_study_scores_every_epoch_and_resumes(kept_run, tmp_path, monkeypatch):
    study = picking_study.main([str(kept_run), "--episodes", "2", "--out", str(tmp_path), "--quiet", "--device", "cpu"])
    assert [row["epoch"] for row in study["epochs"]] == [1, 2, 3]
    history = {r["epoch"]: r["val_success"] for r in load_checkpoint(kept_run / "last.pt")["history"]}
    assert [row["val_success"] for row in study["epochs"]] == [history[e] for e in (1, 2, 3)]
    saved = json.loads((tmp_path / f"{kept_run.parent.name}-{kept_run.name}.json").read_text())
    assert saved["summary"] == json.loads(json.dumps(study["summary"]))
    assert saved["test"]["num_episodes"] == 2 and saved["test"]["split"] == "test"

    calls = []
    monkeypatch.setattr("spf_rl.evaluation.evaluate_policy", lambda *a, **k: calls.append(1))
    again = picking_study.main([str(kept_run), "--episodes", "2", "--out", str(tmp_path), "--quiet", "--device", "cpu"])
    assert calls == [] and again["epochs"] == study["epochs"]  # nothing scored twice


def test_summary_picks_and_ranks():
    summary = picking.summarize_study([1, 2, 3, 4], [0.5, 0.7, 0.7, 0.6], [0.4, 0.6, 0.8, 0.7])
    assert summary["picked_by_validation"] == {"epoch": 2, "val_success": 0.7, "test_success": 0.6}
    assert summary["best_on_test"]["epoch"] == 3 and summary["last"]["epoch"] == 4
    assert summary["regret_of_validation"] == pytest.approx(0.2)
    assert 0 < summary["spearman_rho"] < 1
    assert picking.rank_agreement([1, 2, 3], [3, 2, 1])["spearman_rho"] == pytest.approx(-1.0)
    assert picking.rank_agreement([0.5, 0.5, 0.5], [0.1, 0.2, 0.3])["spearman_rho"] is None  # no NaN in the JSON


@pytest.mark.parametrize(
    "argv, message",
    [(["--episodes", "0"], "--episodes must be a positive"), ([], "keep_epochs=true")],
)
def test_bad_input_is_refused_before_any_work(argv, message, tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text("{}")
    torch.save({}, run / "last.pt")
    with pytest.raises(SystemExit) as exit_info:
        picking_study.main([str(run), "--out", str(tmp_path / "out"), *argv])
    assert exit_info.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
