"""The device option on the CPU: resolving and refusing device settings, and the device
plumbing of batches, policies, collectors, evaluation and checkpoints, with the ``meta``
device standing in for a GPU (a test on ``cpu`` could not fail: everything starts
there). Also bf16 autocast (``amp``) on the CPU: step and sequence mode agree within
the stated tolerance. The CUDA tests are in ``tests/test_device_cuda.py``."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn
from torchrl.modules import set_recurrent_mode

from envs.episode_spec import SIZE_FIELDS, EpisodeSpec
from spf_rl.checkpoint import load_checkpoint, save_checkpoint
from spf_rl.config import load_config
from spf_rl.data import DatasetConfig, empty_training_episodes
from spf_rl.device import AMP_DTYPE, autocast, exact_float32, resolve_device, to_device
from spf_rl.evaluation import EvalConfig, evaluate_policy
from spf_rl.hub import policy_from_checkpoint
from spf_rl.modules import SPFConfig
from spf_rl.modules.registry import build_policy
from spf_rl.modules.views import episodes_to_sequence
from spf_rl.train import collection, dagger, ppo
from spf_rl.train.bc import BCConfig, bc_loss, default_test_config, train_bc
from spf_rl.train.collection import (
    CollectionEnvConfig,
    CollectorConfig,
    collection_device,
    make_collection_env,
    make_collector,
)
from spf_rl.train.dagger import DAggerConfig, train_dagger
from spf_rl.train.ppo import train_ppo
from spf_rl.train.ppo_config import PPOConfig
from spf_rl.train.ppo_loss import AMP_RATIO_SYNC_TOLERANCE, Autocast, make_ppo_modules, recompute_log_prob

META = torch.device("meta")
POLICY = SPFConfig(demo_length=5, sparsity=0.4, feature_dim=16, hidden_size=16, image_size=(32, 32))
ENV = CollectionEnvConfig(episodes=EpisodeSpec(num_houses=1, demo_length=5, max_steps=6, image_size=32), with_expert=False)
ALLOWED = r"must be one of 'auto', 'cpu', 'cuda' or 'cuda:N'"
#: bf16 autocast: step-mode and sequence-mode logits agree within this fraction of the
#: largest |logit| (bf16 keeps 8 mantissa bits, ~0.4% per rounding, and the error grows
#: with the logits' scale; measured: 0.082 at max |logit| 5.5 on spf-s0.8) ...
AMP_LOGIT_RELATIVE_TOLERANCE = 2e-2
#: ... or, where bf16 itself moves the logits further, within this multiple of that move
#: (its largest |bf16 - float32| gap in sequence mode). On 20 random sequences of 3 x 12
#: steps for spf-s0.8, measured on an H200 and on CPUs, the step/sequence gap stayed within
#: 1.3x of bf16's own move; that move reached 6.4% of the largest |logit| (seed 0 below).
AMP_SHIFT_FACTOR = 1.5
#: bf16 sequence-mode logits stay within this fraction of the largest |logit| of float32's
#: (the 6.4% above is the largest move measured).
AMP_SHIFT_RELATIVE_BOUND = 8e-2


def assert_amp_agreement(step16: torch.Tensor, whole16: torch.Tensor, whole32: torch.Tensor) -> None:
    """Under bf16 autocast: step mode agrees with sequence mode as closely as bf16 agrees with
    float32, or within ``AMP_LOGIT_RELATIVE_TOLERANCE``, and bf16 stays near float32."""
    scale = max(1.0, float(whole32.abs().max()))
    shift = float((whole16 - whole32).abs().max())
    assert shift <= AMP_SHIFT_RELATIVE_BOUND * scale, f"bf16 moved the logits by {shift:.3f} at scale {scale:.2f}"
    atol = max(AMP_LOGIT_RELATIVE_TOLERANCE * scale, AMP_SHIFT_FACTOR * shift)
    torch.testing.assert_close(step16, whole16, rtol=0.0, atol=atol)
no_cuda = pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on a machine without CUDA")


def sized_like(evaluation: EvalConfig, env: CollectionEnvConfig) -> EvalConfig:
    """``evaluation`` on episodes of ``env``'s sizes and routes (a policy is evaluated on the episodes it is built for)."""
    sizes = {key: getattr(env.episodes, key) for key in SIZE_FIELDS}
    return dataclasses.replace(evaluation, episodes=evaluation.episodes.replace(**sizes))


def leaf_devices(tensordict: TensorDictBase) -> set[str]:
    return {leaf.device.type for leaf in tensordict.values(include_nested=True, leaves_only=True)}


def module_devices(*modules: nn.Module) -> set[str]:
    return {t.device.type for module in modules for t in [*module.parameters(), *module.buffers()]}


@pytest.fixture
def checkpoint(tmp_path) -> Path:
    torch.manual_seed(0)
    path = tmp_path / "start.pt"
    save_checkpoint(path, "spf", POLICY, {"model": build_policy("spf", POLICY).state_dict()})
    return path


# ---------------------------------------------------------------------- resolving
def test_auto_is_cuda_where_available_else_cpu(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == torch.device("cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto") == torch.device("cuda")
    assert resolve_device("cpu") == torch.device("cpu")


@pytest.mark.parametrize("value", ["gpu", "CPU", "cuda:", "cuda:x", "cuda0", "", "mps"])
def test_bad_values_name_the_parameter_and_the_allowed_values(value):
    with pytest.raises(ValueError, match=f"device {ALLOWED}"):
        resolve_device(value)
    with pytest.raises(ValueError, match=f"--device {ALLOWED}"):
        resolve_device(value, name="--device")


def test_cuda_is_refused_where_there_is_none(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match=r"device='cuda:1' needs CUDA.*Use device=cpu"):
        resolve_device("cuda:1")


def test_auto_stays_on_the_cpu_for_ray_collection(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert collection_device("auto", CollectorConfig(backend="ray")) == torch.device("cpu")  # CPU-only actors
    assert collection_device("auto", CollectorConfig()) == torch.device("cuda")
    assert collection_device("cuda", CollectorConfig(backend="ray")) == torch.device("cuda")  # refused later, clearly


def test_full_float32_on_cuda_unless_amp(tf32_flags):
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = True
    with exact_float32("cuda"):
        assert not torch.backends.cudnn.allow_tf32 and not torch.backends.cuda.matmul.allow_tf32
    with exact_float32("cuda", enabled=False), exact_float32("cpu"):
        assert torch.backends.cudnn.allow_tf32 and torch.backends.cuda.matmul.allow_tf32
    assert torch.backends.cudnn.allow_tf32 and torch.backends.cuda.matmul.allow_tf32  # restored


@pytest.mark.parametrize("schema, name", [(BCConfig, "bc"), (DAggerConfig, "dagger"), (PPOConfig, "ppo")])
def test_recipe_configs_take_and_check_device(schema, name):
    assert load_config(schema, name, []).device == "auto"
    assert load_config(schema, name, ["device=cuda:1"]).device == "cuda:1"  # spelling only: resolved at the start
    with pytest.raises(ValueError, match=f"device {ALLOWED}.*'gpu'"):
        load_config(schema, name, ["device=gpu"])


def test_training_refuses_a_missing_gpu_before_any_work(tmp_path, checkpoint, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    runs = tmp_path / "runs"
    with pytest.raises(ValueError, match="needs CUDA"):
        train_bc(BCConfig(device="cuda", output_dir=str(runs / "bc"), data_dir=str(runs / "data")))
    with pytest.raises(ValueError, match="needs CUDA"):
        train_dagger(DAggerConfig(device="cuda", checkpoint=str(checkpoint), output_dir=str(runs / "dagger")))
    with pytest.raises(ValueError, match="needs CUDA"):
        train_ppo(PPOConfig(device="cuda", checkpoint=str(checkpoint), output_dir=str(runs / "ppo")))
    assert not runs.exists()  # nothing was written: no output directory, no dataset


@no_cuda
def test_recipes_with_device_cuda_fail_clearly_here(tmp_path, capsys):
    import bench_train
    import evaluate

    data = tmp_path / "bench-data"
    with pytest.raises(SystemExit) as exit_info:
        bench_train.main(["--device", "cuda", "--data-dir", str(data), "--quick"])
    assert exit_info.value.code == 2 and not data.exists()
    assert "--device='cuda' needs CUDA" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        evaluate.main(["open_loop", "--device", "cuda:0", "--out", str(tmp_path / "eval")])
    assert "--device='cuda:0' needs CUDA" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        evaluate.main(["open_loop", "--device", "tpu", "--out", str(tmp_path / "eval")])
    assert "--device must be one of" in capsys.readouterr().err


# ---------------------------------------------------------------------- plumbing (meta stands in for a GPU)
def test_every_leaf_of_a_training_batch_lands_on_the_device():
    episodes = empty_training_episodes(DatasetConfig(episodes=EpisodeSpec(demo_length=5, max_steps=6, image_size=32), num_episodes=3))
    episodes["steps", "mask"][:, :4] = True
    sequence = episodes_to_sequence(episodes, META)
    assert sequence.batch_size == (3, 4) and sequence.device == META
    assert set(sequence.keys()) >= {"pixels", "demo_frames", "demo_actions", "is_init", "expert_action", "mask"}
    assert leaf_devices(sequence) == {"meta"}
    # the demonstration moved once per episode and is broadcast over time (a view, no copy)
    assert sequence["demo_frames"].stride(1) == 0 and sequence["demo_actions"].stride(1) == 0
    assert leaf_devices(to_device(episodes, META)) == {"meta"}


def test_policy_weights_and_recurrent_state_land_on_the_device():
    for model_type, config in (("spf", POLICY), ("spf_random", dataclasses.replace(POLICY, sparsity_range=(0.2, 1.0)))):
        policy = build_policy(model_type, config).to(META)
        actor, critic = make_ppo_modules(policy)
        critic.to(META)
        assert module_devices(policy, actor, critic) == {"meta"}  # buffers too (the memory slot indices)
        # the recurrent state is made by the primer in the env (on the CPU) and travels with each step
        env = make_collection_env(ENV, num_agents=2, primer=policy.make_tensordict_primer())
        state = env.reset().select(*policy.in_keys)
        env.close()
        assert {"spf_hidden", "eta", "memory_features"} <= set(state.keys()) and leaf_devices(state) == {"cpu"}
        assert leaf_devices(to_device(state, META)) == {"meta"}


class RecordingPolicy(TensorDictModuleBase):
    """Reads what an SPF policy reads, records the devices of its inputs, answers on the CPU."""

    def __init__(self, policy) -> None:
        super().__init__()
        self.in_keys, self.out_keys = list(policy.in_keys), ["logits", ("next", "spf_hidden")]
        self.make_tensordict_primer = policy.make_tensordict_primer
        self.weight = nn.Parameter(torch.zeros(1, device=META))
        self.seen: list[tuple[set, set]] = []

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        self.seen.append((set(tensordict.keys(True, True)), leaf_devices(tensordict)))
        n = tensordict.shape[0]
        return TensorDict({"logits": torch.zeros(n, 3), ("next", "spf_hidden"): torch.zeros(n, 16)}, [n])


def test_evaluation_steps_the_env_on_the_cpu_and_the_policy_on_its_device():
    recorder = RecordingPolicy(build_policy("spf", POLICY))
    config = EvalConfig(episodes=EpisodeSpec(split="val", num_houses=1, demo_length=5, max_steps=3, image_size=32, seed=1234), num_episodes=2, num_agents=2)
    summary, records = evaluate_policy(recorder, config)
    assert summary["episodes"] == 2 and recorder.seen
    for keys, devices in recorder.seen:
        assert {"pixels", "demo_frames", "spf_hidden", "eta", "memory_features"} <= keys
        assert devices == {"meta"}


def test_collectors_get_the_policy_on_the_device_and_the_envs_on_the_cpu(monkeypatch):
    calls = []

    class RecordingCollector:
        def __init__(self, *args, **kwargs):
            calls.append(kwargs)

        def set_seed(self, seed):
            pass

        def reset(self):
            pass

    monkeypatch.setattr(collection, "Collector", RecordingCollector)
    policy = build_policy("spf", POLICY).to(META)
    for layout in (CollectorConfig(num_agents=2), CollectorConfig(num_agents=2, num_collectors=2)):
        make_collector(policy, ENV, layout, frames_per_batch=12, device=META)
        make_collector(policy, ENV, layout, frames_per_batch=12, device=META, storing_device="cpu")
    for index, kwargs in enumerate(calls):
        assert kwargs["policy_device"] == META and kwargs["env_device"] == torch.device("cpu")
        assert kwargs["storing_device"] == (META if index % 2 == 0 else torch.device("cpu"))
    with pytest.raises(ValueError, match="CPU-only Ray actors.*device=cpu"):
        make_collector(policy, ENV, CollectorConfig(backend="ray"), frames_per_batch=8, device=META)


class Stop(Exception):
    pass


def test_dagger_collects_with_the_learner_on_its_device_into_cpu_storage(tmp_path, monkeypatch):
    captured = {}

    def recording_make_collector(policy, env, layout, **kwargs):
        captured.update(kwargs, policy=policy)
        raise Stop

    monkeypatch.setattr(dagger, "make_collector", recording_make_collector)
    from spf_rl.train.dagger_rounds import RoundConfig

    learner = build_policy("spf", POLICY).to(META)
    config = DAggerConfig(
        checkpoint="unused.pt", output_dir=str(tmp_path), env=ENV, collector=CollectorConfig(num_agents=2),
        episodes_per_round=2, val=sized_like(dagger.default_dagger_val_config(), ENV),
        test=sized_like(default_test_config(), ENV),
    )
    round_config = RoundConfig(episodes=EpisodeSpec(num_houses=1, demo_length=5, max_steps=6, image_size=32, seed=0), round_index=1, beta=0.5, num_episodes=2)
    with pytest.raises(Stop):
        dagger._collect_round(learner, config, round_config, tmp_path / "round-01")
    assert captured["device"] == META and captured["storing_device"] == "cpu"
    assert captured["demo_store"] == tmp_path / "round-01-demos"  # the round's episodes, drawn from its store
    assert module_devices(captured["policy"]) == {"meta"}


def test_ppo_puts_policy_value_head_reference_and_collector_on_the_device(tmp_path, checkpoint, monkeypatch):
    losses, collectors = [], []

    class RecordingLoss(nn.Module):
        def __init__(self, actor, critic, **kwargs):
            super().__init__()
            losses.append(kwargs)

    def recording_make_collector(policy, env, layout, **kwargs):
        collectors.append(dict(kwargs, policy=policy))
        raise Stop

    monkeypatch.setattr(ppo, "SPFPPOLoss", RecordingLoss)  # TorchRL's loss cannot be built on meta
    monkeypatch.setattr(ppo, "make_collector", recording_make_collector)
    env = CollectionEnvConfig(episodes=EpisodeSpec(num_houses=1, demo_length=5, max_steps=6, image_size=32), with_expert=False)
    defaults = PPOConfig()
    config = PPOConfig(
        checkpoint=str(checkpoint), output_dir=str(tmp_path / "run"), frames_per_batch=12, total_frames=12,
        minibatch_rows=1, kl_coef=0.1, store_demos=4, collector=CollectorConfig(num_agents=2),
        env=env, val=sized_like(defaults.val, env), test=sized_like(defaults.test, env),
    )
    config.device = META
    run = ppo._PPORun(config)
    assert module_devices(run.policy, run.actor, run.critic, run.reference) == {"meta"}
    assert losses[0]["device"] == META
    optimised = [p for opt in run.loop.optimizers.values() for group in opt.param_groups for p in group["params"]]
    assert {p.device.type for p in optimised} == {"meta"}
    with pytest.raises(Stop):
        run._train(None)
    assert collectors[0]["device"] == META and module_devices(collectors[0]["policy"]) == {"meta"}


def test_checkpoints_load_onto_any_device(checkpoint):
    payload = load_checkpoint(checkpoint, map_location=META)
    assert {t.device.type for t in payload["model"].values()} == {"meta"}
    policy, _ = policy_from_checkpoint(checkpoint, device=META)
    assert module_devices(policy) == {"meta"} and not policy.training
    # saved from CPU copies: the file holds CPU tensors whatever the device of the run
    raw = torch.load(checkpoint, map_location=None, weights_only=True)
    assert {t.device.type for t in raw["model"].values()} == {"cpu"}


# ---------------------------------------------------------------------- mixed precision (bf16 autocast on the CPU)
def random_sequence(config: SPFConfig, rows: int, steps: int, restart_at: int) -> TensorDict:
    n, size = config.demo_length, config.image_size[0]
    demo = torch.randint(0, 256, (rows, n, size, size, 3), dtype=torch.uint8)
    actions = torch.randint(0, config.num_actions, (rows, n))
    is_init = torch.zeros(rows, steps, 1, dtype=torch.bool)
    is_init[:, 0] = True
    is_init[0, restart_at] = True  # a second episode starts mid-row
    return TensorDict(
        {
            "pixels": torch.randint(0, 256, (rows, steps, size, size, 3), dtype=torch.uint8),
            "demo_frames": demo[:, None].expand(rows, steps, *demo.shape[1:]),
            "demo_actions": actions[:, None].expand(rows, steps, n),
            "is_init": is_init,
        },
        [rows, steps],
    )


def step_and_sequence_logits(policy, sequence: TensorDict, amp: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Logits of sequence mode, and of step mode carrying the state (stored as float32, as the env does),
    on the device of ``policy`` (``sequence`` is moved there)."""
    device = next(policy.parameters()).device
    sequence = to_device(sequence, device)
    state_keys = [key for key in policy.in_keys if key in ("spf_hidden", "eta", "memory_features")]
    with torch.no_grad(), autocast(device, amp):
        with set_recurrent_mode(True):
            whole = policy(sequence.clone())["logits"]
        state, steps = TensorDict({}, sequence.shape[:1]), []
        for t in range(sequence.shape[1]):
            td = sequence[:, t].clone()
            td.update(state)
            out = policy(td)
            steps.append(out["logits"])
            state = out["next"].select(*state_keys).apply(lambda x: x.float())
    if amp:
        assert whole.dtype == AMP_DTYPE  # autocast was on
    return torch.stack(steps, 1).float(), whole.float()


def test_step_and_sequence_logits_agree_under_bf16_autocast():
    import spf_rl

    policy, config = spf_rl.load_policy("spf-s0.8")  # trained weights: logits of realistic size
    torch.manual_seed(0)  # the sequence where bf16 moved the logits most (6.4% of the largest |logit|)
    sequence = random_sequence(config, rows=3, steps=12, restart_at=7)
    step32, whole32 = step_and_sequence_logits(policy, sequence, amp=False)
    torch.testing.assert_close(step32, whole32, rtol=1e-5, atol=1e-5)
    step16, whole16 = step_and_sequence_logits(policy, sequence, amp=True)
    assert (step16 - step32).abs().max() > 0  # bf16 did change the numbers
    assert_amp_agreement(step16, whole16, whole32)


def test_amp_bc_loss_and_ppo_collection_on_the_cpu():
    torch.manual_seed(0)
    policy = build_policy("spf", POLICY)
    episodes = empty_training_episodes(DatasetConfig(episodes=EpisodeSpec(demo_length=5, max_steps=6, image_size=32), num_episodes=2))
    episodes["steps", "mask"][:, :5] = True
    episodes["steps", "pixels"].random_(0, 256)
    loss, _ = bc_loss(policy, episodes, amp=True)
    loss.backward()
    assert loss.dtype == torch.float32 and torch.isfinite(loss)
    assert all(p.grad.dtype == torch.float32 and torch.isfinite(p.grad).all() for p in policy.parameters() if p.grad is not None)
    # PPO under amp: collect with the bf16 actor; the sequence-mode replay agrees within the amp tolerance
    actor, _ = make_ppo_modules(policy.eval())
    collector = make_collector(Autocast(actor), ENV, CollectorConfig(num_agents=2), frames_per_batch=24, total_frames=24,
                               reset_at_each_iter=True, device="cpu")
    batch = next(iter(collector))
    collector.shutdown()
    assert batch["action_log_prob"].dtype == batch["next", "spf_hidden"].dtype == torch.float32
    with autocast("cpu", True):
        replayed = recompute_log_prob(actor, batch).float()
    assert (replayed - batch["action_log_prob"]).abs().max() < AMP_RATIO_SYNC_TOLERANCE


def tiny_ppo_config(tmp_path: Path, checkpoint: Path, **overrides) -> PPOConfig:
    """Two iterations (a value-head warm-up, then a PPO update) of 2 agents x 12 steps."""
    env = overrides.pop(
        "env", CollectionEnvConfig(episodes=EpisodeSpec(num_houses=1, demo_length=5, max_steps=8, image_size=32), with_expert=False)
    )
    sizes = {key: getattr(env.episodes, key) for key in SIZE_FIELDS}  # val and test: the env's sizes and routes
    evaluation = dict(num_episodes=2, num_agents=2)
    values = dict(
        checkpoint=str(checkpoint), output_dir=str(tmp_path / "run"), frames_per_batch=24, total_frames=48,
        ppo_epochs=1, minibatch_rows=1, critic_warmup_iters=1, val_every=2, kl_coef=0.1, logger="", progress=False,
        store_demos=6, store_root=str(tmp_path / "stores"), collector=CollectorConfig(num_agents=2), env=env,
        val=EvalConfig(EpisodeSpec(split="val", seed=1, num_houses=1, **sizes), **evaluation),
        test=EvalConfig(EpisodeSpec(split="test", seed=2, num_houses=1, **sizes), **evaluation),
    )
    return PPOConfig(**{**values, **overrides})


def test_ppo_runs_under_amp_on_the_cpu(tmp_path, checkpoint):
    warmup, update = train_ppo(tiny_ppo_config(tmp_path, checkpoint, device="cpu", amp=True))["history"]
    assert warmup["critic_warmup"] and not update["critic_warmup"]
    assert warmup["skipped_updates"] == update["skipped_updates"] == 0
    assert update["log_ratio_first"] < AMP_RATIO_SYNC_TOLERANCE
    best = load_checkpoint(tmp_path / "run" / "best.pt")
    assert all(t.dtype == torch.float32 for t in best["model"].values() if t.is_floating_point())


# ---------------------------------------------------------------------- the machine a run records
def test_machine_info_tells_cpu_generations_of_one_model_name_apart(monkeypatch):
    from spf_rl import device

    cpuinfo = "processor\t: 0\nvendor_id\t: AuthenticAMD\ncpu family\t: 25\nmodel\t\t: 1\nmodel name\t: AMD EPYC\nstepping\t: 1\n"
    original = Path.read_text
    monkeypatch.setattr(Path, "read_text", lambda self, *a, **k: cpuinfo if str(self) == "/proc/cpuinfo" else original(self, *a, **k))
    info = device.machine_info()
    assert info["cpu_model"] == "AMD EPYC" and info["cpu_family_model_stepping"] == "25/1/1"
    assert info["torch_cpu_capability"] == torch.backends.cpu.get_cpu_capability()
