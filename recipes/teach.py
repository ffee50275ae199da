"""Teach and repeat: show the agent a route once, then watch a shipped policy repeat it under noise.

Record the route with the keyboard in this terminal (the default: arrow keys,
Enter to finish), or give it headless:

* ``--actions FFLFFR...``: F forward 0.3 m, L turn left 20 deg, R turn right 20 deg,
  driven from ``--start``;
* ``--waypoints "x,y;x,y;..."``: points on the top-down map (metres), joined by the
  planner (the noise-free expert on the house's geodesic graph); the route starts at
  ``--start`` if given, else at the first waypoint facing the second.

The policy follows demonstrations of exactly its ``demo_length`` steps (30 for the
shipped checkpoints): an ``--actions`` or keyboard route must have exactly that many
steps; a ``--waypoints`` route is planned and cropped to its first 30 steps (an error
if the plan is shorter). Routes into a wall, out of the house or ending within the
success radius (0.6 m) of their start are refused with the step or waypoint named.

The policy then repeats the route ``--repeats`` times, each under its own actuation
noise, greedily. With ``--homing`` it brings the route home instead: each repeat
starts at the route's end, facing back along it, and must return to the route's
start, its memory the env's homing demonstration of the route (frames rendered
looking back along it, :mod:`envs.homing`), with ``homing-spf-s0.8`` (SPF 0.8 trained
on homing episodes, ``python recipes/bc.py --preset bc_homing``) unless ``--checkpoint``
says otherwise.
Written to ``--out``:

* ``teach.mp4`` (where ``imageio-ffmpeg`` is installed) or ``teach.gif``: the
  demonstration's view beside repeat 1's, with the map;
* ``teach_map.png``: the top-down map with the demonstration and every repeat;
* ``teach.json``: the route (start and actions, enough to replay it), the set-up, and
  success and SPL per repeat. The same arguments and ``--seed`` give the same JSON.

Usage::

    python recipes/teach.py                                   # keyboard, first test house
    python recipes/teach.py --house 0 --start 7.5,1.5,0 --actions FFFFFFLLLFLFLFFRFFLFFRFFLFFRFR --repeats 8
    python recipes/teach.py --house 0 --waypoints "7.5,1.5;9.5,1.5;9.5,5.5;12.5,5.5" --noise paper_symmetric
    python recipes/teach.py --house 0 --start 7.5,1.5,0 --actions FFFFFFLLLFLFLFFRFFLFFRFFLFFRFR --homing
"""
from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path

from envs.atomic_io import atomic_write_json
from envs.follow import default_max_steps
from envs.homing import FOLLOW, HOMING
from envs.scenes import build_house, split_seeds
from envs.transforms import DEFAULT_NOISE, NOISE_PRESETS
from envs.user_demos import RouteError, check_position, default_start, parse_actions, pose_from_degrees

logger = logging.getLogger("teach")

#: The default policy: the best shipped SPF checkpoint (docs/results.md).
DEFAULT_CHECKPOINT = "spf-s0.8"
#: The default policy with --homing: SPF 0.8 trained on homing episodes (python recipes/bc.py --preset bc_homing).
DEFAULT_HOMING_CHECKPOINT = "homing-spf-s0.8"
#: The default house: the first house of the test split (never seen in training).
DEFAULT_HOUSE = split_seeds("test")[0]
#: Default and largest number of repeats (one agent each, stepped together).
DEFAULT_REPEATS = 8
MAX_REPEATS = 64
#: File names written in --out.
JSON_NAME, MAP_NAME, VIDEO_STEM = "teach.json", "teach_map.png", "teach"


def parse_numbers(text: str, count: int, what: str) -> tuple[float, ...]:
    """``count`` finite comma-separated numbers, or a ``ValueError`` naming ``what`` and the form.

    Examples:
        >>> parse_numbers("7.5, 1.5,90", 3, "--start (x,y,heading)")
        (7.5, 1.5, 90.0)
    """
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise ValueError(f"{what}: expected {count} comma-separated numbers, got {text!r}.")
    return values


def parse_waypoints(text: str) -> list[tuple[float, float]]:
    """``"x,y;x,y;..."`` (metres) -> a list of points.

    Examples:
        >>> parse_waypoints("7.5,1.5; 9.5,1.5")
        [(7.5, 1.5), (9.5, 1.5)]
    """
    return [parse_numbers(p, 2, f"--waypoints point {i}") for i, p in enumerate(text.split(";"), 1) if p.strip()]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="teach.py", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    route = parser.add_mutually_exclusive_group()
    route.add_argument("--actions", help="the route as letters F (forward), L (left), R (right), e.g. FFLFFR")
    route.add_argument("--waypoints", help='points "x,y;x,y;..." in metres, joined by the planner')
    parser.add_argument("--house", type=int, default=DEFAULT_HOUSE, help=f"house seed (default {DEFAULT_HOUSE}, the first test house)")
    parser.add_argument("--start", help="start pose x,y,heading: metres, metres, degrees (0 = +x, counter-clockwise)")
    parser.add_argument("--noise", default=DEFAULT_NOISE, help=f"actuation-noise preset: {', '.join(sorted(NOISE_PRESETS))} (default {DEFAULT_NOISE})")
    parser.add_argument("--seed", type=int, default=0, help="seed of the repeats' noise (default 0)")
    parser.add_argument("--repeats", type=int, default=DEFAULT_REPEATS, help=f"repeats, 1 to {MAX_REPEATS} (default {DEFAULT_REPEATS})")
    parser.add_argument(
        "--checkpoint",
        default=None,
        help=f"a shipped name or a .pt path (default {DEFAULT_CHECKPOINT}; with --homing {DEFAULT_HOMING_CHECKPOINT})",
    )
    parser.add_argument("--out", default="runs/teach", help="output directory (default runs/teach)")
    parser.add_argument("--device", default="auto", help="where the policy runs: auto (CUDA if available, else CPU), cpu, cuda, cuda:N")
    parser.add_argument("--homing", action="store_true", help="bring the route home: from its end back to its start")
    parser.add_argument("--no-video", action="store_true", help="skip the video (the slowest output)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def check_args(parser: argparse.ArgumentParser, args: argparse.Namespace):
    """Validate every argument before any work; ``parser.error`` names the parameter and the allowed values.

    Returns:
        ``(house, start or None, the policy, its config)``.
    """
    if args.noise not in NOISE_PRESETS:
        parser.error(f"--noise must be one of {', '.join(sorted(NOISE_PRESETS))}, got {args.noise!r}.")
    if args.seed < 0:
        parser.error(f"--seed must be a non-negative int, got {args.seed}.")
    if not 1 <= args.repeats <= MAX_REPEATS:
        parser.error(f"--repeats must be in [1, {MAX_REPEATS}], got {args.repeats}.")
    if args.house < 0:
        parser.error(f"--house must be a non-negative int (a house seed), got {args.house}.")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        parser.error(f"--out must be a directory, but {out} is a file.")
    if args.checkpoint is None:
        args.checkpoint = DEFAULT_HOMING_CHECKPOINT if args.homing else DEFAULT_CHECKPOINT
    if args.actions is None and args.waypoints is None and not sys.stdin.isatty():
        parser.error("no route given and no terminal for the keyboard: give --actions or --waypoints.")
    try:
        start = None if args.start is None else parse_numbers(args.start, 3, "--start (x m, y m, heading deg)")
        actions = None if args.actions is None else parse_actions(args.actions)
        waypoints = None if args.waypoints is None else parse_waypoints(args.waypoints)
    except ValueError as err:
        parser.error(str(err))
    house = build_house(args.house)
    if start is not None:
        try:
            check_position(house, pose_from_degrees(start)[:2], "--start")
        except RouteError as err:
            parser.error(str(err))
    from spf_rl.checkpoint import CheckpointError
    from spf_rl.device import resolve_device
    from spf_rl.hub import load_policy

    try:
        device = resolve_device(args.device, name="--device")
    except ValueError as err:
        parser.error(str(err))
    try:
        policy, config = load_policy(args.checkpoint, device=device)
    except (ValueError, FileNotFoundError, CheckpointError) as err:
        parser.error(f"--checkpoint: {err}")
    args.parsed_actions, args.parsed_waypoints = actions, waypoints
    return house, start, policy, config


def teach_route(parser: argparse.ArgumentParser, args: argparse.Namespace, house, start, length: int):
    """The demonstration of the route the arguments (or the keyboard) give, of ``length`` steps."""
    from envs.user_demos import demonstration_from_actions, demonstration_from_waypoints

    try:
        if args.parsed_actions is not None:
            return demonstration_from_actions(house, start or default_start(house), args.parsed_actions, length=length)
        if args.parsed_waypoints is not None:
            return demonstration_from_waypoints(house, args.parsed_waypoints, start=start, length=length)
    except RouteError as err:
        parser.error(f"--{'actions' if args.parsed_actions is not None else 'waypoints'}: {err}")
    from spf_rl.teach.keyboard import record_with_keyboard

    demo = record_with_keyboard(house, start or default_start(house), length)
    if demo is None:
        parser.exit(1, "cancelled: no route recorded.\n")
    return demo


def main(argv: list[str] | None = None) -> dict:
    """Run the recipe; returns the JSON content it writes."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(format="%(asctime)s %(name)s: %(message)s")
    logger.setLevel(logging.INFO)
    house, start, policy, config = check_args(parser, args)
    demo = teach_route(parser, args, house, start, config.demo_length)

    from spf_rl.teach.repeat import repeat_route, results, write_map, write_video

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    task, max_steps = HOMING if args.homing else FOLLOW, default_max_steps(demo.length)
    logger.info("route: %d steps, %.2f m; %s %s it %d times under %s noise", demo.length, demo.shortest_length_m,
                args.checkpoint, "brings it home" if args.homing else "repeats", args.repeats, args.noise)
    repeats, demo_frames, played = repeat_route(
        policy, demo, repeats=args.repeats, noise=args.noise, seed=args.seed, max_steps=max_steps,
        image_size=config.image_size[0], progress=not args.quiet, task=task,
    )
    setup = {"checkpoint": args.checkpoint, "task": task, "noise": args.noise, "seed": args.seed, "max_steps": max_steps}
    content = results(demo, repeats, setup, played)
    successes = sum(r.record["success"] for r in repeats)
    what = "bring it home" if args.homing else "succeed"
    title = f"house {demo.house_seed}: {successes}/{len(repeats)} repeats {what} ({args.noise} noise)"
    logger.info("drawing the map")
    files = {"map": write_map(played, repeats, out / MAP_NAME, title).name}
    if not args.no_video:
        logger.info("writing the video")
        files["video"] = write_video(played, demo_frames, repeats[0], out / VIDEO_STEM, args.noise).name
    content["files"] = files
    atomic_write_json((out / JSON_NAME), content)
    for repeat in repeats:
        record = repeat.record
        print(f"repeat {record['repeat']}: {'success' if record['success'] else 'failure'}, SPL {record['spl']:.2f}")
    summary = content["summary"]
    print(f"success {summary['success']:.2f}, SPL {summary['spl']:.2f} over {len(repeats)} repeats -> {out}")
    return content


if __name__ == "__main__":
    main()
