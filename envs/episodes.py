"""Episode loops: numbered episodes of a batched env played through a TorchRL collector.

:func:`run_episodes` plays a fixed, seed-determined set of episodes and returns one
record per episode (:func:`episode_record`: success, SPL, path fidelity, distances);
the evaluation of trained policies (:mod:`spf_rl.evaluation`), the expert and
open-loop figures (:mod:`spf_rl.eval.scripted`) and the taught routes' repeats use it.
:func:`record_episodes` does the same from a collector the caller built.
:func:`play_episode_steps` and :func:`gather_episode_steps` keep every step of each
episode (BC datasets, DAgger rounds).
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.collectors import Collector
from torchrl.envs.utils import ExplorationType
from tqdm.auto import tqdm


def episode_record(final: TensorDictBase) -> dict:
    """How an episode ended, from one agent's last ``"next"`` tensordict.

    Returns:
        success, success_lab, spl, goal_distance (m), path_length (m), shortest_path_length (m),
        ndtw, sdtw, path_length_ratio, wall_hits (:mod:`envs.path_fidelity`), steps, demo_steps
        (the demonstration's own length), episode_seed and house_seed (the house the episode was played in, the key
        of per-house statistics such as :func:`spf_rl.stats.hierarchical_bootstrap_ci`),
        as Python scalars.
    """
    return {
        "success": bool(final["success"].item()),
        "success_lab": bool(final["success_lab"].item()),
        "spl": float(final["spl"].item()),
        "goal_distance": float(final["goal_distance"].item()),
        "path_length": float(final["path_length"].item()),
        "shortest_path_length": float(final["shortest_path_length"].item()),
        "ndtw": float(final["ndtw"].item()),
        "sdtw": float(final["sdtw"].item()),
        "path_length_ratio": float(final["path_length_ratio"].item()),
        "wall_hits": int(final["wall_hits"].item()),
        "steps": int(final["step_count"].item()),
        "demo_steps": int(final["demo_steps"].item()),
        "episode_seed": int(final["episode_seed"].item()),
        "house_seed": int(final["house_seed"].item()),
    }


#: Steps each agent takes per collector batch in :func:`run_episodes` (at most this many
#: minus one steps are taken past an agent's last recorded episode).
STEPS_PER_BATCH = 5


def _episode_collector(env, policy, caller: str) -> Collector:
    """The collector that plays a batched env's numbered episodes: :data:`STEPS_PER_BATCH`
    steps per agent a batch, auto-reset, preallocated buffers, deterministic exploration."""
    if len(env.batch_size) != 1:
        raise ValueError(f"{caller} needs a batched env (batch_size [N]), got {list(env.batch_size)}.")
    return Collector(
        env,
        policy,
        frames_per_batch=env.batch_size[0] * STEPS_PER_BATCH,
        total_frames=-1,
        exploration_type=ExplorationType.DETERMINISTIC,
        use_buffers=True,
        auto_register_policy_transforms=False,
    )


def run_episodes(env, policy, num_episodes: int, progress: bool = False) -> list[dict]:
    """Play episodes ``0 .. num_episodes - 1`` of a seeded batched env with ``policy``, through a TorchRL collector.

    The env numbers its episodes (:mod:`envs.episode_numbering`): agent ``i`` of ``N``
    plays episodes ``i, i + N, i + 2N, ...``, and episode ``j`` depends only on the env
    seed and ``j``. A :class:`~torchrl.collectors.Collector` steps the env (auto-reset,
    preallocated buffers, deterministic exploration) in batches of
    :data:`STEPS_PER_BATCH` steps per agent until every episode below ``num_episodes``
    has ended; each is recorded once, by its number, and later ones are ignored. So
    every policy is scored on the same episodes, whatever ``N``, and short episodes are
    not over-represented.

    Args:
        env: a seeded batched :class:`~envs.nav_env.PathFollowEnv` (``num_agents`` set),
            possibly wrapped in transforms (actuation noise, primers, ...). The
            collector resets it first; it is left open.
        policy: a TensorDict policy (or callable) writing ``"action"``.
        num_episodes: number of episodes (> 0).
        progress: show a progress bar.

    Returns:
        one dict per episode, ordered by episode number: ``episode_index``, success,
        spl, goal_distance, path_length, shortest_path_length, steps, episode_seed, house_seed.
    """
    if isinstance(num_episodes, bool) or not isinstance(num_episodes, int) or num_episodes <= 0:
        raise ValueError(f"num_episodes must be an int > 0, got {num_episodes!r}.")
    collector = _episode_collector(env, policy, "run_episodes")
    try:
        return record_episodes(collector, num_episodes, progress)
    finally:
        collector.shutdown(close_env=False)


def record_episodes(collector, num_episodes: int, progress: bool = False) -> list[dict]:
    """Iterate ``collector`` until episodes ``0 .. num_episodes - 1`` have all ended, and
    record each once, by the number its env gave it (``episode_index``): the loop of
    :func:`run_episodes`, for any collector over numbered envs (several worker processes
    whose envs share one numbering, ``episode_offset=w``, ``episode_stride=W``). The caller
    shuts the collector down.

    Returns:
        one dict per episode, ordered by episode number (as :func:`run_episodes`).
    """
    records: dict[int, dict] = {}
    bar = tqdm(total=num_episodes, disable=not progress, desc="episodes")
    try:
        for batch in collector:
            final_steps = batch.get("next")[batch.get(("next", "done")).squeeze(-1)]
            for final in final_steps.unbind(0):
                number = int(final["episode_index"].item())
                if number < num_episodes and number not in records:
                    records[number] = {"episode_index": number, **episode_record(final)}
                    bar.update(1)
            if len(records) == num_episodes:
                break
    finally:
        bar.close()
    return [records[number] for number in range(num_episodes)]


def play_episode_steps(
    env,
    policy,
    first: int,
    count: int,
    step_keys: Sequence[str],
    max_steps: int,
    episode_keys: Sequence[str] = ("episode_seed",),
    progress: bool = False,
) -> TensorDict:
    """Play the numbered episodes ``first .. first + count - 1`` of a seeded batched env
    with ``policy`` through a TorchRL collector and keep every step of them.

    The env's numbering (:mod:`envs.episode_numbering`) must reach them: with
    ``numbering.offset = first`` and stride 1, its ``N`` agents play them in turn (agent
    ``i`` plays ``first + i``, ``first + i + N``, ...). A
    :class:`~torchrl.collectors.Collector` steps the env in batches of
    :data:`STEPS_PER_BATCH` steps per agent; :func:`gather_episode_steps` keeps the steps.

    Args:
        env: a seeded batched :class:`~envs.nav_env.PathFollowEnv` (possibly transformed).
        policy: a TensorDict policy writing ``"action"``.
        first, count, step_keys, max_steps, episode_keys, progress: as :func:`gather_episode_steps`.

    Returns:
        as :func:`gather_episode_steps`.
    """
    _check_count(count)
    collector = _episode_collector(env, policy, "play_episode_steps")
    try:
        return gather_episode_steps(collector, first, count, step_keys, max_steps, episode_keys, progress)
    finally:
        collector.shutdown(close_env=False)


def _check_count(count: int) -> None:
    if isinstance(count, bool) or not isinstance(count, int) or count <= 0:
        raise ValueError(f"count must be an int > 0, got {count!r}.")


def gather_episode_steps(
    collector,
    first: int,
    count: int,
    step_keys: Sequence[str],
    max_steps: int,
    episode_keys: Sequence[str] = ("episode_seed",),
    progress: bool = False,
) -> TensorDict:
    """Iterate ``collector`` until the numbered episodes ``first .. first + count - 1`` have
    all ended, and keep every step of them (steps of other episodes are dropped).

    ``collector`` is any TorchRL collector over numbered envs that reach those episodes:
    one batched env, or the envs of several worker processes or Ray actors sharing one
    numbering (env ``w`` of ``W`` with ``episode_offset = first + w``, stride ``W``).
    Each step lands in its episode's row at its ``step_count``, so the result does not
    depend on the number of collectors, envs or agents. The caller shuts the collector down.

    Args:
        collector: the collector (its batches hold ``episode_index`` and ``step_count``).
        first: number of the first episode.
        count: number of episodes (> 0).
        step_keys: keys of the root tensordict kept at every step (``"action"`` included).
        max_steps: the envs' episode limit (the padded length).
        episode_keys: integer observations kept once per episode (read at its last step).
        progress: show a progress bar.

    Returns:
        a ``[count]`` TensorDict ordered by episode number: ``steps`` (``[count, max_steps]``:
        ``step_keys``, ``mask`` of the valid steps, ``is_init``), and per episode
        ``episode_keys``, ``length``, ``success`` and ``spl``.

    Raises:
        RuntimeError: if every env is past episodes that have not been played (a numbering
            that never reaches them), or the collector stops before they have all ended.
    """
    _check_count(count)
    steps: TensorDict | None = None
    out = TensorDict(
        {
            **{key: torch.zeros(count, dtype=torch.int64) for key in episode_keys},
            "length": torch.zeros(count, dtype=torch.int64),
            "success": torch.zeros(count, dtype=torch.bool),
            "spl": torch.zeros(count, dtype=torch.float32),
        },
        batch_size=[count],
    )
    ended = torch.zeros(count, dtype=torch.bool)
    bar = tqdm(total=count, disable=not progress, desc="episodes")
    try:
        for batch in collector:
            batch = batch.reshape(-1).to("cpu")
            episode = batch.get("episode_index").reshape(-1) - first
            wanted = (episode >= 0) & (episode < count)
            if not wanted.any():
                if int(episode.min()) >= count:  # every agent is past them: they can never be played
                    missing = (~ended).nonzero().reshape(-1)[:5] + first
                    raise RuntimeError(
                        f"the env's episode numbering never reaches episodes {missing.tolist()}...: set its "
                        f"numbering.offset to {first} (stride 1) before seeding it."
                    )
                continue
            rows, episode = batch[wanted], episode[wanted]
            if steps is None:  # shapes and dtypes from the first kept steps
                steps = TensorDict(
                    {key: torch.zeros(count, max_steps, *rows.get(key).shape[1:], dtype=rows.get(key).dtype) for key in step_keys},
                    batch_size=[count, max_steps],
                )
                steps.set("mask", torch.zeros(count, max_steps, dtype=torch.bool))
            step = rows.get("step_count").reshape(-1)
            for key in step_keys:
                steps.get(key)[episode, step] = rows.get(key).reshape(len(episode), *steps.get(key).shape[2:])
            steps.get("mask")[episode, step] = True
            final = rows.get(("next", "done")).reshape(-1)
            done_rows, done_episodes = rows.get("next")[final], episode[final]
            for key in episode_keys:
                out[key][done_episodes] = done_rows.get(key).reshape(-1)
            out["length"][done_episodes] = step[final] + 1
            out["success"][done_episodes] = done_rows.get("success").reshape(-1)
            out["spl"][done_episodes] = done_rows.get("spl").reshape(-1).float()
            bar.update(int((~ended[done_episodes]).sum()))
            ended[done_episodes] = True
            if ended.all():
                break
    finally:
        bar.close()
    if not ended.all():
        missing = (~ended).nonzero().reshape(-1)[:5] + first
        raise RuntimeError(f"the collector stopped before episodes {missing.tolist()}... ended: give it more total_frames.")
    steps.set("is_init", (torch.arange(max_steps) == 0).expand(count, max_steps).unsqueeze(-1).clone())
    return TensorDict({"steps": steps, **out}, batch_size=[count])


__all__ = ["STEPS_PER_BATCH", "episode_record", "gather_episode_steps", "play_episode_steps", "record_episodes", "run_episodes"]
