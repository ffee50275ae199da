"""Tests for spf_rl.pointer_pace and how Table 1 reports it: the pointer's mean increment per step,
teacher-forced, for both pointer rules; the table's per-seed paces and the mark of a pointer that runs backwards."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch

from envs.episode_spec import EpisodeSpec
from spf_rl.checkpoint import save_checkpoint
from spf_rl.data import DatasetConfig, empty_training_episodes
from spf_rl.eval import table1 as table1_report
from spf_rl.eval import table1_rows
from spf_rl.modules import OpenLoopPolicy
from spf_rl.modules.registry import ModelConfig, build_policy, spf_config
from spf_rl.pointer_pace import BACKWARD_PACE, pointer_pace

N = 6


def episodes(count: int = 3, valid: int = 5) -> torch.Tensor:
    """Random stored episodes with their demonstrations, ``valid`` steps each."""
    torch.manual_seed(0)
    out = empty_training_episodes(DatasetConfig(episodes=EpisodeSpec(demo_length=N, max_steps=8, image_size=16), num_episodes=count))
    out["steps", "pixels"].random_(0, 256)
    out["demo_frames"].random_(0, 256)
    out["steps", "mask"][:, :valid] = True
    out["steps", "is_init"][:, 0] = True
    return out


def policy(step: float, pointer_update: str = "paper", name: str = "spf"):
    model = ModelConfig(name=name, sparsity=0.5, feature_dim=8, hidden_size=8, initial_pointer_step=step,
                        pointer_update=pointer_update)
    return build_policy(name, spf_config(model, demo_length=N, image_size=16))


@pytest.mark.parametrize("step", [0.9, -0.7])
def test_the_papers_rule_moves_by_tanh_b_either_way(step):
    pace = pointer_pace(policy(step), episodes(), batch_size=2)  # two batches, one of one episode
    assert pace == pytest.approx(step, abs=1e-5)
    assert (pace < BACKWARD_PACE) == (step < 0)


def test_rpfs_rule_never_moves_backwards():
    # eta + 1 + tanh(b) >= 0 until the clamp at n - 1: 5 steps from 0 at 0.3 per step stay below n - 1 = 5
    assert pointer_pace(policy(-0.7, "rpf"), episodes()) == pytest.approx(0.3, abs=1e-5)


def test_only_valid_steps_count():
    trained = policy(0.5)
    head = trained.cell.pointer_head
    with torch.no_grad():  # a pointer head that reads the hidden state: paces differ step by step
        (head[-1] if isinstance(head, torch.nn.Sequential) else head).weight.normal_(0, 2.0)
    short, long = episodes(valid=2), episodes(valid=5)
    padded = long.clone()
    padded["steps", "mask"][:, 2:] = False
    assert pointer_pace(trained, padded) == pytest.approx(pointer_pace(trained, short))
    assert pointer_pace(trained, long) != pytest.approx(pointer_pace(trained, short))


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="batch_size must be >= 1, got 0"):
        pointer_pace(policy(0.5), episodes(), batch_size=0)
    with pytest.raises(ValueError, match="no valid step"):
        pointer_pace(policy(0.5), episodes(valid=0))
    with pytest.raises(ValueError, match="has no attention pointer"):
        pointer_pace(OpenLoopPolicy(), episodes())


def test_table1_measures_every_seeds_checkpoint_on_validation_episodes(tmp_path, monkeypatch):
    checkpoints = tmp_path / "ckpt"
    (checkpoints / "table1").mkdir(parents=True)
    for seed, step in ((0, 0.8), (2, -0.6)):  # seed 1 has no checkpoint
        model = policy(step)
        save_checkpoint(checkpoints / "table1" / f"spf-s0.8-seed{seed}.pt", "spf", model.config, {"model": model.state_dict()})
    built = []

    def fake_pace_episodes(overrides, quick):
        built.append((tuple(overrides), quick))
        return episodes(), tmp_path / "data" / "val"

    monkeypatch.setattr(table1_rows, "pace_episodes", fake_pace_episodes)
    rows = [table1_rows.ROW_BY_NAME[name] for name in ("spf-s0.8", "open_loop")]
    lines = table1_rows.table_lines(rows, N, 16)
    paces, info = table1_rows.pointer_paces(lines, [0, 1, 2], checkpoints, [], True, "cpu")
    assert set(paces) == {"spf-s0.8", "dagger-spf-s0.8"} and paces["dagger-spf-s0.8"] == {}
    assert paces["spf-s0.8"] == {"0": pytest.approx(0.8, abs=1e-5), "2": pytest.approx(-0.6, abs=1e-5)}
    assert built == [((), True)]  # the episodes are built once, at the first checkpoint
    assert info["episodes"] == 3 and info["dataset"].endswith("data/val")
    assert table1_rows.pointer_paces(lines[-1:], [0], checkpoints, [], True, "cpu") == ({}, None)  # nothing to measure


def test_pace_episodes_are_the_training_data_on_the_validation_split(tmp_path, monkeypatch):
    from spf_rl.data import EpisodeDataset
    from spf_rl.evaluation import VAL_SEED

    calls = []
    monkeypatch.setattr(EpisodeDataset, "build", classmethod(lambda cls, root, config, workers, progress: calls.append(
        (Path(root), config)) or episodes(2)))
    train = table1_rows.row_config(table1_rows.ROW_BY_NAME["spf-s0.8"], 0, [], quick=False).data
    table1_rows.pace_episodes([], quick=False)
    table1_rows.pace_episodes([], quick=True)
    (root, config), (_, quick) = calls
    assert config == dataclasses.replace(
        train, episodes=train.episodes.replace(split="val", seed=VAL_SEED), num_episodes=table1_rows.PACE_EPISODES
    )
    assert quick.num_episodes == table1_rows.QUICK_EPISODES
    assert root.parts[0] == "data" and root.name.startswith(f"val-{table1_rows.PACE_EPISODES}ep-")


def test_a_line_with_a_backward_seed_is_marked_and_named():
    stats = {"success": {"mean": 0.6, "sd": 0.2}, "spl": {"mean": 0.55, "sd": 0.2}}
    row = {"name": "spf-s0.4", "row": "spf-s0.4", "checkpoint_stem": "spf-s0.4", "label": "SPF sparsity 0.4", "model": "spf",
           "dagger_of": None, "seeds": [0, 1, 2], "seeds_expected": [0, 1, 2], "missing_seeds": [], "sets": {"test": stats},
           "paper_success": 0.782, "paper_spl": 0.7, "pointer_pace": {"0": 0.9, "1": 0.88, "2": -0.7}}
    healthy = {**row, "name": "spf-s0.6", "row": "spf-s0.6", "label": "SPF sparsity 0.6", "pointer_pace": {"0": 0.9}}
    text = table1_report.summary_markdown({"rows": [row, healthy], "claims": []})
    assert f"| SPF sparsity 0.4 {table1_report.BACKWARD_MARK} |" in text and "| SPF sparsity 0.6 |" in text
    assert "pointer runs backwards (SPF sparsity 0.4: seed 2; `pointer_pace`)" in text
    assert table1_report.backward_seeds(row) == [2] and table1_report.backward_seeds(healthy) == []
