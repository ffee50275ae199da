"""spf_rl.train.distributed: ranks from torchrun's environment, batch shards, and a BC run on 2 CPU
processes under torchrun that follows the 1-process run at the same global batch."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import spf_rl
from spf_rl.checkpoint import load_checkpoint
from spf_rl.train.distributed import Ranks, shard_indices

BC_RECIPE = Path(spf_rl.__file__).resolve().parents[1] / "recipes" / "bc.py"
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


def _bc(tmp_path: Path, name: str, launcher: list[str]) -> dict:
    overrides = [
        "seed=0", "num_workers=1", "progress=false", f"data_dir={tmp_path / 'data'}", f"output_dir={tmp_path / name}",
        "data.num_episodes=16", "data.num_houses=2", "data.demo_length=5", "data.max_steps=8", "data.image_size=32",
        "optim.batch_size=8", "optim.epochs=2", "val.num_episodes=4", "val.num_agents=4", "val.store_root=null",
        "test.num_episodes=4", "test.num_agents=4", "test.store_root=null",
    ]
    environment = {**os.environ, "OMP_NUM_THREADS": "1"}
    result = subprocess.run(
        [*launcher, str(BC_RECIPE), *overrides], capture_output=True, text=True, timeout=600, env=environment
    )
    assert result.returncode == 0, result.stderr[-4000:]
    return json.loads((tmp_path / name / "results.json").read_text())


def test_two_processes_follow_one_at_the_same_global_batch(tmp_path):
    one = _bc(tmp_path, "one", [sys.executable])
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"]
    two = _bc(tmp_path, "two", torchrun)
    assert len(one["history"]) == len(two["history"]) == 2
    for a, b in zip(one["history"], two["history"]):
        assert a["step"] == b["step"] == 2 * a["epoch"]  # 16 episodes, global batch 8: 2 steps an epoch
        assert abs(a["train_loss"] - b["train_loss"]) < TOLERANCE
        assert abs(a["train_accuracy"] - b["train_accuracy"]) < TOLERANCE
    weights = [load_checkpoint(tmp_path / name / "last.pt")["model"] for name in ("one", "two")]
    for key, value in weights[0].items():
        torch.testing.assert_close(weights[1][key], value, atol=TOLERANCE, rtol=0)
    # rank 0 alone wrote the run's files: one set, in the 2-process run's directory
    assert sorted(path.name for path in (tmp_path / "two").iterdir()) == sorted(
        path.name for path in (tmp_path / "one").iterdir()
    )
