"""Tests for spf_rl.train.pointer_guard: the pointer-collapse guard of BC and DAgger runs. A collapse is
forced (a pointer that starts running backwards, or a measured pace replaced by a backwards one); a run
that never collapses trains exactly as it would without the guard."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import torch
from test_bc import tiny_config

from spf_rl.checkpoint import content_sha256, load_checkpoint
from spf_rl.train import pointer_guard
from spf_rl.train.bc import train_bc
from spf_rl.train.pointer_guard import COLLAPSE_PACE, MAX_RESTARTS, PointerGuard, restart_seed


def weights(path: Path) -> str:
    return content_sha256(load_checkpoint(path)["model"])


def backwards_once(monkeypatch, at_call: int = 1) -> list[float]:
    """Replace the guard's measured pace by -1 at its ``at_call``-th measurement; returns the paces measured."""
    real, paces = PointerGuard.pace, []

    def pace(self, policy, ranks=None):
        value = real(self, policy, ranks)
        paces.append(value)
        return -1.0 if len(paces) == at_call else value

    monkeypatch.setattr(PointerGuard, "pace", pace)
    return paces


def test_a_run_that_never_collapses_trains_as_without_the_guard(tmp_path, monkeypatch):
    guarded = train_bc(tiny_config(tmp_path / "guarded", epochs=2))
    assert all(record["pointer_pace"] > COLLAPSE_PACE for record in guarded["history"])  # logged every epoch
    assert guarded["pointer_restarts"] == []
    monkeypatch.setattr(PointerGuard, "of", classmethod(lambda cls, policy, source: None))  # no guard at all
    bare = train_bc(tiny_config(tmp_path / "bare", epochs=2))
    assert "pointer_pace" not in bare["history"][0]
    for name in ("best.pt", "last.pt"):
        assert weights(tmp_path / "guarded" / "run" / name) == weights(tmp_path / "bare" / "run" / name)
    assert [r["train_loss"] for r in guarded["history"]] == [r["train_loss"] for r in bare["history"]]


def test_a_collapse_restarts_bc_from_a_documented_seed(tmp_path, monkeypatch):
    backwards_once(monkeypatch)
    config = tiny_config(tmp_path, epochs=2)
    results = train_bc(config)
    assert results["pointer_restarts"] == [{"epoch": 1, "pointer_pace": -1.0, "seed": restart_seed(config.seed, 1)}]
    assert [r["epoch"] for r in results["history"]] == [1, 2]  # the restarted run's epochs only
    saved = json.loads((tmp_path / "run" / "results.json").read_text())
    assert saved["pointer_restarts"] == results["pointer_restarts"]
    assert load_checkpoint(tmp_path / "run" / "last.pt")["pointer_restarts"] == results["pointer_restarts"]
    # the logs hold the restarted run's steps once each (the collapsed attempt's rows trimmed, a fresh logger on)
    loss_log = next((tmp_path / "run" / "logs").rglob("loss.csv"))
    steps = [int(float(line.split(",")[0])) for line in loss_log.read_text().splitlines() if line.strip()]
    assert steps == list(range(1, results["history"][-1]["step"] + 1))
    # the restarted run is deterministic: the same forced collapse gives the same weights
    again = tmp_path / "again"
    backwards_once(monkeypatch)
    train_bc(dataclasses.replace(config, output_dir=str(again / "run")))
    assert weights(again / "run" / "best.pt") == weights(tmp_path / "run" / "best.pt")


def test_an_interrupted_restart_resumes_the_restarted_run(tmp_path, monkeypatch):
    from spf_rl.train.run import TrainingRun

    config = tiny_config(tmp_path, epochs=2)
    backwards_once(monkeypatch)
    uninterrupted = train_bc(dataclasses.replace(config, output_dir=str(tmp_path / "whole")))

    backwards_once(monkeypatch)
    real_train_epoch, calls = TrainingRun.train_epoch, []

    def crash_after_the_restart(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 2:  # the restarted run's first epoch
            raise KeyboardInterrupt
        return real_train_epoch(self, *args, **kwargs)

    monkeypatch.setattr(TrainingRun, "train_epoch", crash_after_the_restart)
    with pytest.raises(KeyboardInterrupt):
        train_bc(config)
    assert load_checkpoint(tmp_path / "run" / "last.pt")["epoch"] == 0 and not (tmp_path / "run" / "best.pt").exists()
    monkeypatch.setattr(TrainingRun, "train_epoch", real_train_epoch)
    monkeypatch.setattr(PointerGuard, "pace", lambda self, policy, ranks=None: 0.9)  # healthy from here on
    resumed = train_bc(config)
    assert resumed["pointer_restarts"] == uninterrupted["pointer_restarts"]
    assert [r["train_loss"] for r in resumed["history"]] == [r["train_loss"] for r in uninterrupted["history"]]
    assert weights(tmp_path / "run" / "last.pt") == weights(tmp_path / "whole" / "last.pt")


def test_a_pointer_that_keeps_running_backwards_stops_restarting(tmp_path, caplog):
    """A pointer that starts at tanh(b) = -0.95 runs backwards after an epoch, every time: MAX_RESTARTS, then on."""
    config = tiny_config(tmp_path, epochs=1)
    config = dataclasses.replace(config, model=dataclasses.replace(config.model, initial_pointer_step=-0.95))
    with caplog.at_level("WARNING", logger=pointer_guard.__name__):
        results = train_bc(config)
    restarts = results["pointer_restarts"]
    assert [r["seed"] for r in restarts] == [restart_seed(config.seed, k) for k in range(1, MAX_RESTARTS + 1)]
    assert all(r["pointer_pace"] < COLLAPSE_PACE and r["epoch"] == 1 for r in restarts)
    assert results["history"][-1]["pointer_pace"] < COLLAPSE_PACE and "training on" in caplog.text


def test_a_collapsed_dagger_round_is_set_aside_and_the_next_starts_from_the_best(tmp_path, monkeypatch):
    from test_dagger import save_bc_checkpoint
    from test_dagger import tiny_config as dagger_config

    from spf_rl.train.dagger import train_dagger
    from spf_rl.train.dagger_rounds import learner_path

    start = save_bc_checkpoint(tmp_path)
    backwards_once(monkeypatch)  # round 1's pace
    config = dagger_config(tmp_path, start, rounds=2)
    results = train_dagger(config)
    history = results["history"]
    assert history[1]["pointer_collapsed"] and history[1]["pointer_pace"] == -1.0
    assert "pointer_collapsed" not in history[2] and results["best"]["round"] != 1
    output = Path(config.output_dir)
    # round 1's learner (which collected round 2) holds round 0's weights, not the collapsed ones
    assert weights(learner_path(output, 1)) == weights(learner_path(output, 0)) == content_sha256(load_checkpoint(start)["model"])


def test_policies_without_a_pointer_have_no_guard(tmp_path):
    from spf_rl.data import EpisodeDataset
    from spf_rl.modules import OpenLoopPolicy
    from spf_rl.modules.registry import build_policy, spf_config

    config = tiny_config(tmp_path, epochs=1)
    dataset = EpisodeDataset.build(tmp_path / "data", config.data, num_workers=1, progress=False)
    assert PointerGuard.of(OpenLoopPolicy(), dataset) is None
    guard = PointerGuard.of(build_policy("spf", spf_config(config.model, 5, 32)), dataset)
    assert guard is not None and guard.episodes.shape[0] == min(pointer_guard.GUARD_EPISODES, len(dataset))
    assert torch.equal(guard.episodes["steps", "action"], dataset[: guard.episodes.shape[0]]["steps", "action"])
