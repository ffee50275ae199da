"""End-to-end tests of spf_rl.train.bc on a tiny configuration: train, resume, results."""
from __future__ import annotations

import dataclasses
import json

import pytest
import torch

from envs.episode_spec import SIZE_FIELDS, EpisodeSpec
from spf_rl.data import DatasetConfig, EpisodeDataset
from spf_rl.evaluation import EvalConfig
from spf_rl.modules.registry import ModelConfig, build_policy, spf_config
from spf_rl.train.bc import BCConfig, bc_loss, train_bc
from spf_rl.train.run import OptimConfig

DATA = DatasetConfig(episodes=EpisodeSpec(num_houses=1, demo_length=5, max_steps=8, image_size=32), num_episodes=8, chunk_size=4)


def tiny_config(tmp_path, epochs: int, model: str = "spf", data: DatasetConfig = DATA) -> BCConfig:
    evaluation = dict(num_episodes=2, num_agents=2)
    sizes = {key: getattr(data.episodes, key) for key in ("num_houses", *SIZE_FIELDS)}  # as the training episodes
    return BCConfig(
        output_dir=str(tmp_path / "run"),
        data_dir=str(tmp_path / "data"),
        device="cpu",  # the CPU suite everywhere; tests/test_device_cuda.py runs BC on CUDA
        num_workers=1,
        logger="csv",
        progress=False,
        data=data,
        model=ModelConfig(name=model, sparsity=0.4, feature_dim=16, hidden_size=16),
        optim=OptimConfig(batch_size=4, epochs=epochs, lr=3e-3),
        val=EvalConfig(EpisodeSpec(split="val", seed=1, **sizes), **evaluation),
        test=EvalConfig(EpisodeSpec(split="test", seed=2, **sizes), **evaluation),
    )


def test_loss_falls_on_a_tiny_dataset(tmp_path):
    dataset = EpisodeDataset.build(tmp_path / "data", DATA, num_workers=1, progress=False)
    policy = build_policy("spf", spf_config(ModelConfig(sparsity=0.4, feature_dim=16, hidden_size=16), 5, 32))
    optimizer = torch.optim.Adam(policy.parameters(), lr=3e-3)
    batch = dataset[:8]
    first = None
    for _ in range(40):
        loss, _ = bc_loss(policy, batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        first = loss.item() if first is None else first
    assert loss.item() < 0.6 * first


def test_train_resume_and_results(tmp_path):
    one = train_bc(tiny_config(tmp_path, epochs=1))
    assert len(one["history"]) == 1
    # run again with more epochs: resumes after epoch 1 instead of starting over
    two = train_bc(tiny_config(tmp_path, epochs=2))
    assert [h["epoch"] for h in two["history"]] == [1, 2]
    assert two["history"][0] == one["history"][0]
    run = tmp_path / "run"
    results = json.loads((run / "results.json").read_text())
    assert results["test"]["episodes"] == 2
    low, high = results["test"]["success_ci"]
    assert low <= results["test"]["success"] <= high
    assert results["memory_bytes"] == 2 * 3 * 32 * 32 + 5  # l = round(0.4 * 5) = 2 frames + 5 actions
    assert results["machine_this_run"]["cpu_count"] >= 1 and results["machine_this_run"]["cpu_model"]  # results depend on the CPU
    assert (run / "training_curves.png").stat().st_size > 1000
    assert (run / "best.pt").exists() and (run / "last.pt").exists()
    # the test records say what they are of (the weights, not the file), so a DAgger run from best.pt reuses them
    # (tests/test_dagger.py), and so does Table 1 from a copy of the file elsewhere
    import shutil

    from spf_rl.evaluation import summarize_episodes
    from spf_rl.hub import policy_from_checkpoint
    from spf_rl.records_cache import read_records, records_key

    test_config = tiny_config(tmp_path, epochs=2).test
    shutil.copy(run / "best.pt", tmp_path / "moved.pt")
    for path in (run / "best.pt", tmp_path / "moved.pt"):
        records = read_records(run / "test_episodes.json", records_key(test_config, policy_from_checkpoint(path)[0]))
        assert summarize_episodes(records)["success"] == results["test"]["success"] and len(records) == 2
    last = records_key(test_config, policy_from_checkpoint(run / "last.pt")[0])
    assert read_records(run / "test_episodes.json", last) is None  # other weights


def test_rows_logged_after_the_last_checkpoint_are_not_logged_twice(tmp_path):
    train_bc(tiny_config(tmp_path, epochs=1))
    loss_log = tmp_path / "run" / "logs" / "bc" / "scalars" / "train" / "loss.csv"
    steps_one = [int(line.split(",")[0]) for line in loss_log.read_text().splitlines()]
    with loss_log.open("a") as log:  # the interrupted epoch 2 had logged a step before it stopped
        log.write(f"{steps_one[-1] + 1},123.0\n")
    train_bc(tiny_config(tmp_path, epochs=2))
    rows = [line.split(",") for line in loss_log.read_text().splitlines()]
    steps = [int(step) for step, _ in rows]
    assert steps == sorted(set(steps)) and steps[: len(steps_one)] == steps_one and len(steps) == 2 * len(steps_one)
    assert all(float(value) != 123.0 for _, value in rows)


def test_resume_refuses_another_model_type(tmp_path):
    train_bc(tiny_config(tmp_path, epochs=1, model="action_only"))
    from spf_rl.checkpoint import CheckpointError

    with pytest.raises(ValueError, match="model.name: 'action_only' -> 'spf'"):  # the run's config.json, first
        train_bc(dataclasses.replace(tiny_config(tmp_path, epochs=2, model="spf")))
    (tmp_path / "run" / "config.json").unlink()  # a run without its config: last.pt's header still refuses
    with pytest.raises(CheckpointError, match="'action_only' model, but a 'spf' model"):
        train_bc(dataclasses.replace(tiny_config(tmp_path, epochs=2, model="spf")))


def test_val_every_validates_some_epochs_and_picks_among_them(tmp_path):
    config = dataclasses.replace(tiny_config(tmp_path, epochs=3), val_every=2)
    results = train_bc(config)
    scored = [h["val_success"] is not None for h in results["history"]]
    assert scored == [False, True, True]  # epoch 2, then the last epoch
    assert results["best_epoch"] in (2, 3)
    with pytest.raises(ValueError, match="val_every"):
        dataclasses.replace(config, val_every=0)


def test_the_main_job_budget_is_stated_in_steps_and_episodes():
    config = BCConfig()
    steps = -(-config.data.num_episodes // config.optim.batch_size) * config.optim.epochs
    assert (config.data.num_episodes, steps) == (2000, 1500)
    assert config.val.num_episodes >= 300  # checkpoints are picked on at least 300 validation episodes


@pytest.mark.parametrize("model", ["spf", "rpf_original", "action_only", "spf_random"])
def test_padded_steps_are_not_encoded_and_change_no_valid_output(model, tmp_path):
    """``bc_loss`` encodes only the valid (``mask``-ed) steps: the loss and its gradients equal
    those of the full sequence, padded steps included."""
    from torch.nn import functional as F
    from torchrl.modules import set_recurrent_mode

    from spf_rl.modules.views import episodes_to_sequence

    dataset = EpisodeDataset.build(tmp_path / "data", DATA, num_workers=1, progress=False)
    batch = dataset[:8]
    trimmed = episodes_to_sequence(batch).get("mask")  # the time axis bc_loss sees
    assert not trimmed.all(), "the test needs padded steps"
    torch.manual_seed(0)
    policy = build_policy(model, spf_config(ModelConfig(name=model, sparsity=0.4, feature_dim=16, hidden_size=16), 5, 32))
    encoded: list[int] = []
    hook = policy.encoder.module.register_forward_pre_hook(lambda module, args: encoded.append(args[0].shape[0]))

    torch.manual_seed(1)  # spf_random draws its memory masks: the same draws for both passes
    loss, _ = bc_loss(policy, batch)
    hook.remove()
    assert encoded[0] == int(trimmed.sum())  # the agent's frames: the valid ones only (then the memory's, if any)
    loss.backward()
    masked_grads = [p.grad.clone() for p in policy.parameters() if p.grad is not None]
    policy.zero_grad()
    sequence = episodes_to_sequence(batch)
    torch.manual_seed(1)
    with set_recurrent_mode(True):
        full = policy(sequence)
    valid = full.get("mask")
    reference = F.cross_entropy(full.get("logits")[valid], full.get("expert_action")[valid])
    reference.backward()
    full_grads = [p.grad.clone() for p in policy.parameters() if p.grad is not None]
    torch.testing.assert_close(loss, reference)
    assert len(masked_grads) == len(full_grads)
    for masked, whole in zip(masked_grads, full_grads):
        torch.testing.assert_close(masked, whole)


def test_valid_steps_are_for_sequence_mode_only():
    policy = build_policy("spf", spf_config(ModelConfig(sparsity=0.4, feature_dim=16, hidden_size=16), 5, 32))
    from tensordict import TensorDict

    td = TensorDict({"pixels": torch.zeros(2, 32, 32, 3, dtype=torch.uint8)}, [2])
    with pytest.raises(ValueError, match="valid applies to recurrent"):
        policy(td, valid=torch.ones(2, dtype=torch.bool))


def test_valid_steps_must_be_a_prefix_along_time():
    from tensordict import TensorDict

    policy = build_policy("spf", spf_config(ModelConfig(sparsity=0.4, feature_dim=16, hidden_size=16), 5, 32))
    td = TensorDict({"pixels": torch.zeros(1, 3, 32, 32, 3, dtype=torch.uint8)}, [1, 3])
    with pytest.raises(ValueError, match="valid must be a prefix along time"):
        policy.encode_pixels(td, valid=torch.tensor([[True, False, True]]))
    with pytest.raises(ValueError, match="valid must have the batch shape"):
        policy.encode_pixels(td, valid=torch.ones(3, dtype=torch.bool))


ROUTES = DatasetConfig(episodes=EpisodeSpec(num_houses=1, demo_length=12, max_steps=None, image_size=16, route_style="driven", route_lengths=(10, 12)), num_episodes=8, chunk_size=8)


def _pointer_error(policy, batch) -> float:
    from torchrl.modules import set_recurrent_mode

    from spf_rl.modules.views import episodes_to_sequence
    from spf_rl.train.bc import pointer_loss

    sequence = episodes_to_sequence(batch)
    with torch.no_grad(), set_recurrent_mode(True):
        return float(pointer_loss(policy(sequence, valid=sequence.get("mask"))))


def test_the_pointer_loss_is_added_to_the_cross_entropy_and_holds_the_pointer_to_the_route(tmp_path):
    batch = EpisodeDataset.build(tmp_path / "data", ROUTES, num_workers=1, progress=False)[list(range(8))]
    model = ModelConfig(name="spf_random", pointer_update="rpf", feature_dim=16, hidden_size=16)
    torch.manual_seed(0)
    policy = build_policy("spf_random", spf_config(model, 12, 16))
    torch.manual_seed(1)  # the same memory masks for every pass
    plain, _ = bc_loss(policy, batch)
    torch.manual_seed(1)
    parts = {}
    with_pointer, _ = bc_loss(policy, batch, pointer_coef=0.5, parts=parts)
    torch.manual_seed(1)
    pointer = _pointer_error(policy, batch)
    assert with_pointer.item() == pytest.approx(plain.item() + 0.5 * pointer, rel=1e-5)
    assert parts == pytest.approx({"cross_entropy": plain.item(), "pointer": pointer}, rel=1e-5)

    errors = {}
    for coef in (0.0, 1.0):  # the same start, the same batches: only the pointer loss differs
        torch.manual_seed(0)
        policy = build_policy("spf_random", spf_config(model, 12, 16))
        optimizer = torch.optim.Adam(policy.parameters(), lr=3e-3)
        for _ in range(20):
            loss, _ = bc_loss(policy, batch, pointer_coef=coef)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
        torch.manual_seed(1)
        errors[coef] = _pointer_error(policy, batch)
    assert errors[1.0] < errors[0.0]


def test_the_pointer_loss_needs_route_step_labels(tmp_path):
    with pytest.raises(ValueError, match=r"optim.pointer_coef > 0 needs episodes of a route style .* set data.route_style"):
        BCConfig(optim=OptimConfig(pointer_coef=0.1))
    with pytest.raises(ValueError, match=r"optim.pointer_coef must be a finite number >= 0, got -1"):
        OptimConfig(pointer_coef=-1)
    batch = EpisodeDataset.build(tmp_path / "data", DATA, num_workers=1, progress=False)[:2]  # the planner's: no labels
    policy = build_policy("spf", spf_config(ModelConfig(sparsity=0.4, feature_dim=16, hidden_size=16), 5, 32))
    with pytest.raises(ValueError, match="pointer_coef > 0 needs 'route_step' in the episodes' steps"):
        bc_loss(policy, batch, pointer_coef=0.1)


def test_a_run_with_the_pointer_loss_logs_it_apart(tmp_path):
    config = dataclasses.replace(
        tiny_config(tmp_path, epochs=2, model="spf_random", data=ROUTES),
        model=ModelConfig(name="spf_random", pointer_update="rpf", feature_dim=16, hidden_size=16),
        optim=OptimConfig(batch_size=4, epochs=2, lr=3e-3, pointer_coef=0.1),
    )
    history = train_bc(config)["history"]
    assert all(record["train_pointer_loss"] > 0 for record in history)
    logged = tmp_path / "run" / "logs" / "bc" / "scalars"
    rows = (logged / "train" / "pointer_loss.csv").read_text().split()
    assert len(rows) == 4  # 8 episodes at batch 4, 2 epochs: a row per gradient step
    assert len((logged / "epoch" / "train_pointer_loss.csv").read_text().split()) == 2
    plain = train_bc(dataclasses.replace(config, output_dir=str(tmp_path / "plain"), optim=OptimConfig(batch_size=4, epochs=2)))
    assert all("train_pointer_loss" not in record for record in plain["history"])
