"""The device option on a GPU: training, collection, evaluation and checkpoints on CUDA
against the CPU, and bf16 autocast on CUDA. Skipped (not failed) where CUDA is missing;
``scripts/gpu_check.sh`` runs them on a GPU machine. The CPU side of the plumbing is
tested with the ``meta`` device in ``tests/test_device.py``."""
from __future__ import annotations

import copy
from pathlib import Path

import pytest
import torch
from test_device import assert_amp_agreement, random_sequence, step_and_sequence_logits, tiny_ppo_config

import spf_rl
from envs.episode_spec import EpisodeSpec
from spf_rl.checkpoint import load_checkpoint, save_checkpoint
from spf_rl.data import DatasetConfig, empty_training_episodes
from spf_rl.device import resolve_device
from spf_rl.evaluation import EvalConfig, evaluate_policy
from spf_rl.hub import policy_from_checkpoint
from spf_rl.modules import SPFConfig
from spf_rl.modules.registry import ModelConfig, build_policy
from spf_rl.train.bc import BCConfig, bc_loss, train_bc
from spf_rl.train.collection import CollectionEnvConfig, CollectorConfig, make_collector
from spf_rl.train.dagger import DAggerConfig, train_dagger
from spf_rl.train.ppo import train_ppo
from spf_rl.train.ppo_loss import AMP_RATIO_SYNC_TOLERANCE, RATIO_SYNC_TOLERANCE, make_ppo_modules, recompute_log_prob
from spf_rl.train.run import OptimConfig

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (torch.cuda.is_available() is False)")

CUDA = torch.device("cuda")
POLICY = SPFConfig(demo_length=5, sparsity=0.4, feature_dim=16, hidden_size=16, image_size=(32, 32))
ENV = CollectionEnvConfig(episodes=EpisodeSpec(num_houses=1, demo_length=5, max_steps=8, image_size=32), with_expert=False)
EVALUATION = dict(num_episodes=2, num_agents=2)
#: the episodes' sizes of the BC data, the DAgger env and (so the policy is evaluated on the episodes it is built for) val and test
SIZES = dict(num_houses=1, demo_length=5, max_steps=8, image_size=32)


@pytest.fixture
def no_tf32(tf32_flags):
    """Full float32 convolutions and matmuls, so that CUDA and CPU float32 agree closely."""
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False


def tensors(value):
    if isinstance(value, torch.Tensor):
        yield value
    elif isinstance(value, dict):
        for item in value.values():
            yield from tensors(item)
    elif isinstance(value, (list, tuple)):
        for item in value:
            yield from tensors(item)


def raw_devices(path: Path) -> set[str]:
    """Devices of the tensors as stored in the file (no map_location)."""
    return {t.device.type for t in tensors(torch.load(path, map_location=None, weights_only=True))}


def test_auto_resolves_to_cuda_and_bad_indices_are_refused():
    assert resolve_device("auto").type == "cuda"
    with pytest.raises(ValueError, match="CUDA device"):
        resolve_device(f"cuda:{torch.cuda.device_count()}")


def test_bc_loss_on_cuda_matches_the_cpu(no_tf32):
    torch.manual_seed(0)
    policy = build_policy("spf", POLICY)
    episodes = empty_training_episodes(DatasetConfig(episodes=EpisodeSpec(demo_length=5, max_steps=6, image_size=32), num_episodes=3))
    episodes["steps", "mask"][:, :5] = True
    episodes["steps", "pixels"].random_(0, 256)
    episodes["demo_frames"].random_(0, 256)
    on_cuda = copy.deepcopy(policy).to(CUDA)
    loss_cpu, accuracy_cpu = bc_loss(policy, episodes)
    loss_cuda, accuracy_cuda = bc_loss(on_cuda, episodes)  # the CPU batch moves to the policy's device
    assert loss_cuda.device.type == "cuda"
    torch.testing.assert_close(loss_cuda.cpu(), loss_cpu, rtol=1e-4, atol=1e-4)
    loss_cuda.backward()
    assert all(p.grad.device.type == "cuda" for p in on_cuda.parameters() if p.grad is not None)
    loss_amp, _ = bc_loss(on_cuda, episodes, amp=True)
    assert loss_amp.dtype == torch.float32 and torch.isfinite(loss_amp)
    torch.testing.assert_close(loss_amp.cpu(), loss_cpu, rtol=5e-2, atol=5e-2)


def test_checkpoints_written_on_cuda_are_device_neutral(tmp_path):
    policy = build_policy("spf", POLICY).to(CUDA)
    optimizer = torch.optim.Adam(policy.parameters())
    for p in policy.parameters():
        p.grad = torch.ones_like(p)
    optimizer.step()
    path = tmp_path / "cuda.pt"
    save_checkpoint(path, "spf", POLICY, {"model": policy.state_dict(), "optimizer": optimizer.state_dict()})
    assert raw_devices(path) == {"cpu"}  # the same file a CPU run writes
    payload = load_checkpoint(path, map_location="cuda")
    assert {t.device.type for t in payload["model"].values()} == {"cuda"}
    loaded, _ = policy_from_checkpoint(path, device="cuda")
    for (name, a), b in zip(policy.state_dict().items(), loaded.state_dict().values()):
        assert b.device.type == "cuda" and torch.equal(a, b), name
    on_cpu, _ = policy_from_checkpoint(path, device="cpu")
    assert {p.device.type for p in on_cpu.parameters()} == {"cpu"}


def test_step_and_sequence_logits_agree_on_cuda(no_tf32):
    policy, config = spf_rl.load_policy("spf-s0.8", device="cuda")
    torch.manual_seed(0)
    sequence = random_sequence(config, rows=3, steps=12, restart_at=7)
    step32, whole32 = step_and_sequence_logits(policy, sequence, amp=False)
    torch.testing.assert_close(step32, whole32, rtol=1e-4, atol=1e-4)
    step16, whole16 = step_and_sequence_logits(policy, sequence, amp=True)
    assert_amp_agreement(step16, whole16, whole32)
    cpu_policy, _ = spf_rl.load_policy("spf-s0.8")
    _, whole_cpu = step_and_sequence_logits(cpu_policy, sequence, amp=False)
    torch.testing.assert_close(whole32.cpu(), whole_cpu, rtol=1e-4, atol=1e-4)


def test_evaluation_on_cuda_plays_the_cpu_episodes(no_tf32):
    config = EvalConfig(episodes=EpisodeSpec(split="val", num_houses=1, max_steps=20, seed=3), num_episodes=4, num_agents=4)
    cpu_policy, _ = spf_rl.load_policy("spf-s0.8")
    cuda_policy, _ = spf_rl.load_policy("spf-s0.8", device="cuda")
    _, cpu_records = evaluate_policy(cpu_policy, config)
    summary, cuda_records = evaluate_policy(cuda_policy, config)
    assert summary["episodes"] == 4 and next(cuda_policy.parameters()).device.type == "cuda"
    same = sum(a == b for a, b in zip(cpu_records, cuda_records))
    assert same >= len(cpu_records) - 1  # greedy actions: at most one near-tie may flip


def test_collector_acts_on_cuda_with_envs_on_the_cpu(no_tf32):
    torch.manual_seed(0)
    policy = build_policy("spf", POLICY).eval()
    actor, _ = make_ppo_modules(policy)
    actor.to(CUDA)
    for storing, expected in ((None, "cuda"), ("cpu", "cpu")):
        collector = make_collector(actor, ENV, CollectorConfig(num_agents=2), frames_per_batch=24, total_frames=24,
                                   reset_at_each_iter=True, device=CUDA, storing_device=storing)
        batch = next(iter(collector))
        collector.shutdown()
        assert {leaf.device.type for leaf in batch.values(True, True)} == {expected}
    replayed = recompute_log_prob(actor, batch.to(CUDA))
    assert (replayed - batch["action_log_prob"].to(CUDA)).abs().max() < RATIO_SYNC_TOLERANCE


@pytest.mark.parametrize("amp", [False, True])
def test_tiny_ppo_run_on_cuda(tmp_path, amp):
    torch.manual_seed(0)
    start = tmp_path / "start.pt"
    save_checkpoint(start, "spf", POLICY, {"model": build_policy("spf", POLICY).state_dict()})
    history = train_ppo(tiny_ppo_config(tmp_path, start, device="cuda", amp=amp, ppo_epochs=2, val_every=1))["history"]
    assert [r["skipped_updates"] for r in history] == [0, 0]
    assert history[1]["log_ratio_first"] < (AMP_RATIO_SYNC_TOLERANCE if amp else RATIO_SYNC_TOLERANCE)
    assert raw_devices(tmp_path / "run" / "last.pt") == raw_devices(tmp_path / "run" / "best.pt") == {"cpu"}


def test_tiny_bc_then_dagger_on_cuda(tmp_path):
    data = DatasetConfig(episodes=EpisodeSpec(**SIZES), num_episodes=8, chunk_size=4)
    bc = BCConfig(
        output_dir=str(tmp_path / "bc"), data_dir=str(tmp_path / "data"), device="cuda", num_workers=1, logger="",
        progress=False, data=data, model=ModelConfig(name="spf", sparsity=0.4, feature_dim=16, hidden_size=16),
        optim=OptimConfig(batch_size=4, epochs=1, lr=3e-3, amp=True),
        val=EvalConfig(EpisodeSpec(split="val", seed=1, **SIZES), **EVALUATION),
        test=EvalConfig(EpisodeSpec(split="test", seed=2, **SIZES), **EVALUATION),
    )
    assert train_bc(bc)["test"]["episodes"] == 2
    assert raw_devices(tmp_path / "bc" / "best.pt") == {"cpu"}
    dagger = DAggerConfig(
        checkpoint=str(tmp_path / "bc" / "best.pt"), output_dir=str(tmp_path / "dagger"), device="cuda", rounds=1,
        episodes_per_round=4, aggregate_bc_data=False, logger="", progress=False, test_every_round=False,
        env=CollectionEnvConfig(episodes=EpisodeSpec(**SIZES)),
        collector=CollectorConfig(num_agents=2), optim=OptimConfig(batch_size=2, lr=3e-4, cosine_schedule=False),
        val=EvalConfig(EpisodeSpec(split="val", seed=1, **SIZES), **EVALUATION),
        test=EvalConfig(EpisodeSpec(split="test", seed=2, **SIZES), **EVALUATION),
    )
    results = train_dagger(dagger)
    assert [r["round"] for r in results["history"]] == [0, 1]
    assert raw_devices(tmp_path / "dagger" / "last.pt") == {"cpu"}
