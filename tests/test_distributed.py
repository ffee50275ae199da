"""spf_rl.train.distributed: ranks from torchrun's environment, batch shards, and a BC run on 2 CPU
processes under torchrun that follows the 1-process run at the same global batch."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import spf_rl
from spf_rl.checkpoint import load_checkpoint
from spf_rl.train.dagger_rounds import round_directory
from spf_rl.train.distributed import Ranks, shard_indices

RECIPES = Path(spf_rl.__file__).resolve().parents[1] / "recipes"
TORCHRUN = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]
#: The episodes' sizes of every run here (the BC dataset's, DAgger's rounds' and the evaluations').
SIZES = ["demo_length=5", "max_steps=8", "image_size=32", "num_houses=2"]
#: Largest difference allowed between the 1-process and 2-process runs (losses, accuracies,
#: weights): the two differ only in the order of float sums (the gradient all-reduce).
TOLERANCE = 1e-5


def test_ranks_come_from_torchruns_environment(monkeypatch):
    for name in ("RANK", "WORLD_SIZE", "LOCAL_RANK"):
        monkeypatch.delenv(name, raising=False)
    assert Ranks.from_env() == Ranks(0, 1, 0) and not Ranks.from_env().distributed
    monkeypatch.setenv("RANK", "1")
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("LOCAL_RANK", "1")
    ranks = Ranks.from_env()
    assert ranks == Ranks(1, 2, 1) and ranks.distributed and not ranks.is_main
    monkeypatch.setenv("RANK", "2")
    with pytest.raises(ValueError, match="0 <= RANK < WORLD_SIZE"):
        Ranks.from_env()
    monkeypatch.setenv("RANK", "one")
    with pytest.raises(ValueError, match="RANK must be an integer"):
        Ranks.from_env()


@pytest.mark.parametrize("batch", [8, 7, 1])
@pytest.mark.parametrize("world_size", [1, 2, 3])
def test_shards_cover_the_global_batch(batch, world_size):
    indices = torch.randperm(20)[:batch]
    shards = [shard_indices(indices, Ranks(rank, world_size, rank)) for rank in range(world_size)]
    assert len({len(shard) for shard in shards}) == 1  # every rank gets as many episodes
    covered = torch.cat(shards)
    assert set(covered.tolist()) == set(indices.tolist())  # every episode of the batch, padding repeats some
    assert len(covered) == batch + (-batch % world_size)


def _run(recipe: str, launcher: list[str], overrides: list[str], output: Path) -> dict:
    environment = {**os.environ, "OMP_NUM_THREADS": "1"}
    result = subprocess.run(
        [*launcher, str(RECIPES / recipe), *overrides, f"output_dir={output}"],
        capture_output=True, text=True, timeout=600, env=environment,
    )
    assert result.returncode == 0, result.stderr[-4000:]
    return json.loads((output / "results.json").read_text())


def _evaluations(prefix: str) -> list[str]:
    return [f"{prefix}.num_episodes=4", f"{prefix}.num_agents=4", f"{prefix}.store_root=null"]


def _bc(tmp_path: Path, name: str, launcher: list[str]) -> dict:
    overrides = [  # the paper's recipe: its planner routes may be as short as 5 steps (the main job's labelled ones not)
        "--preset", "bc_paper", "seed=0", "num_workers=1", "progress=false", f"data_dir={tmp_path / 'data'}", "data.num_episodes=16",
        *(f"data.{size}" for size in SIZES), "optim.batch_size=8", "optim.epochs=2",
        *_evaluations("val"), *_evaluations("test"),
    ]
    return _run("bc.py", launcher, overrides, tmp_path / name)


@pytest.fixture(scope="session")
def one_process_bc(shared_build) -> Path:
    """The 1-process BC run (``one/``) and its dataset (``data/``), made once in the test session; tests copy
    the dataset rather than write next to it."""
    return shared_build("distributed-bc", lambda root: _bc(root, "one", [sys.executable]))


def _copy_data(one_process_bc: Path, tmp_path: Path) -> None:
    shutil.copytree(one_process_bc / "data", tmp_path / "data")


def _assert_same_weights(first: Path, second: Path) -> None:
    weights = [load_checkpoint(path)["model"] for path in (first, second)]
    for key, value in weights[0].items():
        torch.testing.assert_close(weights[1][key], value, atol=TOLERANCE, rtol=0)


def test_two_processes_follow_one_at_the_same_global_batch(tmp_path, one_process_bc):
    _copy_data(one_process_bc, tmp_path)
    one = json.loads((one_process_bc / "one" / "results.json").read_text())
    two = _bc(tmp_path, "two", TORCHRUN)
    assert len(one["history"]) == len(two["history"]) == 2
    for a, b in zip(one["history"], two["history"]):
        assert a["step"] == b["step"] == 2 * a["epoch"]  # 16 episodes, global batch 8: 2 steps an epoch
        assert abs(a["train_loss"] - b["train_loss"]) < TOLERANCE
        assert abs(a["train_accuracy"] - b["train_accuracy"]) < TOLERANCE
    _assert_same_weights(one_process_bc / "one" / "last.pt", tmp_path / "two" / "last.pt")
    # rank 0 alone wrote the run's files: one set, in the 2-process run's directory
    assert sorted(path.name for path in (tmp_path / "two").iterdir()) == sorted(
        path.name for path in (one_process_bc / "one").iterdir()
    )


def test_dagger_retrains_on_two_processes_as_on_one(tmp_path, one_process_bc):
    _copy_data(one_process_bc, tmp_path)
    overrides = [
        f"checkpoint={one_process_bc / 'one' / 'best.pt'}", "seed=0", "num_workers=1", "progress=false", "rounds=2",
        "episodes_per_round=4", "steps_per_round=3", "window_rounds=2", "test_every_round=false",
        "optim.batch_size=6", f"bc_data_dir={tmp_path / 'data'}", "bc_data.num_episodes=16",
        *(f"bc_data.{size}" for size in SIZES), *(f"env.{size}" for size in SIZES), "collector.num_agents=2",
        *_evaluations("val"), *_evaluations("test"),
    ]
    one = _run("dagger.py", [sys.executable], overrides, tmp_path / "one")
    two = _run("dagger.py", TORCHRUN, overrides, tmp_path / "two")
    assert [r["round"] for r in one["history"]] == [r["round"] for r in two["history"]] == [0, 1, 2]
    for a, b in zip(one["history"][1:], two["history"][1:]):
        assert a["gradient_steps"] == b["gradient_steps"] == 3 and a["training_episodes"] == b["training_episodes"]
        assert abs(a["train_loss"] - b["train_loss"]) < TOLERANCE
    _assert_same_weights(tmp_path / "one" / "last.pt", tmp_path / "two" / "last.pt")
    # rank 0 alone collected each round, the same episodes as one process (the stores' checksums)
    for index in (1, 2):
        metas = [json.loads((round_directory(tmp_path / name, index) / "meta.json").read_text()) for name in ("one", "two")]
        assert metas[0]["checksums"] == metas[1]["checksums"]
