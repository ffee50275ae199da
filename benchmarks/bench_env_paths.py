"""The measured paths of ``benchmarks/bench_env.py``: the raw render loop, one env, collectors.

Each path returns a result dict (``fps``: median frames/s over timed chunks,
``frames``, ``seconds``, and for paths that sample demonstrations at reset
``demo_frames`` and ``rendered_fps``). :class:`BenchPaths` builds every path of
the benchmark from a :class:`BenchConfig`; the paths and what they measure are
listed in ``DESCRIPTIONS`` (the JSON's ``description`` of each result).

Env factories are module-level functions (picklable under ``spawn``, for
``ParallelEnv`` and multi-process collectors).
"""
from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from envs.demo_store import DemoStore, DemoStoreConfig
from envs.demos import apply_motion, nominal_motion
from envs.episode_spec import EpisodeSpec
from envs.factory import make_path_follow_env
from envs.house_mesh import house_model
from envs.render import FirstPersonRenderer
from envs.scenes import build_house

REPO_ROOT = Path(__file__).resolve().parents[1]
#: Demonstrations in the benchmark's store.
BENCH_STORE_DEMOS = 1000
#: Forward, left, right: the actions drawn (no STOP).
NUM_ACTIONS = 3
#: Timed chunks per path (``--quick``: fewer), and the scale of chunk and batch sizes.
CHUNKS, QUICK_CHUNKS = 5, 3
QUICK_SCALE = 0.4
#: Warm-up of the raw loop and of the single env before timing, frames.
WARMUP_FRAMES = 300
#: Frames per timed chunk of the raw loop and of the single env (times the scale).
RAW_CHUNK_FRAMES = 2000
ENV_STEP_CHUNK_FRAMES = 600
#: Collector batch sizes, frames (times the scale).
SINGLE_BATCH_FRAMES = 500
BATCHED_BATCH_FRAMES = 1600
PARALLEL_BATCH_FRAMES = 250
MULTISYNC_BATCH_FRAMES = 3200
#: Batch of the policy-side look-up path (not scaled), frames.
LOOKUP_BATCH_FRAMES = 3200
#: Episode length bound of the env (``max_steps``): a multi-sync batch holds at least one per agent.
MAX_EPISODE_STEPS = 50
#: Agents per batched env, and per batched env of the larger store path.
NUM_AGENTS, NUM_AGENTS_LARGE = 8, 32
#: Worker processes of ``ParallelEnv`` and of ``MultiSyncCollector``.
NUM_WORKERS = 2

DESCRIPTIONS = {
    "raw": "(a) pose update + FirstPersonRenderer.render + torch uint8 HWC tensor, one house, no torchrl",
    "env_step": "(b) one unbatched env (ActuationNoise paper + InitTracker), step_and_maybe_reset loop",
    "collector_single": "(c) Collector(single env), random policy",
    "collector_batched8": "(d) Collector(batched env, num_agents=8)",
    "collector_parallel2": "(e) Collector(ParallelEnv(2, single env), spawn, shared-memory buffers)",
    "multisync_2x_batched8": "(f) MultiSyncCollector([batched env num_agents=8] * 2), spawn",
    "diag_batched8_no_demo_frames": "diagnostic, not a usable config: (d) with demo_frames excluded "
    "(ExcludeTransform), to show what carrying 30 demo frames in every step's output costs",
    "collector_batched8_store": "(h) (d) with a DemoStore: pre-rendered demonstrations, demo_id emitted "
    "instead of demo_frames (emit_demo_frames=False)",
    "multisync_2x_batched8_store": "(i) (f) with a DemoStore, demo_id emitted instead of demo_frames",
    "multisync_2x_batched32_store": "(i') (i) with 32 agents per batched env",
    "multisync_2x_batched32_store_lookup": "(i'') (i') with a policy that looks demo_frames up in the store "
    "where is_init is true (lookup_module(only_where='is_init') + random actor, frames kept out of the batch)",
    "multisync_2x_batched8_store_frames": "(j) (f) with a DemoStore, demo_frames still emitted at every step",
}


def make_bench_env(**kwargs: Any):
    """``make_path_follow_env`` with the split's house models compiled up front.

    Module-level (picklable under ``spawn``); the GL context is still created
    lazily at the first render.
    """
    torch.set_num_threads(1)
    env = make_path_follow_env(**kwargs)
    for seed in env.base_env.house_seeds:
        compile_house_model(seed)
    return env


def compile_house_model(seed: int) -> None:
    """Compile a house's MuJoCo model now (it is cached with the house), outside any timed loop."""
    house_model(build_house(seed))


def make_bench_env_without_demo_frames(**kwargs: Any):
    """Diagnostic only: :func:`make_bench_env` with ``demo_frames`` excluded from the outputs."""
    from torchrl.envs import ExcludeTransform

    return make_bench_env(**kwargs).append_transform(ExcludeTransform("demo_frames"))


class RandomActionAfterLookup(torch.nn.Module):
    """A random policy that first reads ``demo_frames`` (so a store look-up in front of it is not skipped).

    Module-level (picklable under ``spawn``); actions are uniform over forward/left/right.
    ``demo_frames`` is ``[*batch, n, H, W, 3]``.
    """

    def forward(self, demo_frames: torch.Tensor) -> torch.Tensor:
        return torch.randint(0, NUM_ACTIONS, demo_frames.shape[:-4])


def make_lookup_policy(store_root: str):
    """``store.lookup_module()`` + :class:`RandomActionAfterLookup`, the frames kept out of the batch."""
    from tensordict.nn import TensorDictModule, TensorDictSequential

    store = DemoStore(store_root, verify=False)
    actor = TensorDictModule(RandomActionAfterLookup(), in_keys=["demo_frames"], out_keys=["action"])
    return TensorDictSequential(store.lookup_module(only_where="is_init"), actor, selected_out_keys=["action"])


def median_fps(frames: list[int], seconds: list[float]) -> float:
    """Median over chunks of frames / seconds."""
    return float(statistics.median(f / s for f, s in zip(frames, seconds)))


def bench_raw(house_seed: int, image_size: int, chunks: int, chunk_frames: int, warmup: int, seed: int) -> dict:
    """Pose update (nominal motion with collisions) + render + uint8 HWC tensor, one house."""
    house = build_house(house_seed)
    renderer = FirstPersonRenderer(image_size, image_size)
    rng = np.random.default_rng(seed)
    pose = np.array([[*house.spawn_xy, 0.0]])

    def run(count: int) -> float:
        nonlocal pose
        actions = rng.integers(0, NUM_ACTIONS, size=count)
        start = time.perf_counter()
        for action in actions:
            pose, _ = apply_motion(house, pose, nominal_motion(action)[None])
            torch.from_numpy(renderer.render(house, pose[0]))  # [H, W, 3] uint8, as the env's pixels
        return time.perf_counter() - start

    run(warmup)
    seconds = [run(chunk_frames) for _ in range(chunks)]
    renderer.close()
    fps = median_fps([chunk_frames] * chunks, seconds)
    return {"fps": fps, "frames": chunk_frames * chunks, "seconds": sum(seconds), "render_ms_per_frame": 1e3 / fps}


class _Timer:
    """Accumulates the time spent in a wrapped bound method."""

    def __init__(self, owner: Any, name: str) -> None:
        self.seconds = 0.0
        self.calls = 0
        method = getattr(owner, name)

        def wrapped(*args, **kwargs):
            start = time.perf_counter()
            try:
                return method(*args, **kwargs)
            finally:
                self.seconds += time.perf_counter() - start
                self.calls += 1

        setattr(owner, name, wrapped)

    def reset(self) -> None:
        self.seconds, self.calls = 0.0, 0


def bench_env_step(env_kwargs: dict, chunks: int, chunk_frames: int, warmup: int, seed: int) -> tuple[dict, dict]:
    """One unbatched env in a ``step_and_maybe_reset`` loop, with a time breakdown (the profile)."""
    env = make_bench_env(**env_kwargs)
    env.set_seed(seed)
    generator = torch.Generator().manual_seed(seed)
    base = env.base_env
    timers = {name: _Timer(base, name) for name in ("_step", "_reset", "_render", "_observation")}
    noise_timer = _Timer(env.transform[0], "_inv_call")
    demo_length = base.demo_length
    tensordict = env.reset()

    def run(count: int) -> tuple[float, int]:
        nonlocal tensordict
        actions = torch.randint(0, NUM_ACTIONS, (count,), generator=generator)
        resets = 0
        start = time.perf_counter()
        for action in actions:
            tensordict.set("action", action)
            tensordict, next_tensordict = env.step_and_maybe_reset(tensordict)
            resets += int(tensordict.get(("next", "done")))
            tensordict = next_tensordict
        return time.perf_counter() - start, resets

    run(warmup)
    for timer in (*timers.values(), noise_timer):
        timer.reset()
    results = [run(chunk_frames) for _ in range(chunks)]
    seconds = [r[0] for r in results]
    resets = sum(r[1] for r in results)
    frames = chunk_frames * chunks
    total = sum(seconds)
    # _render is called once per step and once per reset (demo frames), _observation likewise
    reset_seconds, step_seconds = timers["_reset"].seconds, timers["_step"].seconds
    frames_rendered = frames + timers["_reset"].calls * demo_length  # step frames + demo frames at reset
    profile = {
        "steps": frames,
        "resets": resets,
        "steps_per_episode": frames / max(resets, 1),
        "ms_per_step_total": 1e3 * total / frames,
        "ms_per_reset": 1e3 * reset_seconds / max(timers["_reset"].calls, 1),
        "reset_ms_per_step_amortised": 1e3 * reset_seconds / frames,
        "base_env_step_ms": 1e3 * step_seconds / frames,
        "render_ms_per_frame_in_env": 1e3 * timers["_render"].seconds / frames_rendered,
        "observation_ms_per_call": 1e3 * timers["_observation"].seconds / max(timers["_observation"].calls, 1),
        "actuation_noise_ms_per_step": 1e3 * noise_timer.seconds / frames,
        "torchrl_overhead_ms_per_step": 1e3 * (total - step_seconds - reset_seconds - noise_timer.seconds) / frames,
    }
    env.close(raise_if_closed=False)
    result = {
        "fps": median_fps([chunk_frames] * chunks, seconds),
        "frames": frames,
        "seconds": total,
        "demo_frames": resets * demo_length,
        "rendered_fps": (frames + resets * demo_length) / total,
    }
    return result, profile


def bench_collector(make_collector: Callable[[], Any], demo_length: int, chunks: int, warmup_batches: int) -> dict:
    """Median frames/s over ``chunks`` batches after discarding ``warmup_batches``.

    ``demo_length`` > 0: demonstrations are rendered at each reset (``rendered_fps`` counts them).
    """
    collector = make_collector()
    frames, seconds, demo_frames = [], [], 0
    iterator = iter(collector)
    try:
        for _ in range(warmup_batches):
            next(iterator)
        start = time.perf_counter()
        for _ in range(chunks):
            batch = next(iterator)
            now = time.perf_counter()
            frames.append(batch.numel())
            seconds.append(now - start)
            demo_frames += int(batch.get(("next", "done")).sum()) * demo_length
            start = now
    finally:
        collector.shutdown()
    total_frames, total_seconds = sum(frames), sum(seconds)
    result = {
        "fps": median_fps(frames, seconds),
        "frames": total_frames,
        "seconds": total_seconds,
        "frames_per_batch": frames[0],
    }
    if demo_length:
        result["demo_frames"] = demo_frames
        result["rendered_fps"] = (total_frames + demo_frames) / total_seconds
    return result


@dataclass(frozen=True)
class BenchConfig:
    """What the command line sets: frame size, houses, demonstrations, seed, length of the run."""

    image_size: int = 64
    num_houses: int = 4
    demo_length: int = 30
    seed: int = 0
    quick: bool = False
    #: Demo store directory prefix: the store goes to ``<prefix>-h<houses>-n<demo length>-s<size>``.
    demo_store_prefix: Path = REPO_ROOT / "runs" / "bench_env" / "demo_store"

    @property
    def chunks(self) -> int:
        return QUICK_CHUNKS if self.quick else CHUNKS

    @property
    def scale(self) -> float:
        """Factor on chunk and batch sizes."""
        return QUICK_SCALE if self.quick else 1.0

    @property
    def env_kwargs(self) -> dict:
        return {
            "noise": "paper",
            "split": "train",
            "num_houses": self.num_houses,
            "demo_length": self.demo_length,
            "image_size": self.image_size,
        }

    @property
    def store_root(self) -> Path:
        prefix = self.demo_store_prefix
        return prefix.with_name(f"{prefix.name}-h{self.num_houses}-n{self.demo_length}-s{self.image_size}")

    def frames(self, base: int) -> int:
        """A chunk or batch size, frames, scaled for ``quick``."""
        return int(base * self.scale)


class BenchPaths:
    """Every path of the benchmark, run by name with :meth:`run`.

    Creating it builds one env in this process (the first house's seed for the raw
    loop). ``store_info`` describes the demo store once a store path has built or
    reopened it (empty until then).
    """

    def __init__(self, config: BenchConfig) -> None:
        self.config = config
        self.store_info: dict = {}
        self.env_kwargs = config.env_kwargs
        self.make_single = partial(make_bench_env, **self.env_kwargs)
        self.make_batched = partial(make_bench_env, num_agents=NUM_AGENTS, **self.env_kwargs)
        self.house_seed = self.make_single().base_env.house_seeds[0]

    def run(self, name: str) -> tuple[dict, dict]:
        """The result of path ``name`` and the single env's profile (empty but for ``env_step``)."""
        config, chunks = self.config, self.config.chunks
        if name == "raw":
            return bench_raw(
                self.house_seed, config.image_size, chunks, config.frames(RAW_CHUNK_FRAMES), WARMUP_FRAMES, config.seed
            ), {}
        if name == "env_step":
            return bench_env_step(self.env_kwargs, chunks, config.frames(ENV_STEP_CHUNK_FRAMES), WARMUP_FRAMES, config.seed)
        make_collector, warmup_batches, samples_demos = self._collectors()[name]
        demo_length = config.demo_length if samples_demos else 0
        return bench_collector(make_collector, demo_length, chunks, warmup_batches), {}

    def _collectors(self) -> dict[str, tuple[Callable[[], Any], int, bool]]:
        """Collector factory, warm-up batches, and whether episodes render a demonstration at reset."""
        return {
            "collector_single": (self._collector_single, 2, True),
            "collector_batched8": (partial(self._collector_batched, self.make_batched), 1, True),
            "collector_parallel2": (self._collector_parallel, 2, True),
            "multisync_2x_batched8": (self._multisync, 1, True),
            "diag_batched8_no_demo_frames": (partial(self._collector_batched, self._make_without_demo_frames()), 1, True),
            # with a demo store: demonstrations are pre-rendered
            "collector_batched8_store": (self._collector_batched_store, 1, False),
            "multisync_2x_batched8_store": (partial(self._multisync_store, False), 1, False),
            "multisync_2x_batched32_store": (partial(self._multisync_store, False, NUM_AGENTS_LARGE), 1, False),
            "multisync_2x_batched32_store_lookup": (self._multisync_store_lookup, 1, False),
            "multisync_2x_batched8_store_frames": (partial(self._multisync_store, True), 1, False),
        }

    def _make_without_demo_frames(self):
        return partial(make_bench_env_without_demo_frames, num_agents=NUM_AGENTS, **self.env_kwargs)

    def _collector_single(self):
        from torchrl.collectors import Collector

        return Collector(self.make_single, None, frames_per_batch=self.config.frames(SINGLE_BATCH_FRAMES), total_frames=-1)

    def _collector_batched(self, make_env: Callable[[], Any]):
        from torchrl.collectors import Collector

        return Collector(make_env, None, frames_per_batch=self.config.frames(BATCHED_BATCH_FRAMES), total_frames=-1)

    def _collector_parallel(self):
        from torchrl.collectors import Collector
        from torchrl.envs import ParallelEnv

        # Shared-memory buffers (torchrl's default). metadata_from_workers=True would force
        # use_buffers=False: then every step_and_maybe_reset sends (td, next_td) through the
        # worker's pipe unconsolidated, i.e. ~32 tensors pickled as shared-memory file
        # descriptors, which ran at about 59 frames/s on this machine.
        env = ParallelEnv(NUM_WORKERS, self.make_single)
        return Collector(env, None, frames_per_batch=self.config.frames(PARALLEL_BATCH_FRAMES), total_frames=-1)

    def _multisync(self):
        from torchrl.collectors import MultiSyncCollector

        frames_per_batch = self.config.frames(MULTISYNC_BATCH_FRAMES)
        return MultiSyncCollector([self.make_batched] * NUM_WORKERS, None, frames_per_batch=frames_per_batch, total_frames=-1)

    def _store_env_kwargs(self, emit_demo_frames: bool) -> dict:
        """Env kwargs with the demo store, built (or reopened) on first use."""
        root = self.config.store_root
        if not self.store_info:
            start = time.perf_counter()
            existed = (root / "meta.json").exists()
            store_config = DemoStoreConfig(
                EpisodeSpec(split="train", num_houses=self.config.num_houses, demo_length=self.config.demo_length,
                            image_size=self.config.image_size),
                num_demos=BENCH_STORE_DEMOS,
            )
            DemoStore.build(root, store_config, progress=True)
            try:
                shown_root = str(root.resolve().relative_to(REPO_ROOT))
            except ValueError:  # a store outside the repository
                shown_root = str(root)
            self.store_info.update(
                root=shown_root,
                num_demos=BENCH_STORE_DEMOS,
                build_seconds=None if existed else time.perf_counter() - start,
                reused=existed,
            )
        return {**self.env_kwargs, "demo_store": str(root), "emit_demo_frames": emit_demo_frames}

    def _collector_batched_store(self):
        return self._collector_batched(partial(make_bench_env, num_agents=NUM_AGENTS, **self._store_env_kwargs(False)))

    def _multisync_store(self, emit_demo_frames: bool, num_agents: int = NUM_AGENTS):
        from torchrl.collectors import MultiSyncCollector

        make = partial(make_bench_env, num_agents=num_agents, **self._store_env_kwargs(emit_demo_frames))
        frames_per_batch = max(self.config.frames(MULTISYNC_BATCH_FRAMES), NUM_WORKERS * num_agents * MAX_EPISODE_STEPS)
        return MultiSyncCollector([make] * NUM_WORKERS, None, frames_per_batch=frames_per_batch, total_frames=-1)

    def _multisync_store_lookup(self):
        from torchrl.collectors import MultiSyncCollector

        make = partial(make_bench_env, num_agents=NUM_AGENTS_LARGE, **self._store_env_kwargs(False))
        policy = make_lookup_policy(str(self.config.store_root))
        return MultiSyncCollector([make] * NUM_WORKERS, policy, frames_per_batch=LOOKUP_BATCH_FRAMES, total_frames=-1)
