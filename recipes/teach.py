"""Teach and repeat: show the agent a route once, then watch a shipped policy repeat it under noise.

Record the route with the keyboard in this terminal (the default: arrow keys, Enter to finish), or give it headless:

* ``--actions FFLFFR...``: F forward 0.3 m, L turn left 20 deg, R turn right 20 deg, driven from ``--start``;
* ``--waypoints "x,y;x,y;..."``: points on the top-down map (metres), joined by the planner (the noise-free
  expert on the house's geodesic graph); the route starts at ``--start`` if given, else at the first waypoint
  facing the second.

A route keeps the length it is given (up to 198 steps; ``--length N`` requires N steps and crops a waypoint plan
to N), and the policy follows it at that length. Routes into a
wall, out of the house or ending within the success radius (0.6 m) of their start are refused with the step or
waypoint named.

The policy (``--checkpoint``; default ``routes-spf``, trained on routes of every style and 10-100 steps) then
repeats the route ``--repeats`` times, each under its own actuation noise, greedily. With
``--homing`` it brings the route home instead: each repeat starts at the route's end, facing back along it, and
must return to the route's start, its memory the env's homing demonstration of the route (frames rendered looking
back along it, :mod:`envs.homing`), with ``homing-spf-s0.8`` (SPF 0.8 trained on homing episodes,
``python recipes/bc.py --preset bc_homing``) unless ``--checkpoint`` says otherwise. With ``--conditions``
the repeats happen in a changed world (:mod:`envs.conditions`: at dusk, repainted, the furniture moved,
another camera or sensor); the route's memory is still the taught one. Written to ``--out``:

* ``teach.mp4`` (where ``imageio-ffmpeg`` is installed) or ``teach.gif``: the demonstration's view beside
  repeat 1's, with the map;
* ``teach_map.png``: the top-down map with the demonstration and every repeat;
* ``teach.json``: the route (start and actions, enough to replay it), the set-up, and per repeat success, SPL,
  nDTW and the path's length against the route's. The same arguments and ``--seed`` give the same JSON.

Usage::

    python recipes/teach.py                                   # keyboard, first test house
    python recipes/teach.py --house 0 --start 7.5,1.5,0 --actions FFFFFFLLLFLFLFFRFFLFFRFFLFFRFR --repeats 8
    python recipes/teach.py --house 0 --waypoints "7.5,1.5;9.5,1.5;9.5,5.5;12.5,5.5" --noise paper_symmetric
    python recipes/teach.py --house 0 --start 7.5,1.5,0 --actions FFFFFFLLLFLFLFFRFFLFFRFFLFFRFR --homing
    python recipes/teach.py --house 0 --start 7.5,1.5,0 --actions FFFFFFLLLFLFLFFRFFLFFRFFLFFRFR --conditions light@1
"""
from __future__ import annotations

import argparse
import logging
import sys

from envs.scenes import build_house
from envs.transforms import DEFAULT_NOISE, NOISE_PRESETS
from envs.user_demos import RouteError, check_position, parse_actions, parse_pose, parse_waypoints, pose_from_degrees
from spf_rl.checkpoint import CheckpointError
from spf_rl.cli import ArgumentParser
from spf_rl.device import resolve_device
from spf_rl.hub import load_policy
from spf_rl.teach import repeat
from spf_rl.teach.route import MAX_TAUGHT_STEPS, route_source, teach_route


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(prog="teach.py", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    route = parser.add_mutually_exclusive_group()
    route.add_argument("--actions", help="the route as letters F (forward), L (left), R (right), e.g. FFLFFR")
    route.add_argument("--waypoints", help='points "x,y;x,y;..." in metres, joined by the planner')
    parser.add_argument("--house", type=int, default=repeat.DEFAULT_HOUSE, help=f"house seed (default {repeat.DEFAULT_HOUSE}, the first test house)")
    parser.add_argument("--start", help="start pose x,y,heading: metres, metres, degrees (0 = +x, counter-clockwise)")
    parser.add_argument("--length", type=int, help="the steps the route must have (waypoint plans are cropped to it; default: its own)")
    parser.add_argument("--noise", default=DEFAULT_NOISE, help=f"actuation-noise preset: {', '.join(sorted(NOISE_PRESETS))} (default {DEFAULT_NOISE})")
    parser.add_argument("--seed", type=int, default=0, help="seed of the repeats' noise (default 0)")
    parser.add_argument("--repeats", type=int, default=repeat.DEFAULT_REPEATS, help=f"repeats, 1 to {repeat.MAX_REPEATS} (default {repeat.DEFAULT_REPEATS})")
    parser.add_argument("--checkpoint", default=None, help=f"a shipped name or a .pt path (default {repeat.DEFAULT_CHECKPOINT}; with --homing {repeat.DEFAULT_HOMING_CHECKPOINT})")
    parser.add_argument("--out", default=repeat.DEFAULT_OUT, help=f"output directory (default {repeat.DEFAULT_OUT})")
    parser.add_argument("--device", default="auto", help="where the policy runs: auto (CUDA if available, else CPU), cpu, cuda, cuda:N")
    parser.add_argument("--homing", action="store_true", help="bring the route home: from its end back to its start")
    parser.add_argument("--conditions", help="repeat in a changed world (envs.conditions): name@strength with name one of "
                        "light, paint, furniture, camera, sensor and strength in [0, 1], e.g. light@0.5, or a mixture "
                        "'light@1=1,furniture@1=1' (each repeat draws its own change)")
    parser.add_argument("--no-video", action="store_true", help="skip the video (the slowest output)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    return parser


def setup(parser: ArgumentParser, args: argparse.Namespace):
    """Check every argument before any work (a bad one: one ``parser.error`` line naming it), load the policy
    and teach the route; returns ``(options, the demonstration, the policy, its config)``."""
    try:
        options = repeat.TeachOptions(
            house=args.house, noise=args.noise, seed=args.seed, repeats=args.repeats, out=args.out, checkpoint=args.checkpoint,
            homing=args.homing, video=not args.no_video, progress=not args.quiet, conditions=args.conditions,
        )
        if args.actions is None and args.waypoints is None and not sys.stdin.isatty():
            raise ValueError("no route given and no terminal for the keyboard: give --actions or --waypoints.")
        if args.length is not None and not 1 <= args.length <= MAX_TAUGHT_STEPS:
            raise ValueError(f"--length must be in [1, {MAX_TAUGHT_STEPS}] steps, got {args.length}.")
        start = None if args.start is None else parse_pose(args.start, "--start (x m, y m, heading deg)")
        actions = None if args.actions is None else parse_actions(args.actions)
        waypoints = None if args.waypoints is None else parse_waypoints(args.waypoints, "--waypoints")
        if start is not None:
            check_position(build_house(args.house), pose_from_degrees(start)[:2], "--start")
        device = resolve_device(args.device, name="--device")
    except ValueError as err:
        parser.error(str(err))
    try:
        policy, config = load_policy(options.checkpoint, device=device)
    except (ValueError, FileNotFoundError, CheckpointError) as err:
        parser.error(f"--checkpoint: {err}")
    try:
        demo = teach_route(options.house, start, actions, waypoints, length=args.length)
    except RouteError as err:
        parser.error(f"--{route_source(actions, waypoints)}: {err}")
    if demo is None:
        parser.exit(1, "cancelled: no route recorded.\n")
    return options, demo, policy, config


def main(argv: list[str] | None = None) -> dict:
    """Run the recipe; returns the JSON content it writes."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(format="%(asctime)s %(name)s: %(message)s")
    logging.getLogger("spf_rl.teach").setLevel(logging.INFO)
    options, demo, policy, config = setup(parser, args)
    content = repeat.teach_and_repeat(policy, demo, options, image_size=config.image_size[0])
    for r in content["repeats"]:
        print(f"repeat {r['repeat']}: {'success' if r['success'] else 'failure'}, SPL {r['spl']:.2f}, nDTW {r['ndtw']:.2f}, "
              f"path {r['path_length_ratio']:.2f}x the route's")
    s = content["summary"]
    print(f"success {s['success']:.2f}, SPL {s['spl']:.2f}, nDTW {s['ndtw']:.2f} over {len(content['repeats'])} repeats -> {options.out}")
    return content


if __name__ == "__main__":
    main()
