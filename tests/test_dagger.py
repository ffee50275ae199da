"""DAgger: the beta-mixed behaviour policy, rounds, aggregation, resume and errors."""
from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from envs.episode_spec import SIZE_FIELDS, EpisodeSpec
from spf_rl.checkpoint import load_checkpoint, save_checkpoint
from spf_rl.evaluation import EvalConfig
from spf_rl.modules import SPFConfig
from spf_rl.modules.registry import build_policy
from spf_rl.records_cache import from_columns, records_key, write_records
from spf_rl.train.collection import CollectionEnvConfig, CollectorConfig
from spf_rl.train.dagger import DAggerConfig, ExpertMixturePolicy, train_dagger
from spf_rl.train.dagger_rounds import RoundConfig, RoundError, RoundStore
from spf_rl.train.run import OptimConfig


def constant_learner(action: int) -> TensorDictModule:
    def logits(pixels):
        out = torch.zeros(pixels.shape[0], 3)
        out[:, action] = 1.0
        return out

    return TensorDictModule(logits, ["pixels"], ["logits"])


def mixing_input(count: int, expert: int = 2) -> TensorDict:
    return TensorDict(
        {
            "pixels": torch.zeros(count, 1),
            "expert_action": torch.full((count,), expert),
            "episode_seed": torch.arange(count)[:, None] * 7919,
            "step_count": (torch.arange(count)[:, None] % 50),
        },
        [count],
    )


def test_mixture_takes_the_expert_with_probability_beta():
    actions = ExpertMixturePolicy(constant_learner(0), beta=0.3)(mixing_input(4000))["action"]
    expert_share = (actions == 2).float().mean().item()
    assert abs(expert_share - 0.3) < 0.03
    assert set(actions.unique().tolist()) == {0, 2}


def test_mixture_coin_is_a_function_of_episode_and_step_only():
    td = mixing_input(64)
    policy = ExpertMixturePolicy(constant_learner(0), beta=0.5)
    actions = policy(td.clone())["action"]
    permutation = torch.randperm(64, generator=torch.Generator().manual_seed(0))
    permuted = policy(td[permutation].clone())["action"]
    assert torch.equal(permuted, actions[permutation])  # same coins whatever the batch order
    assert 0 < (actions == 2).sum() < 64


def test_mixture_refuses_bad_beta():
    with pytest.raises(ValueError, match="beta"):
        ExpertMixturePolicy(constant_learner(0), beta=1.5)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"beta0": -0.1}, "beta0"),
        ({"beta_decay": 2.0}, "beta_decay"),
        ({"rounds": -1}, "rounds"),
        ({"episodes_per_round": 0}, "episodes_per_round"),
        ({"steps_per_round": 0}, "steps_per_round"),
        ({"window_rounds": 0}, "window_rounds"),
        ({"rounds_share": 0.0}, "rounds_share"),
        ({"rounds_share": 1.0}, "rounds_share"),
        ({"rounds_share": True}, "rounds_share"),
        ({"rounds_share": "half"}, "rounds_share"),
        ({"rounds_share": 0.5, "aggregate_bc_data": False}, "rounds_share needs aggregate_bc_data"),
        ({"rounds_share": 0.5, "optim": OptimConfig(batch_size=1)}, "rounds_share needs optim.batch_size >= 2"),
    ],
)
def test_config_errors_name_the_parameter(kwargs, name):
    with pytest.raises(ValueError, match=name):
        DAggerConfig(**kwargs)


def test_retraining_batches_are_drawn_as_before_without_a_rounds_share():
    from spf_rl.train.dagger import retraining_order

    sizes, steps, batch = torch.tensor([37, 9, 11]), 13, 8
    order = retraining_order(sizes, steps, batch, torch.Generator().manual_seed(5))
    generator = torch.Generator().manual_seed(5)  # the draw every earlier run made: passes over all rows
    total = int(sizes.sum())
    passes = -(-steps * batch // total)
    before = torch.cat([torch.randperm(total, generator=generator) for _ in range(passes)])
    assert torch.equal(order, torch.stack([before[step * batch : (step + 1) * batch] for step in range(steps)]))


@pytest.mark.parametrize("share, from_rounds", [(0.5, 4), (0.25, 2), (0.01, 1), (0.99, 7)])
def test_a_rounds_share_fixes_each_batchs_part_of_round_episodes(share, from_rounds):
    from spf_rl.train.dagger import retraining_order

    sizes, steps, batch = torch.tensor([40, 6, 6]), 15, 8
    order = retraining_order(sizes, steps, batch, torch.Generator().manual_seed(1), rounds_share=share)
    assert order.shape == (steps, batch) and int(order.min()) >= 0 and int(order.max()) < 52
    assert (order >= 40).sum(1).tolist() == [from_rounds] * steps  # every batch: its share of the rounds
    # each part: passes without replacement over its rows (the batches that lie within a first pass repeat none)
    for rows, count, per_batch in ((order[order < 40], 40, batch - from_rounds), (order[order >= 40], 12, from_rounds)):
        first_pass = rows[: count // per_batch * per_batch].tolist()
        assert len(set(first_pass)) == len(first_pass) > 0
    again = retraining_order(sizes, steps, batch, torch.Generator().manual_seed(1), rounds_share=share)
    assert torch.equal(order, again)


def tiny_config(tmp_path, checkpoint, **overrides) -> DAggerConfig:
    env = overrides.pop("env", CollectionEnvConfig(episodes=EpisodeSpec(num_houses=1, demo_length=5, max_steps=6, image_size=32)))
    # val and test play episodes of the env's sizes and routes (the policy is built for them)
    sizes = {key: getattr(env.episodes, key) for key in SIZE_FIELDS}
    evaluation = dict(num_episodes=4, num_agents=4)
    base = dict(
        checkpoint=str(checkpoint),
        output_dir=str(tmp_path / "dagger"),
        device="cpu",  # the CPU suite everywhere; tests/test_device_cuda.py runs DAgger on CUDA
        rounds=2,
        episodes_per_round=4,
        beta0=0.5,
        steps_per_round=None,
        window_rounds=None,
        aggregate_bc_data=False,
        logger="csv",
        progress=False,
        env=env,
        collector=CollectorConfig(num_agents=2),
        val=EvalConfig(EpisodeSpec(split="val", seed=1, num_houses=1, **sizes), **evaluation),
        test=EvalConfig(EpisodeSpec(split="test", seed=2, num_houses=1, **sizes), **evaluation),
    )
    base.update(overrides)
    return DAggerConfig(**base)


def save_bc_checkpoint(directory: Path, make: bool = False) -> Path:
    if make:
        directory.mkdir(parents=True)
    torch.manual_seed(0)
    config = SPFConfig(demo_length=5, sparsity=0.4, feature_dim=8, hidden_size=8, image_size=(32, 32))
    policy = build_policy("spf", config)
    path = directory / "bc.pt"
    save_checkpoint(path, "spf", config, {"model": policy.state_dict()})
    return path


@pytest.fixture()
def bc_checkpoint(tmp_path):
    return save_bc_checkpoint(tmp_path)


# Runs shared by the module's tests, each made once in the test session (the ``shared_build`` fixture: by
# whichever pytest-xdist worker asks first). They start from one checkpoint file (a run's config names it: a
# resumed copy must start from the same file). Tests read them, never change them: a test that changes a run
# works on its own copy (copy_run). Their results are the runs' results.json.
@pytest.fixture(scope="session")
def shared_checkpoint(shared_build) -> Path:
    return shared_build("dagger-bc", lambda directory: save_bc_checkpoint(directory, make=True)) / "bc.pt"


def _shared_run(shared_build, name: str, config) -> tuple[Path, dict]:
    """``config(root)``'s run, made once: its root (of ``dagger/``) and results."""
    root = shared_build(name, lambda directory: train_dagger(config(directory)))
    return root, json.loads((root / "dagger" / "results.json").read_text())


@pytest.fixture(scope="session")
def two_rounds(shared_build, shared_checkpoint) -> tuple[Path, dict]:
    """``tiny_config``'s run (2 rounds): its directory (of ``dagger/``) and results."""
    return _shared_run(shared_build, "dagger-two-rounds", lambda root: tiny_config(root, shared_checkpoint))


@pytest.fixture(scope="session")
def one_round(shared_build, shared_checkpoint) -> Path:
    """The directory (of ``dagger/``) of ``tiny_config``'s run stopped after round 1."""
    return _shared_run(shared_build, "dagger-one-round", lambda root: tiny_config(root, shared_checkpoint, rounds=1))[0]


def _three_learner_driven_rounds(root: Path, checkpoint: Path) -> DAggerConfig:
    config = tiny_config(root, checkpoint, rounds=3, beta0=0.0, steps_per_round=3, window_rounds=2, test_every_round=False)
    config.optim.batch_size = 2
    return config


@pytest.fixture(scope="session")
def three_learner_driven_rounds(shared_build, shared_checkpoint) -> tuple[DAggerConfig, dict]:
    """Learner-driven rounds (beta 0) of 3 gradient steps on a window of 2 rounds, tested
    only at round 0 and after the last round: the config and results."""
    root, results = _shared_run(shared_build, "dagger-three-rounds", lambda root: _three_learner_driven_rounds(root, shared_checkpoint))
    return _three_learner_driven_rounds(root, shared_checkpoint), results


def copy_run(run: Path, to: Path) -> None:
    """A private copy of a shared run's ``dagger/`` directory under ``to``."""
    shutil.copytree(run / "dagger", to / "dagger")


def test_rounds_aggregate_retrain_and_report(two_rounds, shared_checkpoint):
    run, results = two_rounds
    output = run / "dagger"
    history = results["history"]
    assert [r["round"] for r in history] == [0, 1, 2]
    assert [r["beta"] for r in history] == [None, 0.5, 0.25]
    assert [r["training_episodes"] for r in history] == [0, 4, 8]
    assert [r.get("gradient_steps") for r in history] == [None, 1, 1]  # one pass of batch 16
    assert all("test_success" in r and 0.0 <= r["val_spl"] <= r["val_success"] + 1e-6 for r in history)
    written = json.loads((output / "results.json").read_text())
    assert written["best_round_by_val"] == results["best_round_by_val"] == results["best"]["round"]
    assert written["machine_this_run"]["cpu_count"] >= 1 and written["machine_this_run"]["cpu_model"]  # results depend on the CPU
    shipped = json.loads((output / "test_episodes.json").read_text())  # the best round's own test records
    successes = [float(ok) for ok in shipped["columns"]["success"]]
    assert shipped["round"] == results["best"]["round"] and sum(successes) / len(successes) == pytest.approx(results["best"]["test_success"])
    best_record = history[results["best"]["round"]]
    assert results["best"]["val_success"] == best_record["val_success"] and "test_success" in results["best"]
    assert (output / "dagger.png").stat().st_size > 0
    stored = RoundStore(output / "rounds" / "round-01")
    assert (stored.config.round_index, stored.config.beta, stored.config.episodes.max_steps) == (1, 0.5, 6)
    episodes = stored.episodes
    assert episodes.batch_size == torch.Size([4])
    assert episodes["steps", "is_init"][:, 0].all() and episodes["steps", "mask"][:, 0].all()
    # numbered episodes 0..3 of the round's seed, each referring to its demonstration in round-01-demos
    assert episodes["demo_id"].tolist() == [0, 1, 2, 3] and "demo_frames" not in episodes.keys()
    rows = stored[torch.tensor([2, 0])]
    assert torch.equal(rows["demo_frames"][0], stored.demos.frames[2]) and rows["demo_frames"].shape == (2, 5, 32, 32, 3)
    assert history[1]["episodes"] == 4 and history[1]["behaviour_success"] == episodes["success"].float().mean().item()
    # every stored state carries a valid expert label
    labels = episodes["steps", "expert_action"][episodes["steps", "mask"]]
    assert labels.numel() > 0 and labels.min() >= 0 and labels.max() <= 2
    # the learner changed, and its checkpoints load weights-only into the start's model type
    start = load_checkpoint(shared_checkpoint)["model"]
    last = load_checkpoint(output / "last.pt", expected_model_type="spf")
    assert last["round"] == 2
    assert any(not torch.equal(start[k], last["model"][k]) for k in start)
    best = load_checkpoint(output / "best.pt", expected_model_type="spf")
    build_policy("spf", best["model_config"]).load_state_dict(best["model"])


def test_expert_only_round_succeeds_in_every_episode(tmp_path, bc_checkpoint):
    """beta = 1 without noise: the expert drives every step of every (whole) episode, so each succeeds."""
    config = tiny_config(
        tmp_path, bc_checkpoint, rounds=1, beta0=1.0, episodes_per_round=8, env=CollectionEnvConfig(episodes=EpisodeSpec(num_houses=1, noise="none", demo_length=5, max_steps=12, image_size=32))
    )
    config.val = config.test = EvalConfig(episodes=EpisodeSpec(split="val", num_houses=1, demo_length=5, max_steps=12, image_size=32, seed=1), num_episodes=2, num_agents=2)
    round_one = train_dagger(config)["history"][1]
    assert round_one["episodes"] == 8 and round_one["behaviour_success"] == 1.0
    episodes = RoundStore(tmp_path / "dagger" / "rounds" / "round-01").episodes
    steps = episodes["steps"][episodes["steps", "mask"]]
    assert torch.equal(steps["action"], steps["expert_action"])
    assert round_one["mean_length"] == episodes["length"].float().mean().item() < 12


def test_a_round_is_the_same_whatever_the_collector_layout(tmp_path, bc_checkpoint):
    """Numbered episodes: 2 agents, 3 agents or 2 worker processes store the same round bytes."""
    def round_one(name: str, collector: CollectorConfig):
        train_dagger(tiny_config(tmp_path / name, bc_checkpoint, rounds=1, episodes_per_round=5, collector=collector))
        return RoundStore(tmp_path / name / "dagger" / "rounds" / "round-01").episodes

    first = round_one("a", CollectorConfig(num_agents=2))
    for name, layout in (("b", CollectorConfig(num_agents=3)), ("c", CollectorConfig(num_agents=2, num_collectors=2))):
        other = round_one(name, layout)
        assert all(torch.equal(first[key], other[key]) for key in first.keys(True, True)), name


def test_interrupted_run_resumes_to_the_same_result(tmp_path, two_rounds, one_round, shared_checkpoint):
    straight_run, straight = two_rounds
    copy_run(one_round, tmp_path / "b")  # "interrupted" after round 1
    round_one = (tmp_path / "b" / "dagger" / "rounds" / "round-01").stat().st_mtime_ns
    # an interruption after round 2's episodes were stored but before last.pt: they are reused
    for name in ("round-02-demos", "round-02"):
        shutil.copytree(straight_run / "dagger" / "rounds" / name, tmp_path / "b" / "dagger" / "rounds" / name)
    val_log = tmp_path / "b" / "dagger" / "logs" / "dagger" / "scalars" / "round" / "val_success.csv"
    with val_log.open("a") as log:  # round 2 was scored and logged, but last.pt did not hold it yet
        log.write("2,0.123\n")
    resumed = train_dagger(tiny_config(tmp_path / "b", shared_checkpoint))
    logged = [line.split(",") for line in val_log.read_text().splitlines()]
    assert [int(r) for r, _ in logged] == [0, 1, 2] and float(logged[2][1]) == resumed["history"][2]["val_success"]
    assert (tmp_path / "b" / "dagger" / "rounds" / "round-01").stat().st_mtime_ns == round_one  # not re-collected
    assert [r["round"] for r in resumed["history"]] == [0, 1, 2]
    a = load_checkpoint(straight_run / "dagger" / "last.pt")["model"]
    b = load_checkpoint(tmp_path / "b" / "dagger" / "last.pt")["model"]
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert straight["history"][2]["val_success"] == resumed["history"][2]["val_success"]


def test_a_run_moved_without_its_round_data_collects_its_rounds_again(tmp_path, two_rounds, one_round, shared_checkpoint):
    """On another machine with last.pt and learners/ but not the rounds' episodes, resuming collects
    the window's rounds again with the learners that collected them and ends where the
    uninterrupted run ends."""
    straight_run, straight = two_rounds
    copy_run(one_round, tmp_path / "b")
    run = tmp_path / "b" / "dagger"
    assert sorted(p.name for p in (run / "learners").iterdir()) == ["learner-00.pt", "learner-01.pt"]
    shutil.rmtree(run / "rounds")
    (run / "learners" / "learner-01.pt").unlink()  # as in a run begun before learners/: last.pt holds it
    resumed = train_dagger(tiny_config(tmp_path / "b", shared_checkpoint))
    kept = load_checkpoint(run / "learners" / "learner-01.pt")["model"]
    after_one = load_checkpoint(one_round / "dagger" / "last.pt")["model"]
    assert all(torch.equal(kept[k], after_one[k]) for k in after_one)
    for name in ("round-01", "round-02"):
        again = RoundStore(run / "rounds" / name).episodes
        original = RoundStore(straight_run / "dagger" / "rounds" / name).episodes
        assert again.batch_size == original.batch_size and (again == original).all()
    a = load_checkpoint(straight_run / "dagger" / "last.pt")["model"]
    b = load_checkpoint(run / "last.pt")["model"]
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert [r["val_success"] for r in resumed["history"]] == [r["val_success"] for r in straight["history"]]


def test_a_resumed_run_needs_only_its_own_state(tmp_path):
    """last.pt and learners/ are the whole resume state: the starting checkpoint and the rounds'
    episodes may be gone (a run moved to another machine without them)."""
    start = save_bc_checkpoint(tmp_path)
    train_dagger(tiny_config(tmp_path, start, rounds=1))
    start.unlink()
    shutil.rmtree(tmp_path / "dagger" / "rounds")
    resumed = train_dagger(tiny_config(tmp_path, start))
    assert [r["round"] for r in resumed["history"]] == [0, 1, 2]
    with pytest.raises(FileNotFoundError):  # a new run does need it
        train_dagger(tiny_config(tmp_path / "new", start))


def test_a_finished_run_resumed_writes_its_results_without_collecting_its_window_again(tmp_path, three_learner_driven_rounds):
    """A run resumed with no round left to train (its rounds reached, or rounds=N lowered to where it stopped) only
    writes its results: the window's episodes, gone, are not collected again."""
    config, results = three_learner_driven_rounds
    copy_run(Path(config.output_dir).parent, tmp_path)
    shutil.rmtree(tmp_path / "dagger" / "rounds")
    (tmp_path / "dagger" / "results.json").unlink()
    again = train_dagger(dataclasses.replace(config, output_dir=str(tmp_path / "dagger")))
    assert not list((tmp_path / "dagger" / "rounds").glob("round-*"))  # nothing collected
    assert [r["val_success"] for r in again["history"]] == [r["val_success"] for r in results["history"]]
    assert json.loads((tmp_path / "dagger" / "results.json").read_text())["best"]["round"] == results["best"]["round"]


def test_learners_are_kept_for_the_window_only(three_learner_driven_rounds):
    config, _ = three_learner_driven_rounds  # window of 2 rounds, after round 3: rounds 2 and 3 need learners 1 and 2
    learners = sorted(p.name for p in (Path(config.output_dir) / "learners").iterdir())
    assert learners == ["learner-01.pt", "learner-02.pt", "learner-03.pt"]


def test_a_stored_round_of_another_run_or_corrupt_is_refused(tmp_path, one_round, shared_checkpoint):
    """Resuming never trains on a round collected by another config, or on damaged bytes."""
    copy_run(one_round, tmp_path / "a")
    other = tiny_config(tmp_path / "b", shared_checkpoint, rounds=1, seed=1)
    (tmp_path / "b" / "dagger" / "rounds").mkdir(parents=True)
    shutil.copytree(tmp_path / "a" / "dagger" / "rounds" / "round-01", tmp_path / "b" / "dagger" / "rounds" / "round-01")
    with pytest.raises(RoundError, match="belongs to another run"):
        train_dagger(other)

    (tmp_path / "a" / "dagger" / "last.pt").unlink()  # as if interrupted after storing round 1
    pixels = tmp_path / "a" / "dagger" / "rounds" / "round-01" / "data" / "steps" / "pixels.memmap"
    damaged = bytearray(pixels.read_bytes())
    damaged[0] ^= 0xFF
    pixels.write_bytes(bytes(damaged))
    with pytest.raises(RoundError, match="checksum mismatch"):
        train_dagger(tiny_config(tmp_path / "a", shared_checkpoint, rounds=1))


def test_a_round_of_an_older_layout_or_without_its_demonstrations_is_refused(tmp_path, one_round, shared_checkpoint):
    copy_run(one_round, tmp_path)
    round_dir = tmp_path / "dagger" / "rounds" / "round-01"
    (tmp_path / "dagger" / "last.pt").unlink()  # as if interrupted after storing round 1
    shutil.rmtree(round_dir.with_name("round-01-demos"))
    with pytest.raises(RoundError, match="round-01-demos are missing"):
        train_dagger(tiny_config(tmp_path, shared_checkpoint, rounds=1))
    meta = json.loads((round_dir / "meta.json").read_text())
    meta["format_version"] = 1
    (round_dir / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(RoundError, match="version 1 stored every episode's demonstration frames"):
        RoundStore(round_dir)


def test_round_store_refuses_a_wrong_count_and_bad_configs(tmp_path):
    from spf_rl.data import DatasetConfig, EpisodeDataset

    config = RoundConfig(episodes=EpisodeSpec(demo_length=4, max_steps=5, image_size=8, seed=3), round_index=1, beta=0.0, num_episodes=2)
    three = EpisodeDataset.empty(DatasetConfig(episodes=EpisodeSpec(demo_length=4, max_steps=5, image_size=8), num_episodes=3))
    with pytest.raises(ValueError, match=r"batch size \[2\]"):
        RoundStore.write(tmp_path / "round-01", config, three)
    assert not (tmp_path / "round-01").exists()
    with pytest.raises(ValueError, match="beta must be in"):
        RoundConfig(episodes=EpisodeSpec(demo_length=4, max_steps=5, image_size=8, seed=3), round_index=1, beta=1.5, num_episodes=2)
    with pytest.raises(ValueError, match="round_index"):
        RoundConfig(episodes=EpisodeSpec(demo_length=4, max_steps=5, image_size=8, seed=3), round_index=0, beta=0.0, num_episodes=2)


def test_checkpoint_of_other_sizes_is_refused(tmp_path, bc_checkpoint):
    config = tiny_config(tmp_path, bc_checkpoint, env=CollectionEnvConfig(episodes=EpisodeSpec(num_houses=1, demo_length=6, max_steps=6, image_size=32)))
    with pytest.raises(ValueError, match=r"env.demo_length / env.image_size \(6, 32\) must match the checkpoint's"):
        train_dagger(config)


def test_recipe_configs_load_and_refuse_unknown_keys():

    from spf_rl.config import load_config

    default = load_config(DAggerConfig, "dagger", [])
    quick = load_config(DAggerConfig, "dagger", ["collector.backend=ray"], preset="dagger_quick")
    assert default.checkpoint == "spf-s0.8" and default.rounds >= 10
    assert default.beta0 == 0.0 and default.steps_per_round and default.window_rounds  # learner-driven, windowed
    control = load_config(DAggerConfig, "dagger", [], preset="dagger_control")
    assert control.beta(1) == control.beta(10) == 1.0 and control.steps_per_round == default.steps_per_round
    assert quick.episodes_per_round < default.episodes_per_round and quick.collector.backend == "ray"
    with pytest.raises(ValueError, match="collector"):
        load_config(DAggerConfig, "dagger", ["collector.backend=slurm"])
    with pytest.raises(ValueError):
        load_config(DAggerConfig, "dagger", ["no_such_key=1"])


def test_learner_driven_rounds_train_fixed_steps_on_a_sliding_window(three_learner_driven_rounds):
    history = three_learner_driven_rounds[1]["history"]
    assert [r["beta"] for r in history] == [None, 0.0, 0.0, 0.0]
    assert [r.get("gradient_steps") for r in history] == [None, 3, 3, 3]
    assert [r["training_episodes"] for r in history] == [0, 4, 8, 8]  # round 3 trains on rounds 2 and 3


def test_resuming_without_the_round_data_names_what_is_missing(tmp_path):
    from spf_rl.data import DatasetConfig, EpisodeDataset
    from spf_rl.train.dagger_rounds import training_sources

    config = RoundConfig(episodes=EpisodeSpec(demo_length=4, max_steps=5, image_size=8, seed=3), round_index=1, beta=0.0, num_episodes=2)
    episodes = EpisodeDataset.empty(DatasetConfig(episodes=EpisodeSpec(demo_length=4, max_steps=5, image_size=8), num_episodes=2))
    RoundStore.write(tmp_path / "rounds" / "round-01", config, episodes)
    (tmp_path / "rounds" / "round-03").mkdir()  # a round directory without meta.json is incomplete
    with pytest.raises(FileNotFoundError, match="round-02 is missing or incomplete"):
        training_sources(None, tmp_path, round_index=3, window=4)
    assert len(training_sources(None, tmp_path, round_index=1, window=4)) == 1


def test_the_best_round_is_tested_from_best_pt(three_learner_driven_rounds):
    """Without a test after every round, the run still tests the checkpoint it ships (best.pt)."""
    from spf_rl.evaluation import evaluate_policy

    config, results = three_learner_driven_rounds
    assert [("test_success" in r) for r in results["history"]] == [True, False, False, True]
    best = load_checkpoint(Path(config.output_dir) / "best.pt", expected_model_type="spf")
    assert best["round"] == results["best"]["round"]
    policy = build_policy("spf", best["model_config"])
    policy.load_state_dict(best["model"])
    summary, records = evaluate_policy(policy, config.test)
    assert results["best"]["test_success"] == summary["success"] and results["best"]["test_spl"] == summary["spl"]
    shipped = json.loads((Path(config.output_dir) / "test_episodes.json").read_text())  # for recipes/paired.py
    assert shipped["round"] == best["round"] and from_columns(shipped["columns"]) == json.loads(json.dumps(records, default=str))
    assert shipped["key"] == records_key(config.test, policy)  # of the best round's weights


def test_round_0_reuses_the_start_checkpoints_own_test_records(tmp_path, monkeypatch):
    """A start checkpoint with its BC run's test records beside it (the same file, the same episodes) is not
    tested again at round 0; records of other episodes are not reused."""
    import dataclasses

    import spf_rl.train.dagger as dagger_module
    from spf_rl.evaluation import evaluate_policy

    start = save_bc_checkpoint(tmp_path)
    config = tiny_config(tmp_path, start, rounds=0)
    test_config = config.test  # of the env's sizes
    policy = build_policy("spf", load_checkpoint(start)["model_config"])
    policy.load_state_dict(load_checkpoint(start)["model"])
    summary, records = evaluate_policy(policy, test_config)
    write_records(tmp_path / "test_episodes.json", records_key(test_config, policy), records)
    played = []
    monkeypatch.setattr(dagger_module, "evaluate_policy", lambda p, c, progress=False: played.append(c) or evaluate_policy(p, c))

    results = train_dagger(config)
    assert [c.episodes.split for c in played] == ["val"]  # round 0's test came from the file
    assert (results["start"]["test_success"], results["start"]["test_spl"]) == (summary["success"], summary["spl"])
    shipped = json.loads((Path(config.output_dir) / "test_episodes.json").read_text())
    assert shipped["round"] == 0 and from_columns(shipped["columns"]) == json.loads(json.dumps(records, default=str))

    other = dataclasses.replace(test_config, episodes=test_config.episodes.replace(seed=9))  # records of other episodes: played again
    write_records(tmp_path / "test_episodes.json", records_key(other, policy), records)
    played.clear()
    train_dagger(dataclasses.replace(config, output_dir=str(tmp_path / "again")))
    assert [c.episodes.split for c in played] == ["val", "test"]


def test_random_sparsity_rounds_do_not_depend_on_the_global_rng(tmp_path):
    # a model that draws a memory sparsity per training episode: its draws come from the round
    # and step, not from whatever the process did before (a dataset built or loaded, a resume)
    torch.manual_seed(0)
    config = SPFConfig(demo_length=5, sparsity=0.4, sparsity_range=(0.2, 1.0), feature_dim=8, hidden_size=8, image_size=(32, 32))
    checkpoint = tmp_path / "random.pt"
    save_checkpoint(checkpoint, "spf_random", config, {"model": build_policy("spf_random", config).state_dict()})
    train_dagger(tiny_config(tmp_path / "a", checkpoint))
    train_dagger(tiny_config(tmp_path / "b", checkpoint, rounds=1))  # "interrupted" after round 1
    torch.rand(1000)  # other work in the process
    train_dagger(tiny_config(tmp_path / "b", checkpoint))
    a = load_checkpoint(tmp_path / "a" / "dagger" / "last.pt")["model"]
    b = load_checkpoint(tmp_path / "b" / "dagger" / "last.pt")["model"]
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_a_run_grows_an_anchor_and_a_replay_gate_and_trains_them_on_changed_worlds_and_mismatched_memories(tmp_path, monkeypatch):
    """DAgger from a checkpoint without an anchor, ``anchor_radius`` and ``replay_gate`` set: rounds of a route
    style (the pointer and anchor labels) repeated under a condition with mismatched memories, retrained beside
    BC data of the teaching world (every batch half of each, ``rounds_share``: it mixes the two layouts); the
    kept weights anchor and gate, and the gate trained."""
    from spf_rl.data import DatasetConfig

    torch.manual_seed(0)
    config = SPFConfig(demo_length=12, feature_dim=8, hidden_size=8, image_size=(32, 32), pointer_update="rpf", sparsity_range=(0.2, 1.0))
    start = build_policy("spf_random", config)
    save_checkpoint(tmp_path / "start.pt", "spf_random", config, {"model": start.state_dict()})
    episodes = EpisodeSpec(num_houses=1, demo_length=12, max_steps=None, image_size=32, route_style="driven", route_lengths=(10, 12),
                           conditions="light@0.5=1,none=1", memory_mismatch=0.5)
    bc_data = DatasetConfig(episodes=episodes.replace(conditions=None, memory_mismatch=None), num_episodes=4, chunk_size=4, num_agents=4)
    run = tiny_config(tmp_path, tmp_path / "start.pt", rounds=1, anchor_radius=3, env=CollectionEnvConfig(episodes=episodes),
                      optim=OptimConfig(lr=3e-4, cosine_schedule=False, pointer_coef=0.1, batch_size=8, replay_gate_coef=0.5),
                      aggregate_bc_data=True, bc_data=bc_data, bc_data_dir=str(tmp_path / "bc"), num_workers=1,
                      rounds_share=0.5, replay_gate=True)
    from spf_rl.train import dagger as dagger_module

    orders = []

    def recorded(sizes, steps, batch_size, generator, rounds_share=None):
        order = real_order(sizes, steps, batch_size, generator, rounds_share)
        orders.append((sizes.tolist(), rounds_share, order))
        return order

    real_order = dagger_module.retraining_order
    monkeypatch.setattr(dagger_module, "retraining_order", recorded)
    results = train_dagger(run)
    assert json.loads((tmp_path / "dagger" / "config.json").read_text())["rounds_share"] == 0.5
    (sizes, share, order), = orders  # one round: its batches drew half from the round's episodes
    assert sizes[0] == 4 and len(sizes) == 2 and share == 0.5
    assert (order >= 4).sum(1).tolist() == [4] * len(order)
    kept = load_checkpoint(tmp_path / "dagger" / "best.pt")
    last = load_checkpoint(tmp_path / "dagger" / "last.pt")
    assert kept["model_config"].anchor_radius == 3 and last["model_config"].anchor_radius == 3
    assert kept["model_config"].replay_gate and last["model_config"].replay_gate
    assert any(key.startswith("cell.anchor_gate") for key in last["model"])
    assert not torch.equal(last["model"]["cell.replay_gate.weight"], torch.zeros_like(last["model"]["cell.replay_gate.weight"]))
    assert results["history"][-1]["train_pointer_loss"] > 0 and results["history"][-1]["train_replay_gate_loss"] > 0
    shipped = {key: value for key, value in last["model"].items() if "anchor" not in key and "replay_gate" not in key}
    assert any(not torch.equal(value, start.state_dict()[key]) for key, value in shipped.items())  # trained on
