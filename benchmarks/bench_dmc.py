"""Benchmark: the dm_control face (:mod:`envs.dmc`) beside ``PathFollowEnv``, as ratios in one run.

Writes ``benchmarks/results/dmc.json`` and prints a table. Paths, each stepping ONE
unbatched env in this process with uniformly random forward/left/right actions
(no actuation noise; episodes end on success or after ``max_steps`` = 50, and each
reset samples a demonstration and renders its frames, as in training):

a. ``dmc``: ``env.step(action)`` on :func:`envs.dmc.load` (dm_env time steps);
   dm_control resets by itself after a last step: that call is not counted as a frame;
b. ``dmc_wrapper``: :class:`torchrl.envs.DMControlWrapper` around (a), stepped with
   ``step_and_maybe_reset`` (one-hot actions, the wrapper's convention);
c. ``path_follow_env``: :class:`~envs.nav_env.PathFollowEnv` (no transforms), stepped
   with ``step_and_maybe_reset``.

And rendering alone, one house, a pose sequence of one random walk:

d. ``render_first_person``: :class:`~envs.render.FirstPersonRenderer` on the
   house-with-agent model (what the task uses);
e. ``render_physics``: ``physics.render(camera_id="eye")`` (dm_control's ``Camera``,
   its own GL context), after setting the pose and ``physics.forward()``.

Timed chunks are interleaved (a b c d e, a b c d e, ...) after a warm-up of every
path (house compilation and GL contexts are not counted), so load from other
processes on a shared machine falls on every path alike; each figure is the median
over chunks, and speed is stated as ratios between paths of the same run.

Usage::

    python benchmarks/bench_dmc.py            # about 1 minute
    python benchmarks/bench_dmc.py --quick    # about 30 s
    python benchmarks/bench_env.py --only dmc # the same, from bench_env
"""
from __future__ import annotations

import argparse
import logging
import os
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from bench_env_paths import median_fps
from bench_env_report import other_processes_cpu_seconds
from torchrl.envs import DMControlWrapper

from envs.atomic_io import atomic_write_json
from envs.demos import apply_motion, nominal_motion
from envs.dmc import load
from envs.dmc_physics import HousePhysics, agent_house_model
from envs.house_mesh import house_model
from envs.nav_env import DEFAULT_MAX_STEPS, PathFollowEnv
from envs.render import FirstPersonRenderer
from envs.scenes import build_house, split_seeds
from spf_rl.device import machine_info

logger = logging.getLogger("bench_dmc")

RESULTS_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "results" / "dmc.json"
#: Forward, left, right: the actions drawn (no STOP).
NUM_ACTIONS = 3
#: Warm-up steps of each path before timing, frames.
WARMUP_FRAMES = 200

DESCRIPTIONS = {
    "dmc": "(a) envs.dmc.load(...): env.step(action), dm_env time steps",
    "dmc_wrapper": "(b) DMControlWrapper(envs.dmc.load(...)): step_and_maybe_reset, one-hot actions",
    "path_follow_env": "(c) PathFollowEnv (unbatched, no transforms): step_and_maybe_reset",
    "render_first_person": "(d) FirstPersonRenderer.render of the house-with-agent model, one house",
    "render_physics": "(e) HousePhysics.render(camera_id='eye') after set_agent_pose + forward, one house",
}


def _dmc_path(env_kwargs: dict, seed: int) -> Callable[[int], float]:
    env = load(seed=seed, **env_kwargs)
    env.reset()
    rng = np.random.default_rng(seed)

    def run(count: int) -> float:
        actions = rng.integers(0, NUM_ACTIONS, size=count)
        steps = 0
        start = time.perf_counter()
        while steps < count:
            if not env.step(actions[steps]).first():  # a first time step is dm_control's reset
                steps += 1
        return time.perf_counter() - start

    return run


def _torchrl_path(env, seed: int, one_hot: bool) -> Callable[[int], float]:
    env.set_seed(seed)
    generator = torch.Generator().manual_seed(seed)
    tensordict = env.reset()

    def run(count: int) -> float:
        nonlocal tensordict
        actions = torch.randint(0, NUM_ACTIONS, (count,), generator=generator)
        if one_hot:
            actions = torch.nn.functional.one_hot(actions, NUM_ACTIONS)
        start = time.perf_counter()
        for action in actions:
            tensordict.set("action", action)
            _, tensordict = env.step_and_maybe_reset(tensordict)
        return time.perf_counter() - start

    return run


def _render_paths(house_seed: int, image_size: int, seed: int) -> tuple[Callable[[int], float], Callable[[int], float]]:
    house = build_house(house_seed)
    physics = HousePhysics.from_house(house)
    view = physics.first_person_view
    renderer = FirstPersonRenderer(image_size, image_size)
    rng = np.random.default_rng(seed)
    pose = np.array([[*house.spawn_xy, 0.0]])
    walk = []
    for action in rng.integers(0, NUM_ACTIONS, size=500):
        pose, _ = apply_motion(house, pose, nominal_motion(action)[None])
        walk.append(pose[0])

    def first_person(count: int) -> float:
        start = time.perf_counter()
        for index in range(count):
            renderer.render(view, walk[index % len(walk)])
        return time.perf_counter() - start

    def dm_control_camera(count: int) -> float:
        start = time.perf_counter()
        for index in range(count):
            physics.set_agent_pose(walk[index % len(walk)])
            physics.forward()
            physics.render(image_size, image_size, camera_id="eye")
        return time.perf_counter() - start

    return first_person, dm_control_camera


def bench_dmc(
    image_size: int = 64, num_houses: int = 4, demo_length: int = 30, seed: int = 0, quick: bool = False
) -> dict:
    """Measure the paths (see the module docstring) and return the JSON-ready results."""
    torch.set_num_threads(1)
    chunks = 3 if quick else 5
    env_frames = 200 if quick else 500
    render_frames = 200 if quick else 500
    env_kwargs = {"num_houses": num_houses, "demo_length": demo_length, "image_size": image_size}
    house_seeds = split_seeds("train", num_houses)
    for house_seed in house_seeds:  # compile once per process, outside the timed chunks
        agent_house_model(house_seed)
        house_model(build_house(house_seed))
    wrapped = DMControlWrapper(load(seed=seed, **env_kwargs))
    path_follow_env = PathFollowEnv("train", **env_kwargs)
    first_person, dm_control_camera = _render_paths(house_seeds[0], image_size, seed)
    paths = {
        "dmc": (_dmc_path(env_kwargs, seed), env_frames),
        "dmc_wrapper": (_torchrl_path(wrapped, seed, one_hot=True), env_frames),
        "path_follow_env": (_torchrl_path(path_follow_env, seed, one_hot=False), env_frames),
        "render_first_person": (first_person, render_frames),
        "render_physics": (dm_control_camera, render_frames),
    }
    for name, (run, _) in paths.items():
        logger.info("warming up %s", name)
        run(WARMUP_FRAMES)
    others_before = other_processes_cpu_seconds() if Path("/proc").exists() else {}
    machine = machine_info()
    wall_start = time.perf_counter()
    seconds: dict[str, list[float]] = {name: [] for name in paths}
    for chunk in range(chunks):
        for name, (run, frames) in paths.items():
            seconds[name].append(run(frames))
        logger.info("chunk %d/%d done", chunk + 1, chunks)
    wall = time.perf_counter() - wall_start
    wrapped.close()
    path_follow_env.close()

    results = {}
    for name, (_, frames) in paths.items():
        fps = median_fps([frames] * chunks, seconds[name])
        results[name] = {
            "fps": fps,
            "ms_per_frame": 1e3 / fps,
            "frames": frames * chunks,
            "description": DESCRIPTIONS[name],
        }
    fps = {name: result["fps"] for name, result in results.items()}
    ratios = {
        "dmc_over_path_follow_env": fps["dmc"] / fps["path_follow_env"],
        "dmc_wrapper_over_path_follow_env": fps["dmc_wrapper"] / fps["path_follow_env"],
        "dmc_wrapper_over_dmc": fps["dmc_wrapper"] / fps["dmc"],
        "render_first_person_over_render_physics": fps["render_first_person"] / fps["render_physics"],
    }
    if others_before:
        used = {
            pid: (command, cpu - (others_before[pid][1] if pid in others_before else 0.0))
            for pid, (command, cpu) in other_processes_cpu_seconds().items()
        }
        busy = {command: round(cpu / wall, 2) for command, cpu in used.values() if cpu > 0.05 * wall}
        machine["other_processes_cpu_share"] = busy
    return {
        "benchmark": "benchmarks/bench_dmc.py" + (" --quick" if quick else ""),
        "machine": {**machine, "load_average_at_end": [round(x, 2) for x in os.getloadavg()]},
        "setup": {
            "image_size": image_size,
            "num_houses": num_houses,
            "house_set": "train split, first num_houses seeds",
            "demo_length": demo_length,
            "max_steps": DEFAULT_MAX_STEPS,
            "noise": "none",
            "actions": "uniform over forward/left/right, no STOP",
            "statistic": f"median frames/s over {chunks} interleaved timed chunks after {WARMUP_FRAMES} warm-up frames",
        },
        "results": results,
        "ratios": ratios,
        "notes": [
            "Ratios are between paths measured in this run (interleaved chunks); absolute frames/s depend on the "
            "machine and its load (machine.other_processes_cpu_share).",
            "Env paths include episode resets (a demonstration sampled and its frames rendered about every "
            "episode); render paths draw frames only.",
        ],
    }


def write_results(output: dict, path: Path = RESULTS_PATH) -> None:
    """Write ``output`` as JSON to ``path`` and log a table of it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(path, output)
    for name, result in output["results"].items():
        logger.info("%-20s %8.0f frames/s  %.3f ms/frame", name, result["fps"], result["ms_per_frame"])
    for name, ratio in output["ratios"].items():
        logger.info("%-40s %.2fx", name, ratio)
    logger.info("wrote %s", path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="fewer, shorter chunks")
    parser.add_argument("--image-size", type=int, default=64)
    parser.add_argument("--num-houses", type=int, default=4)
    parser.add_argument("--demo-length", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", type=Path, default=RESULTS_PATH)
    args = parser.parse_args()
    # force: dm_control's absl has already put a handler on the root logger
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", force=True)
    output = bench_dmc(args.image_size, args.num_houses, args.demo_length, args.seed, args.quick)
    write_results(output, args.output)


if __name__ == "__main__":
    main()
