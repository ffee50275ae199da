"""A taught route repeated by a policy, then video, map and JSON (``recipes/teach.py`` is the command line).

* :func:`repeat_route`: a batched :class:`~envs.nav_env.PathFollowEnv` of one agent
  per repeat, every agent playing the taught demonstration under its own actuation
  noise (the env seed fixes each repeat's episode seed, and so its noise), driven by
  the greedy policy in one ``env.rollout`` (the path of
  :func:`~spf_rl.evaluation.record_rollout`, batched); with ``task="homing"``
  the env plays the route's homing episode (:mod:`envs.homing`: from the route's end
  back to its start, the memory rendered looking back) and says which demonstration
  it played;
* :func:`write_video`: the demonstration's first-person view beside a repeat's,
  and the map with both paths, step by step (MP4 where a codec is present, GIF
  otherwise: :func:`spf_rl.viz.write_video`);
* :func:`write_map`: the top-down map with the demonstration and every repeat;
* :func:`results`: the JSON content: the route, the set-up and success and SPL per repeat
  (and, for homing, the demonstration the env played);
* :class:`TeachOptions` and :func:`teach_and_repeat`: a whole run of ``recipes/teach.py``
  after the route is taught: the repeats, then the map, the video and the JSON in the
  output directory.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type
from tqdm.auto import tqdm

from envs.atomic_io import atomic_write_json
from envs.conditions import parse_conditions
from envs.demos import Demonstration
from envs.episode_spec import EpisodeSpec
from envs.episodes import episode_record
from envs.factory import make_env
from envs.follow import default_max_steps, success_radius
from envs.homing import FOLLOW, HOMING
from envs.render import draw_top_down_map
from envs.scenes import build_house, split_seeds
from envs.transforms import DEFAULT_NOISE, NOISE_PRESETS
from envs.user_demos import ACTION_LETTERS
from spf_rl.evaluation import greedy_on_device
from spf_rl.metrics import summarize
from spf_rl.modules.views import policy_for_length
from spf_rl.viz import figure_to_array, pyplot, write_figure
from spf_rl.viz import write_video as write_frames

logger = logging.getLogger(__name__)

#: Frames per second of the side-by-side video.
VIDEO_FPS = 4
#: Size of a video frame, inches at VIDEO_DPI: 800 x 288 pixels (multiples of 16 for MP4).
VIDEO_FIGSIZE_IN = (10.0, 3.6)
VIDEO_DPI = 80
#: Resolution of the map PNG, dots per inch.
MAP_DPI = 110
#: Font size of the map's title, points.
TITLE_FONTSIZE = 10
#: Drawing order of the demonstration on the map (above the repeats' lines).
DEMO_ZORDER = 5
#: Letter of each action in the JSON (the ``--actions`` alphabet).
ACTION_LETTER = {action: letter for letter, action in ACTION_LETTERS.items()}
#: The default policy: the route model, trained on planner routes, tours and driven routes of 10-100 steps
#: (docs/results.md); the Table 1 policies follow routes of exactly 30 steps.
DEFAULT_CHECKPOINT = "routes-spf"
#: The default policy with homing: SPF 0.8 trained on homing episodes (python recipes/bc.py --preset bc_homing).
DEFAULT_HOMING_CHECKPOINT = "homing-spf-s0.8"
#: The default house: the first house of the test split (never seen in training).
DEFAULT_HOUSE = split_seeds("test")[0]
#: Default and largest number of repeats (one agent each, stepped together).
DEFAULT_REPEATS = 8
MAX_REPEATS = 64
#: Default output directory.
DEFAULT_OUT = "runs/teach"
#: File names written in the output directory.
JSON_NAME, MAP_NAME, VIDEO_STEM = "teach.json", "teach_map.png", "teach"


@dataclass(frozen=True)
class TeachOptions:
    """The set-up of a teach-and-repeat run, checked when made (messages name ``recipes/teach.py``'s options).

    Attributes:
        house: house seed (default: the first test house).
        noise: actuation-noise preset of the repeats.
        seed: seed of the repeats' noise.
        repeats: repeats, 1 to :data:`MAX_REPEATS`.
        out: output directory (made by :func:`teach_and_repeat`).
        checkpoint: a shipped name or a ``.pt`` path; ``None``: :data:`DEFAULT_CHECKPOINT`,
            or :data:`DEFAULT_HOMING_CHECKPOINT` with ``homing``.
        homing: bring the route home (from its end back to its start) instead of repeating it.
        video: write the video (the slowest output).
        progress: show a progress bar.

    Raises:
        ValueError: a value out of range, naming the option and the allowed values.

    Examples:
        >>> TeachOptions().checkpoint, TeachOptions(homing=True).checkpoint, TeachOptions(homing=True).task
        ('routes-spf', 'homing-spf-s0.8', 'homing')
        >>> TeachOptions(repeats=0)
        Traceback (most recent call last):
        ...
        ValueError: --repeats must be in [1, 64], got 0.
    """

    house: int = DEFAULT_HOUSE
    noise: str = DEFAULT_NOISE
    seed: int = 0
    repeats: int = DEFAULT_REPEATS
    out: Path = field(default_factory=lambda: Path(DEFAULT_OUT))
    checkpoint: str | None = None
    homing: bool = False
    video: bool = True
    progress: bool = True
    conditions: str | None = None

    def __post_init__(self) -> None:
        try:
            mixture = parse_conditions(self.conditions)
        except ValueError as err:
            raise ValueError(f"--{err}") from None
        object.__setattr__(self, "conditions", None if mixture is None else mixture.spec)
        if self.noise not in NOISE_PRESETS:
            raise ValueError(f"--noise must be one of {', '.join(sorted(NOISE_PRESETS))}, got {self.noise!r}.")
        if self.seed < 0:
            raise ValueError(f"--seed must be a non-negative int, got {self.seed}.")
        if not 1 <= self.repeats <= MAX_REPEATS:
            raise ValueError(f"--repeats must be in [1, {MAX_REPEATS}], got {self.repeats}.")
        if self.house < 0:
            raise ValueError(f"--house must be a non-negative int (a house seed), got {self.house}.")
        object.__setattr__(self, "out", Path(self.out))
        if self.out.exists() and not self.out.is_dir():
            raise ValueError(f"--out must be a directory, but {self.out} is a file.")
        if self.checkpoint is None:
            object.__setattr__(self, "checkpoint", DEFAULT_HOMING_CHECKPOINT if self.homing else DEFAULT_CHECKPOINT)

    @property
    def task(self) -> str:
        """The env's task: ``"homing"`` with :attr:`homing`, else ``"follow"``."""
        return HOMING if self.homing else FOLLOW


@dataclass
class Repeat:
    """One repeat of the route by the policy.

    Attributes:
        record: ``repeat`` (from 1) and :func:`~envs.episodes.episode_record`'s keys
            (``success``, ``spl``, ``goal_distance``, ``path_length``, ``steps``, ...; metres).
        poses: ``(T + 1, 3)`` poses (x m, y m, heading rad): the start, then after each step.
        frames: ``(T + 1, H, W, 3)`` uint8 first-person frames at those poses.

    Examples:
        >>> repeat = Repeat({"repeat": 1, "success": True}, np.zeros((3, 3)), np.zeros((3, 64, 64, 3), np.uint8))
        >>> repeat.record["repeat"], repeat.poses.shape[0] == repeat.frames.shape[0]
        (1, True)
    """

    record: dict
    poses: np.ndarray
    frames: np.ndarray
    house: object = None


def repeat_route(
    policy,
    demo: Demonstration,
    *,
    repeats: int,
    noise: str,
    seed: int,
    max_steps: int,
    image_size: int,
    progress: bool = True,
    task: str = FOLLOW,
    demo_length: int | None = None,
    conditions: str | None = None,
) -> tuple[list[Repeat], np.ndarray, Demonstration]:
    """The policy follows ``demo`` (or brings it home) ``repeats`` times under ``noise``, greedily.

    Args:
        policy: an SPF-family policy (:func:`spf_rl.load_policy`), in eval mode.
        demo: the taught demonstration (of up to ``demo_length`` steps).
        repeats: how many times (one agent each, stepped together).
        noise: actuation-noise preset.
        seed: env seed: the same seed gives the same repeats.
        max_steps: episode limit, steps.
        image_size: frame side, pixels (the policy's).
        progress: show a progress bar over the steps.
        task: ``"follow"`` (repeat the route) or ``"homing"`` (return from its end to its start).
        demo_length: the env's (and the policy's) demonstration length, to which a shorter
            route is padded (the policy reads ``demo_steps``); ``None``: the route's own.
        conditions: the world of the repeats (:mod:`envs.conditions`, e.g. ``"light@1"``): each
            repeat draws its change from its own episode seed; ``None``: the teaching world.

    Returns:
        (the repeats, in agent order; the played demonstration's ``(n, H, W, 3)`` frames;
        the demonstration the env played: ``demo`` itself, or its homing demonstration).
    """
    spec = EpisodeSpec(
        house_seeds=(demo.house_seed,), noise=noise, demo_length=demo.length if demo_length is None else demo_length,
        max_steps=max_steps, image_size=image_size, task=task, seed=seed, conditions=conditions,
    )
    env = make_env(spec, repeats, primer=policy.make_tensordict_primer(), seeded=True, demonstrations=[demo])
    base = env.base_env
    bar = tqdm(total=max_steps, desc=f"{repeats} repeats", unit="step", disable=not progress)
    try:
        with torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            start = env.reset()
            houses = base.houses  # the world each repeat runs in (changed by ``conditions``)
            # lazy stack: the demo frames every step holds are not copied max_steps times
            rollout = env.rollout(
                max_steps,
                greedy_on_device(policy),
                auto_reset=False,
                tensordict=start,
                break_when_any_done=False,
                return_contiguous=False,
                callback=lambda *_: bar.update(1),
            )
    finally:
        bar.update(bar.total - bar.n)  # the last step calls no callback
        bar.close()
        env.close()
    done = rollout.get(("next", "done")).reshape(repeats, -1)
    pose, next_pose = rollout.get("pose"), rollout.get(("next", "pose"))
    pixels, next_pixels = rollout.get("pixels"), rollout.get(("next", "pixels"))
    out = []
    for agent in range(repeats):
        last = int(torch.nonzero(done[agent])[0, 0])  # every agent's first episode ends by max_steps
        final = rollout[agent, last].get("next")
        out.append(
            Repeat(
                record={"repeat": agent + 1, **episode_record(final)},
                poses=torch.cat([pose[agent, : last + 1], next_pose[agent, last : last + 1]]).numpy().astype(np.float64),
                frames=torch.cat([pixels[agent, : last + 1], next_pixels[agent, last : last + 1]]).numpy(),
                house=houses[agent],
            )
        )
    return out, rollout[0, 0].get("demo_frames")[: demo.length].numpy(), base.demonstrations[0]


def route_letters(demo: Demonstration) -> str:
    """The demonstration's actions as ``--actions`` letters (``"FFLR..."``)."""
    return "".join(ACTION_LETTER[int(action)] for action in demo.actions)


def success_radius_m(demo: Demonstration) -> float:
    """The follow protocol's success radius around the end of the demonstration played, metres."""
    return float(success_radius(demo.shortest_length_m))


def demo_label(demo: Demonstration) -> str:
    """How the map and the video name the demonstration played."""
    return "demonstration, driven back" if demo.task == HOMING else "demonstration"


def write_map(demo: Demonstration, repeats: list[Repeat], path: Path, title: str) -> Path:
    """The top-down map with the demonstration played, every repeat and the success radius, as a PNG:
    the house as repeat 1 found it (its furniture moved, under ``furniture`` conditions)."""
    pyplot()  # matplotlib, or an ImportError that says how to install it
    from matplotlib.patches import Circle

    paths = {demo_label(demo): demo.poses[:, :2]}
    for repeat in repeats:
        outcome = "success" if repeat.record["success"] else "failure"
        paths[f"repeat {repeat.record['repeat']} ({outcome})"] = repeat.poses[:, :2]
    house = repeats[0].house if repeats and repeats[0].house is not None else build_house(demo.house_seed)
    ax = draw_top_down_map(house, paths=paths, title=title)
    ax.lines[0].set_zorder(DEMO_ZORDER)  # the demonstration on top of the repeats
    ax.title.set_fontsize(TITLE_FONTSIZE)
    ax.add_patch(Circle(demo.end_xy, success_radius_m(demo), fill=False, linestyle="--", color="black"))
    ax.figure.tight_layout()
    return write_figure(ax.figure, path, dpi=MAP_DPI)


def write_video(demo: Demonstration, demo_frames: np.ndarray, repeat: Repeat, path: Path, noise: str) -> Path:
    """The demonstration's view, the repeat's view and the map with both paths, step by step.

    The demonstration shows frame ``min(t, n - 1)`` at step ``t`` (it holds its last
    frame while the repeat goes on); the file is MP4 where imageio has its ffmpeg
    codec, GIF otherwise.
    """
    plt = pyplot()
    demo_xy, repeat_xy = demo.poses[:, :2], repeat.poses[:, :2]
    fig, (left, middle, right) = plt.subplots(1, 3, figsize=VIDEO_FIGSIZE_IN, dpi=VIDEO_DPI)
    demo_view = left.imshow(demo_frames[0], interpolation="nearest")
    repeat_view = middle.imshow(repeat.frames[0], interpolation="nearest")
    for ax in (left, middle):
        ax.set_axis_off()
    draw_top_down_map(build_house(demo.house_seed), paths={demo_label(demo): demo_xy}, ax=right)
    (trail,) = right.plot(repeat_xy[:1, 0], repeat_xy[:1, 1], "-", linewidth=2, label=f"repeat {repeat.record['repeat']}")
    (demo_at,) = right.plot(demo_xy[:1, 0], demo_xy[:1, 1], "o", color="tab:blue", markersize=4)
    right.legend(loc="upper right", fontsize=7)
    outcome = f"{'success' if repeat.record['success'] else 'failure'}, SPL {repeat.record['spl']:.2f}"
    frames = []
    for step in range(max(len(demo_frames), len(repeat.frames))):
        shown = min(step, len(demo_frames) - 1)
        demo_view.set_data(demo_frames[shown])
        left.set_title(f"{demo_label(demo)}, step {shown}/{len(demo_frames) - 1}", fontsize=9)
        demo_at.set_data(demo_xy[shown : shown + 1, 0], demo_xy[shown : shown + 1, 1])
        here = min(step, len(repeat.frames) - 1)
        repeat_view.set_data(repeat.frames[here])
        middle.set_title(f"repeat {repeat.record['repeat']} ({noise} noise), step {here}", fontsize=9)
        trail.set_data(repeat_xy[: here + 1, 0], repeat_xy[: here + 1, 1])
        right.set_title(outcome if here == len(repeat.frames) - 1 else "", fontsize=9)
        frames.append(figure_to_array(fig))
    plt.close(fig)
    return write_frames(frames, path, fps=VIDEO_FPS)


def route_json(demo: Demonstration) -> dict:
    """A demonstration in the JSON: house, start, actions (``--actions`` letters), end, lengths, success radius."""
    start = demo.start_pose
    return {
        "house": demo.house_seed,
        "start": [float(start[0]), float(start[1]), float(np.degrees(start[2]))],
        "start_units": "x m, y m, heading deg",
        "actions": route_letters(demo),
        "steps": demo.length,
        "end_xy_m": [float(v) for v in demo.end_xy],
        "shortest_length_m": float(demo.shortest_length_m),
        "success_radius_m": success_radius_m(demo),
    }


def results(demo: Demonstration, repeats: list[Repeat], setup: dict, played: Demonstration | None = None) -> dict:
    """The JSON content: the set-up, the route (enough to replay it with ``--actions``), each repeat, a summary.

    ``played``: the demonstration the env played when it is not the route (homing),
    written as ``"homing"``: its start is the route's end, its end the route's start.
    """
    content = {**setup, "route": route_json(demo)}
    if played is not None and played is not demo:
        content[played.task] = route_json(played)
    content["repeats"] = [repeat.record for repeat in repeats]
    content["summary"] = summarize([repeat.record for repeat in repeats])
    return content


def teach_and_repeat(policy, demo: Demonstration, options: TeachOptions, *, image_size: int) -> dict:
    """Repeat the taught route (or bring it home) and write the map, the video and the JSON in ``options.out``.

    Args:
        policy: the policy of ``options.checkpoint`` (:func:`spf_rl.load_policy`), in eval mode.
        demo: the taught demonstration (:func:`spf_rl.teach.route.teach_route`), of any length: a
            shorter one than the policy's ``demo_length`` is padded, and the policy is built for a
            longer one (:func:`~spf_rl.modules.views.policy_for_length`, the same weights).
        options: the run's set-up.
        image_size: frame side, pixels (the policy's).

    Returns:
        The JSON content written to :data:`JSON_NAME` (:func:`results`, with ``"files"``: the
        names of the map and, unless ``options.video`` is false, the video).
    """
    out = options.out
    out.mkdir(parents=True, exist_ok=True)
    task, max_steps = options.task, default_max_steps(demo.length)
    demo_length = max(demo.length, policy.config.demo_length)
    if demo_length != policy.config.demo_length:
        policy = policy_for_length(policy, demo_length)
    logger.info("route: %d steps, %.2f m; %s %s it %d times under %s noise", demo.length, demo.shortest_length_m,
                options.checkpoint, "brings it home" if options.homing else "repeats", options.repeats, options.noise)
    repeats, demo_frames, played = repeat_route(
        policy, demo, repeats=options.repeats, noise=options.noise, seed=options.seed, max_steps=max_steps,
        image_size=image_size, progress=options.progress, task=task, demo_length=demo_length, conditions=options.conditions,
    )
    setup = {"checkpoint": options.checkpoint, "task": task, "noise": options.noise, "seed": options.seed, "max_steps": max_steps}
    if options.conditions is not None:
        setup["conditions"] = options.conditions
    content = results(demo, repeats, setup, played)
    successes = sum(r.record["success"] for r in repeats)
    what = "bring it home" if options.homing else "succeed"
    world = "" if options.conditions is None else f", {options.conditions}"
    title = f"house {demo.house_seed}: {successes}/{len(repeats)} repeats {what} ({options.noise} noise{world})"
    logger.info("drawing the map")
    files = {"map": write_map(played, repeats, out / MAP_NAME, title).name}
    if options.video:
        logger.info("writing the video")
        files["video"] = write_video(played, demo_frames, repeats[0], out / VIDEO_STEM, options.noise).name
    content["files"] = files
    atomic_write_json(out / JSON_NAME, content)
    return content
