"""The env composed with standard TorchRL parts: noise through batched envs and
collectors, standard image transforms, hidden privileged keys, the package surface
and clear errors."""
from __future__ import annotations

import functools
import importlib.util
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from torchrl.collectors import MultiSyncCollector
from torchrl.envs import (
    CatFrames,
    Compose,
    GrayScale,
    InitTracker,
    ParallelEnv,
    Resize,
    SerialEnv,
    ToTensorImage,
    TransformedEnv,
    check_env_specs,
)

from envs.demos import nominal_motion
from envs.factory import make_parallel_path_follow_env, make_path_follow_env
from envs.nav_env import PathFollowEnv
from envs.specs import PRIVILEGED_KEYS, HidePrivileged
from envs.transforms import ActuationNoise
from envs.worker_processes import start_method

SMALL = dict(num_houses=1, demo_length=6, max_steps=25, image_size=32, render=False)
STEPS = 20


def _forward(td):
    return td.set("action", torch.zeros(td.shape, dtype=torch.long))


def heading_deviation_deg(data) -> np.ndarray:
    """Executed minus nominal rotation of every step, degrees (0 everywhere without noise)."""
    turned = (data["next", "pose"][..., 2] - data["pose"][..., 2]).numpy()
    nominal = nominal_motion(data["action"].numpy())[..., 2]
    return np.rad2deg(np.angle(np.exp(1j * (turned - nominal))))


def _final_poses(env, steps: int = STEPS, close: bool = True) -> torch.Tensor:
    env.set_seed(0)
    rollout = env.rollout(steps, _forward, break_when_any_done=False)
    if close:
        env.close(raise_if_closed=False)
    return rollout


@pytest.mark.parametrize("serial", [True, False], ids=["SerialEnv", "ParallelEnv"])
def test_noise_around_a_batched_env_reaches_the_workers(serial: bool) -> None:
    noisy_env = make_parallel_path_follow_env(2, noise="paper", serial=serial, **SMALL)
    noisy = _final_poses(noisy_env, close=False)
    # the same batched env (a ParallelEnv's worker processes are started once), its transforms without noise
    clean = _final_poses(TransformedEnv(noisy_env.base_env, Compose(ActuationNoise("none"), InitTracker())))
    assert not torch.equal(noisy["next", "pose"][:, -1], clean["next", "pose"][:, -1])
    assert np.abs(heading_deviation_deg(clean)).max() < 1e-3
    # forward steps of the paper preset turn by up to 4 degrees, 4 exactly most of the time
    deviation = np.abs(heading_deviation_deg(noisy))
    assert deviation.max() <= 4 + 1e-3 and (np.abs(deviation - 4) < 1e-3).mean() > 0.8
    # the same noise as with the transform inside each worker
    batched = SerialEnv if serial else functools.partial(ParallelEnv, mp_start_method=start_method())
    inside = _final_poses(batched(2, functools.partial(make_path_follow_env, noise="paper", **SMALL)))
    torch.testing.assert_close(inside["next", "pose"], noisy["next", "pose"])


def test_noise_through_a_multisync_collector() -> None:
    factory = functools.partial(make_parallel_path_follow_env, 2, noise="paper", serial=True, **SMALL)
    collector = MultiSyncCollector([factory, factory], _forward, frames_per_batch=40, total_frames=40)
    collector.set_seed(0)
    batch = next(iter(collector))
    collector.shutdown()
    deviation = np.abs(heading_deviation_deg(batch))
    assert (np.abs(deviation - 4) < 1e-3).mean() > 0.8


#: torchrl's Resize and GrayScale call torchvision; PyPI's torchvision wheels are CUDA
#: builds that do not load beside the CPU torch wheel this project pins.
needs_torchvision = pytest.mark.skipif(
    importlib.util.find_spec("torchvision") is None, reason="torchvision is not installed"
)


@pytest.mark.parametrize(
    "transform",
    [
        lambda: ToTensorImage(in_keys=["pixels"]),
        pytest.param(
            lambda: Compose(ToTensorImage(in_keys=["pixels"]), Resize(16, 16, in_keys=["pixels"])),
            marks=needs_torchvision,
        ),
        pytest.param(
            lambda: Compose(ToTensorImage(in_keys=["pixels"]), GrayScale(in_keys=["pixels"])),
            marks=needs_torchvision,
        ),
        lambda: Compose(ToTensorImage(in_keys=["pixels"]), CatFrames(N=4, dim=-3, in_keys=["pixels"])),
    ],
    ids=["ToTensorImage", "Resize", "GrayScale", "CatFrames"],
)
def test_standard_image_transforms(transform) -> None:
    env = TransformedEnv(PathFollowEnv(**{**SMALL, "render": True}), transform())
    check_env_specs(env)
    pixels = env.reset()["pixels"]
    assert pixels.dtype == torch.float32 and pixels.shape[-3] in (1, 3, 12)
    assert pixels.shape[-2:] in ((32, 32), (16, 16))
    assert 0.0 <= pixels.min() and pixels.max() <= 1.0 and pixels.max() > 0


def test_pixels_are_hwc_uint8() -> None:
    env = PathFollowEnv(**{**SMALL, "render": True})
    td = env.reset()
    assert td["pixels"].shape == (32, 32, 3) and td["pixels"].dtype == torch.uint8
    assert td["demo_frames"].shape == (6, 32, 32, 3)
    torch.testing.assert_close(td["pixels"], td["demo_frames"][0])  # the agent starts on the demo's first pose
    env.close()


def test_hide_privileged_removes_them_from_the_policy_input() -> None:
    env = TransformedEnv(PathFollowEnv(**SMALL, with_expert=True), HidePrivileged())
    check_env_specs(env)
    policy_input = set(env.observation_spec.keys(True, True))
    assert not policy_input & set(PRIVILEGED_KEYS)
    assert {"pixels", "demo_frames", "demo_actions"} <= policy_input
    assert not set(env.rollout(3).keys(True, True)) & set(PRIVILEGED_KEYS)
    # without it they are there (route_step with the route expert's labels only)
    assert set(PRIVILEGED_KEYS) <= set(
        PathFollowEnv(**SMALL, with_expert=True, expert="route", conditions="none", memory_mismatch=0.0).observation_spec.keys()
    )
    assert "route_step" not in PathFollowEnv(**SMALL, with_expert=True, expert="goal").observation_spec.keys()
    # an env without expert labels: the keys it has are hidden, the one it lacks ignored
    env = TransformedEnv(PathFollowEnv(**SMALL), HidePrivileged())
    check_env_specs(env)
    assert not set(env.observation_spec.keys()) & set(PRIVILEGED_KEYS)


def test_public_names_import_from_the_package() -> None:
    from envs import ActuationNoise as Noise
    from envs import PathFollowEnv as Env
    from envs import make_path_follow_env as make

    assert Env is PathFollowEnv and Noise is ActuationNoise and make is make_path_follow_env


def _run_python(code: str, env_update: dict[str, str | None]) -> subprocess.CompletedProcess:
    environ = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM", "LP_NUM_THREADS")}
    for key, value in env_update.items():
        if value is None:
            environ.pop(key, None)
        else:
            environ[key] = value
    return subprocess.run([sys.executable, "-c", code], env=environ, capture_output=True, text=True, timeout=120)


def test_import_leaves_the_process_environment_alone() -> None:
    code = "import os; before = dict(os.environ); import envs, envs.nav_env; print(dict(os.environ) == before)"
    result = _run_python(code, {})
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "True"


def test_no_gl_backend_is_needed_without_rendering() -> None:
    """A machine without EGL or OSMesa: envs import, render=False works, the first render says what to install."""
    code = (
        "import envs.render\n"
        "envs.render._can_load = lambda library: False  # no libEGL, no libOSMesa\n"
        "from envs import PathFollowEnv\n"
        "env = PathFollowEnv(num_houses=1, demo_length=5, render=False)\n"
        "print(env.rollout(3, break_when_any_done=False)['next', 'pose'].shape)\n"
        "try:\n"
        "    PathFollowEnv(num_houses=1, demo_length=5).reset()\n"
        "except Exception as err:\n"
        "    print(type(err).__name__, err)\n"
    )
    result = _run_python(code, {})
    assert result.returncode == 0, result.stderr
    lines = result.stdout.strip().splitlines()
    assert lines[0] == "torch.Size([3, 3])"
    assert lines[1].startswith("RendererUnavailableError No headless OpenGL back-end found")
    assert "apt-get install libegl1" in lines[1] and "('egl', 'osmesa', 'glfw')" in lines[1]


def test_unsupported_gl_backend_is_named_at_the_first_render(monkeypatch: pytest.MonkeyPatch) -> None:
    from envs.render import RendererUnavailableError, select_gl_backend

    monkeypatch.setenv("MUJOCO_GL", "wayland")
    with pytest.raises(RendererUnavailableError, match=r"MUJOCO_GL='wayland' is not supported.*\('egl', 'osmesa', 'glfw'\)"):
        select_gl_backend()


def test_step_before_reset_is_a_clear_error() -> None:
    env = PathFollowEnv(**SMALL)
    td = env.full_action_spec.zero()
    with pytest.raises(RuntimeError, match=r"before reset\(\)"):
        env.step(td)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_actuation_noise_is_a_clear_error(bad: float) -> None:
    env = PathFollowEnv(**SMALL)
    td = env.reset()
    td["action"] = torch.tensor(0)
    td["actuation_noise"] = torch.tensor([bad, 0.0, 0.0])
    with pytest.raises(ValueError, match="actuation_noise must be finite"):
        env.step(td)


def test_wrong_action_is_a_clear_error() -> None:
    env = PathFollowEnv(**SMALL)
    td = env.reset()
    td["action"] = torch.tensor(7)
    with pytest.raises(ValueError, match=r"action must be an integer in \[0, 2\] \(0 forward, 1 left, 2 right\)"):
        env.step(td)


def test_lab_success_is_reported_beside_ours() -> None:
    """The RPF lab code's criterion: horizontal Euclidean distance < 0.8 m or < 10% of the initial one."""
    from envs.episodes import run_episodes
    from envs.scripted import ExpertPolicy
    from spf_rl.metrics import summarize

    env = TransformedEnv(PathFollowEnv(**{**SMALL, "num_agents": 4, "with_expert": True}), ActuationNoise("paper"))
    env.set_seed(0)
    records = run_episodes(env, ExpertPolicy(), 8)
    assert all(isinstance(r["success_lab"], bool) for r in records)
    summary = summarize(records)
    assert 0.0 <= summary["success_lab"] <= 1.0 and len(summary["success_lab_ci"]) == 2
    # the expert ends within our geodesic radius (>= 0.6 m); the Euclidean distance is no longer
    assert all(r["success_lab"] for r in records if r["success"] and r["goal_distance"] < 0.8)
