"""Tests for spf_rl.export and the runtime (runtime/, spf_rl_runtime): every model type exported to ONNX
steps as the eager policy does, the route memory keeps what it should in the bytes it says, and the runtime
runs in an environment without torch."""
from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
import venv
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from spf_rl.export import TeachGraph, export_checkpoint, export_policy
from spf_rl.modules import SPFConfig
from spf_rl.modules.memory import memory_indices as torch_memory_indices
from spf_rl.modules.registry import build_policy

spf_rl_runtime = pytest.importorskip("spf_rl_runtime")
Follower, RouteMemory = spf_rl_runtime.Follower, spf_rl_runtime.RouteMemory

BASE = SPFConfig(demo_length=6, feature_dim=8, hidden_size=8, image_size=(16, 16))
CASES = {
    "spf": ("spf", {}),
    "spf-rpf-rule": ("spf", {"pointer_update": "rpf"}),
    "spf_random": ("spf_random", {"sparsity_range": (0.2, 1.0)}),
    "rpf": ("rpf", {}),
    "rpf_original": ("rpf_original", {}),
    "action_only": ("action_only", {}),
    "spf_random-anchor": ("spf_random", {"sparsity_range": (0.2, 1.0), "pointer_update": "rpf", "anchor_radius": 2}),
    "spf_random-anchor-normalized": (
        "spf_random", {"sparsity_range": (0.2, 1.0), "pointer_update": "rpf", "anchor_radius": 2, "normalize_frames": True}
    ),
    "spf_random-anchor-replay-gate": (
        "spf_random", {"sparsity_range": (0.2, 1.0), "pointer_update": "rpf", "anchor_radius": 2, "replay_gate": True}
    ),
    "spf_random-anchor-replay-gate-start-check": (
        "spf_random",
        {"sparsity_range": (0.2, 1.0), "pointer_update": "rpf", "anchor_radius": 2, "replay_gate": True, "start_check": 0.5},
    ),
    "spf-start-check": ("spf", {"start_check": 0.5}),
}


def tiny_policy(model_type: str, seed: int = 0, **config):
    torch.manual_seed(seed)
    policy = build_policy(model_type, dataclasses.replace(BASE, **config)).eval()
    for parameter in policy.parameters():  # larger weights than at initialisation: the pointer moves, both ways
        torch.nn.init.normal_(parameter, std=0.5)
    if model_type == "spf_random":
        policy.set_sparsity(0.5)
    return policy


def eager_logits(policy, frames, demo_frames, demo_actions) -> list[np.ndarray]:
    """The eager policy in step mode, as an env steps it (``is_init`` at the first step)."""
    state, out = {}, []
    with torch.no_grad():
        for t, frame in enumerate(frames):
            td = TensorDict({"pixels": frame[None], "demo_frames": demo_frames[None], "demo_actions": demo_actions[None],
                             "is_init": torch.tensor([[t == 0]]), **state}, [1])
            result = policy(td)
            out.append(result["logits"][0].numpy())
            state = {key: result["next", key] for key in result["next"].keys()}
    return out


def route(seed: int = 1, steps: int = 10):
    generator = torch.Generator().manual_seed(seed)
    frames = torch.randint(0, 256, (steps, 16, 16, 3), dtype=torch.uint8, generator=generator)
    demo_frames = torch.randint(0, 256, (6, 16, 16, 3), dtype=torch.uint8, generator=generator)
    demo_actions = torch.randint(0, 3, (6,), generator=generator)
    return frames, demo_frames, demo_actions


class Exports(dict):
    """``exports[name]``: (policy, manifest, directory) of :data:`CASES`' ``name``, exported on first use."""

    def __init__(self, shared_build: Callable[[str, Callable[[Path], object]], Path]):
        super().__init__()
        self.shared_build = shared_build

    def __missing__(self, name: str) -> tuple:
        model_type, config = CASES[name]
        directory = self.shared_build(f"export-{name}", lambda out: export_policy(tiny_policy(model_type, **config), out, model_type))
        self[name] = (tiny_policy(model_type, **config), json.loads((directory / "manifest.json").read_text()), directory)
        return self[name]


@pytest.fixture(scope="session")
def exports(shared_build) -> Exports:
    """Built once in the test session (the ``shared_build`` fixture): an export costs about 7 s of CPU."""
    return Exports(shared_build)


@pytest.fixture(scope="session")
def shipped_export(shared_build) -> Path:
    """The export of the shipped ``spf-s0.8`` (read only)."""
    return shared_build("export-spf-s0.8", lambda out: export_checkpoint("spf-s0.8", out))


@pytest.mark.parametrize("name", list(CASES))
def test_the_runtime_steps_as_the_eager_policy(exports, name):
    policy, manifest, directory = exports[name]
    frames, demo_frames, demo_actions = route()
    expected = eager_logits(policy, frames, demo_frames, demo_actions)
    follower = Follower(directory)
    follower.start(follower.teach(demo_frames.numpy(), demo_actions.numpy()))
    got = [follower.step_logits(frame.numpy()) for frame in frames]
    assert max(float(np.abs(a - b).max()) for a, b in zip(expected, got)) < 1e-4
    assert manifest["model_type"] == CASES[name][0] and (directory / "step.onnx").is_file()
    assert (directory / "teach.onnx").is_file() == (name != "action_only")


def test_the_manifest_names_what_was_exported_and_a_changed_file_is_refused(exports, tmp_path):
    from spf_rl.records_cache import policy_sha256

    policy, manifest, directory = exports["spf"]
    saved = json.loads((directory / "manifest.json").read_text())
    assert saved["format_version"] == 2 and saved["weights"] == "fp32" and saved["opset"] >= 18
    assert saved["step"]["initial_state"] == {"eta": 0.0, "hidden": 0.0} and "start_match" not in saved["step"]["inputs"]
    assert saved["source"]["policy_sha256"] == policy_sha256(policy) and saved["versions"]["torch"]
    assert set(saved["files"]) == {"teach.onnx", "step.onnx"} and saved["model_config"]["demo_length"] == 6
    copy = tmp_path / "copy"
    copy.mkdir()
    for path in directory.iterdir():
        (copy / path.name).write_bytes(path.read_bytes())
    data = bytearray((copy / "step.onnx").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (copy / "step.onnx").write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"step\.onnx is missing or differs from manifest\.json"):
        Follower(copy)


def test_a_start_checks_export_carries_the_match_from_unmeasured_and_refuses_a_step_without_it(exports):
    policy, manifest, directory = exports["spf-start-check"]
    assert manifest["step"]["inputs"][-1] == "start_match" and manifest["step"]["outputs"][-1] == "start_match_next"
    assert manifest["step"]["initial_state"] == {"eta": 0.0, "hidden": 0.0, "start_match": 2.0}
    export = spf_rl_runtime.Export(directory)
    frames, demo_frames, demo_actions = route()
    follower = Follower(directory)
    memory = follower.teach(demo_frames.numpy(), demo_actions.numpy())
    state = {"memory": memory.dequantized()[None], "slot_indices": memory.slot_indices[None].astype(np.int64),
             "demo_actions": demo_actions.numpy()[None], "route_length": np.array([6]), "eta": np.zeros(1, np.float32),
             "hidden": np.zeros((1, 8), np.float32)}
    with pytest.raises(ValueError, match=r"also carries \['start_match'\]"):
        export.step(frames[0].numpy()[None], **state)
    logits, _, _, match = export.step(frames[0].numpy()[None], **state, start_match=np.full(1, 2.0, np.float32))
    follower.start(memory)
    assert np.allclose(follower.step_logits(frames[0].numpy()), logits[0], atol=1e-6)
    assert -1.0 <= float(match[0]) <= 1.0 and float(follower._state["start_match"][0]) == float(match[0])


def test_any_route_length_and_sparsity_through_one_export(exports):
    """The random-sparsity model's export keeps any sparsity; a longer route than the training one works."""
    from spf_rl.modules.views import policy_for_length

    policy, _, directory = exports["spf_random"]
    follower = Follower(directory)
    frames, _, _ = route(seed=3, steps=6)
    generator = torch.Generator().manual_seed(4)
    demo_frames = torch.randint(0, 256, (9, 16, 16, 3), dtype=torch.uint8, generator=generator)
    demo_actions = torch.randint(0, 3, (9,), generator=generator)
    view = policy_for_length(policy, 9).set_sparsity(0.3)
    expected = eager_logits(view, frames, demo_frames, demo_actions)
    memory = follower.teach(demo_frames.numpy(), demo_actions.numpy(), sparsity=0.3)
    assert memory.slot_indices.tolist() == torch_memory_indices(9, 0.3).tolist()
    follower.start(memory)
    assert max(float(np.abs(follower.step_logits(f.numpy()) - e).max()) for f, e in zip(frames, expected)) < 1e-4


def test_the_runtimes_kept_frames_are_the_eager_memorys():
    for n in range(2, 200):
        for sparsity in (0.1, 0.2, 0.25, 0.3, 0.4, 0.5, 0.6, 0.7, 0.75, 0.8, 0.9, 1.0):
            assert spf_rl_runtime.memory_indices(n, sparsity).tolist() == torch_memory_indices(n, sparsity).tolist(), (n, sparsity)


@pytest.mark.parametrize("dtype, tolerance", [("float32", 1e-6), ("float16", 1e-2), ("int8", 2e-2)])
def test_a_route_memory_round_trips_through_bytes(exports, dtype, tolerance):
    policy, _, directory = exports["spf"]
    follower = Follower(directory)
    _, demo_frames, demo_actions = route()
    memory = follower.teach(demo_frames.numpy(), demo_actions.numpy(), memory_dtype=dtype)
    again = RouteMemory.from_bytes(memory.to_bytes())
    assert again == memory and len(memory.to_bytes()) == memory.nbytes
    slots = torch_memory_indices(6, 0.8)
    with torch.no_grad():
        exact = TeachGraph(policy)(demo_frames[slots], demo_actions[slots]).numpy()
    scale = np.abs(exact).max(axis=-1, keepdims=True)
    assert (np.abs(again.dequantized() - exact) <= tolerance * scale + 1e-5).all()
    itemsize = {"float32": 4, "float16": 2, "int8": 1}[dtype]
    assert memory.nbytes == 52 + len(slots) * 8 * itemsize + (len(slots) * 4 if dtype == "int8" else 0) + len(slots) * 2 + 6


def test_bad_input_is_refused_with_its_name(exports, tmp_path):
    follower = Follower(exports["spf"][2])
    frames, demo_frames, demo_actions = route()
    with pytest.raises(ValueError, match="frames must be uint8"):
        follower.teach(demo_frames.numpy().astype(np.float32), demo_actions.numpy())
    with pytest.raises(ValueError, match="sparsity must be in"):
        follower.teach(demo_frames.numpy(), demo_actions.numpy(), sparsity=1.5)
    with pytest.raises(ValueError, match="memory_dtype must be one of"):
        follower.teach(demo_frames.numpy(), demo_actions.numpy(), memory_dtype="int4")
    with pytest.raises(ValueError, match="actions must be in 0..2"):
        follower.teach(demo_frames.numpy(), np.full(6, 3))
    with pytest.raises(RuntimeError, match="start"):
        follower.step(frames[0].numpy())
    other = Follower(exports["spf-rpf-rule"][2])
    with pytest.raises(ValueError, match="another export"):
        follower.start(other.teach(demo_frames.numpy(), demo_actions.numpy()))
    with pytest.raises(ValueError, match="holds no export"):
        Follower(tmp_path)
    with pytest.raises(ValueError, match="not a route memory"):
        RouteMemory.from_bytes(b"nothing")


def test_int8_weights_export_and_step_close_to_float32(exports, tmp_path):
    policy, _, directory = exports["spf"]
    export_policy(policy, tmp_path / "int8", "spf", weights="int8")
    frames, demo_frames, demo_actions = route()
    logits = {}
    for name, path in (("fp32", directory), ("int8", tmp_path / "int8")):
        follower = Follower(path)
        follower.start(follower.teach(demo_frames.numpy(), demo_actions.numpy()))
        logits[name] = np.stack([follower.step_logits(frame.numpy()) for frame in frames])
    assert json.loads((tmp_path / "int8" / "manifest.json").read_text())["weights"] == "int8"
    assert (tmp_path / "int8" / "step.onnx").stat().st_size < (directory / "step.onnx").stat().st_size
    assert np.isfinite(logits["int8"]).all() and not np.array_equal(logits["int8"], logits["fp32"])
    with pytest.raises(ValueError, match="weights must be one of"):
        export_policy(policy, tmp_path / "bad", "spf", weights="int4")


def test_a_shipped_checkpoint_exports_by_name(shipped_export):
    manifest = json.loads((shipped_export / "manifest.json").read_text())
    assert manifest["source"]["checkpoint"] == "spf-s0.8" and tuple(manifest["model_config"]["image_size"]) == (64, 64)
    assert Follower(shipped_export).sparsity == pytest.approx(0.8)


def test_the_runtime_runs_without_torch(exports, tmp_path):
    """A virtual environment that holds numpy, onnxruntime and the runtime only: it teaches and follows, and
    torch, torchrl, tensordict and mujoco are never imported."""
    import onnxruntime

    env = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(env)
    site = next((env / "lib").glob("python*/site-packages"))
    links = tmp_path / "only"
    links.mkdir()
    parent = Path(onnxruntime.__file__).parents[1]
    for name in ("numpy", "numpy.libs", "onnxruntime", "flatbuffers", "google", "packaging", "coloredlogs", "humanfriendly",
                 "sympy", "mpmath"):
        if (parent / name).exists():
            (links / name).symlink_to(parent / name)
    runtime_source = Path(spf_rl_runtime.__file__).parents[1]
    (site / "only.pth").write_text(f"{links}\n{runtime_source}\n")
    policy, _, directory = exports["spf"]
    frames, demo_frames, demo_actions = route()
    np.save(tmp_path / "frames.npy", frames.numpy())
    np.save(tmp_path / "demo_frames.npy", demo_frames.numpy())
    np.save(tmp_path / "demo_actions.npy", demo_actions.numpy())
    script = f"""
import sys, numpy as np
from spf_rl_runtime import Follower, RouteMemory
f = Follower({str(directory)!r})
memory = RouteMemory.from_bytes(f.teach(np.load({str(tmp_path / 'demo_frames.npy')!r}), np.load({str(tmp_path / 'demo_actions.npy')!r}), memory_dtype="int8").to_bytes())
f.start(memory)
logits = np.stack([f.step_logits(frame) for frame in np.load({str(tmp_path / 'frames.npy')!r})])
np.save({str(tmp_path / 'runtime_logits.npy')!r}, logits)
print(sorted(name for name in ("torch", "torchrl", "tensordict", "mujoco", "spf_rl", "envs") if name in sys.modules))
"""
    python = env / "bin" / "python"
    clean = {key: value for key, value in os.environ.items() if key not in ("PYTHONPATH", "PYTHONHOME")}
    result = subprocess.run([str(python), "-c", "import torch"], capture_output=True, text=True, env=clean)
    assert result.returncode != 0  # torch is not there at all
    result = subprocess.run([str(python), "-c", script], capture_output=True, text=True, env=clean, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"
    expected = np.stack(eager_logits(policy, frames, demo_frames, demo_actions))
    assert np.abs(np.load(tmp_path / "runtime_logits.npy") - expected).max() < 0.5  # int8 memory: close, not equal
    assert sys.version_info >= (3, 10)


def test_the_runtime_needs_python_3_10_at_most():
    """ROS 2 Humble's Python is 3.10: the runtime's code uses nothing newer (vermin reads it statically)."""
    import spf_rl_runtime as runtime

    result = subprocess.run([str(Path(sys.executable).parent / "vermin"), "--target=3.10-", "--no-tips", "--violations",
                             str(Path(runtime.__file__).parent)], capture_output=True, text=True)
    assert result.returncode == 0, result.stdout + result.stderr


@pytest.mark.parametrize(
    "argv, message",
    [
        (["missing.pt"], "argument checkpoint: checkpoint file missing.pt does not exist."),
        (["spf-s0.8", "--weights", "int4"], "argument --weights: invalid choice: 'int4'"),
        (["spf-s0.8", "--sparsity", "0.5"], "argument --sparsity: only a random-sparsity model (spf_random)"),
        (["spf_random-s0.2-1", "--sparsity", "1.5"], "argument --sparsity: must be in (0, 1], got 1.5"),
    ],
)
def test_the_export_recipe_refuses_bad_values_before_any_work(tmp_path, capsys, argv, message):
    import export as recipe

    with pytest.raises(SystemExit) as exit_info:
        recipe.main([*argv, "--out", str(tmp_path / "out")])
    assert exit_info.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_the_export_recipe_writes_a_directory_the_runtime_follows(tmp_path):
    import export as recipe

    manifest = recipe.main(["spf_random-s0.2-1", "--sparsity", "0.4", "--out", str(tmp_path / "out")])
    follower = Follower(tmp_path / "out")
    assert manifest["model_type"] == "spf_random" and follower.sparsity == pytest.approx(0.4)
    frames = np.zeros((30, 64, 64, 3), np.uint8)
    memory = follower.teach(frames, np.zeros(30, np.int64), memory_dtype="int8")
    follower.start(memory)
    assert memory.slot_indices.size == 12 and follower.step(frames[0]) in (0, 1, 2)


@pytest.mark.parametrize("name", ["spf", "rpf_original", "action_only"])
def test_the_exported_policy_plays_the_eager_policys_episodes(tmp_path, name):
    """ExportedPolicy (ONNX Runtime in a TensorDict module, a batch of agents) plays the same episodes as the
    eager policy, with the same actions: the same per-episode records."""
    from envs.episode_spec import EpisodeSpec
    from spf_rl.evaluation import EvalConfig, evaluate_policy
    from spf_rl.modules.exported import ExportedPolicy

    model_type, config = CASES[name]
    torch.manual_seed(0)
    policy = build_policy(model_type, dataclasses.replace(BASE, demo_length=5, image_size=(32, 32), **config)).eval()
    export_policy(policy, tmp_path / name, model_type)
    evaluation = EvalConfig(EpisodeSpec(split="val", num_houses=1, demo_length=5, max_steps=8, image_size=32),
                            num_episodes=4, num_agents=2)
    _, eager = evaluate_policy(policy, evaluation)
    _, exported = evaluate_policy(ExportedPolicy(tmp_path / name), evaluation)
    keys = ("episode_seed", "success", "steps", "goal_distance", "path_length")
    assert [{k: r[k] for k in keys} for r in exported] == [{k: r[k] for k in keys} for r in eager]


def test_evaluate_runs_an_export_directory_as_the_eager_checkpoint(tmp_path, shipped_export):
    """recipes/evaluate.py DIR: the exported policy, in worker processes too, scores as its checkpoint does."""
    import copy

    import evaluate as recipe

    from spf_rl.modules.exported import ExportedPolicy

    assert copy.deepcopy(ExportedPolicy(shipped_export)).export.export_id  # picklable: sessions made again
    common = ["--episodes", "4", "--num-agents", "2", "--split", "val", "--store-root", str(tmp_path / "stores"), "--no-progress"]
    exported = recipe.main([str(shipped_export), *common, "--out", str(tmp_path / "a"), "--num-collectors", "2"])[0]
    eager = recipe.main(["spf-s0.8", *common, "--out", str(tmp_path / "b")])[0]
    assert exported["model"] == "spf" and exported["success"] == eager["success"]
    keys = ("episode_seed", "success", "steps", "goal_distance")
    assert [{k: r[k] for k in keys} for r in exported["episodes_records"]] == [{k: r[k] for k in keys} for r in eager["episodes_records"]]


def test_the_route_bench_and_teach_run_an_export(tmp_path, shipped_export):
    """recipes/route_bench.py --models DIR and recipes/teach.py --checkpoint DIR: the exported policy plays what
    the eager one plays (the same records), at another route length too."""
    import teach as teach_recipe

    from spf_rl.eval import route_bench

    options = dict(styles=("driven",), buckets=((10, 12),), sets=("test",), episodes=2, test_houses=2, num_resamples=100,
                   store_root=str(tmp_path / "stores"))
    eager = route_bench.run_bench(route_bench.BenchOptions(models=("spf-s0.8",), out=tmp_path / "a.json", **options))
    exported = route_bench.run_bench(route_bench.BenchOptions(models=(str(shipped_export),), out=tmp_path / "b.json", **options))
    columns = {name: next(iter(content["cells"].values()))["models"] for name, content in (("eager", eager), ("exported", exported))}
    assert columns["exported"][str(shipped_export)]["columns"]["success"] == columns["eager"]["spf-s0.8"]["columns"]["success"]
    assert columns["exported"][str(shipped_export)]["policy_sha256"] != columns["eager"]["spf-s0.8"]["policy_sha256"]
    content = teach_recipe.main(["--actions", "FFFFLFFFFF", "--checkpoint", str(shipped_export), "--repeats", "1",
                                 "--no-video", "--out", str(tmp_path / "teach")])
    assert content["checkpoint"] == str(shipped_export) and len(content["repeats"]) == 1


@pytest.mark.parametrize("name", ["spf", "spf_random", "rpf_original", "action_only", "spf_random-anchor-replay-gate-start-check"])
def test_the_exported_policy_steps_a_batch_of_padded_routes_as_eager(exports, name):
    """Three agents on routes of 4, 6 and 5 steps padded to 6, one of them starting again mid-way: the
    exported module's logits are the eager policy's, row by row."""
    from spf_rl.modules.exported import ExportedPolicy

    policy, _, directory = exports[name]
    exported = ExportedPolicy(directory)
    generator = torch.Generator().manual_seed(5)
    demo_frames = torch.randint(0, 256, (3, 6, 16, 16, 3), dtype=torch.uint8, generator=generator)
    demo_actions = torch.randint(0, 3, (3, 6), generator=generator)
    steps = torch.tensor([[4], [6], [5]])
    states = {"eager": {}, "exported": {}}
    worst = 0.0
    with torch.no_grad():
        for t in range(7):
            frames = torch.randint(0, 256, (3, 16, 16, 3), dtype=torch.uint8, generator=generator)
            is_init = torch.tensor([[t == 0], [t in (0, 3)], [t == 0]])
            logits = {}
            for kind, module in (("eager", policy), ("exported", exported)):
                td = TensorDict({"pixels": frames, "demo_frames": demo_frames, "demo_actions": demo_actions, "demo_steps": steps,
                                 "is_init": is_init, **states[kind]}, [3])
                out = module(td)
                logits[kind] = out["logits"]
                states[kind] = {key: out["next", key] for key in out["next"].keys()}
            worst = max(worst, float((logits["eager"] - logits["exported"]).abs().max()))
    assert worst < 1e-4


def test_a_route_memory_refuses_what_it_cannot_keep():
    features = np.ones((2, 3), np.float32)
    with pytest.raises(ValueError, match="export_id must be a SHA-256"):
        RouteMemory.of(features, [0, 1], [0, 0], "abc")
    with pytest.raises(ValueError, match="not finite"):
        RouteMemory.of(features * np.nan, [0, 1], [0, 0], "0" * 64)
    with pytest.raises(ValueError, match="exceed float16's range"):
        RouteMemory.of(features * 1e6, [0, 1], [0, 0], "0" * 64, "float16")
    data = bytearray(RouteMemory.of(features, [0, 1], [0, 0], "0" * 64).to_bytes())
    data[6] = 9  # the precision code
    with pytest.raises(ValueError, match="unknown feature precision"):
        RouteMemory.from_bytes(bytes(data))


def test_an_export_refuses_bad_settings_naming_them(exports):
    from spf_rl.modules.exported import ExportedPolicy

    directory = exports["spf"][2]
    with pytest.raises(ValueError, match="threads must be an int >= 1"):
        Follower(directory, threads=0)
    with pytest.raises(ValueError, match="sparsity must be in"):
        ExportedPolicy(directory, sparsity=1.5)
    with pytest.raises(ValueError, match="memory_dtype must be one of"):
        ExportedPolicy(directory, memory_dtype="int4")
