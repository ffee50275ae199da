"""Sample routes of each style (planner, tour, driven) in one house, drawn on its map.

The routes are those an env with ``route_style=<style>`` samples (:mod:`envs.route_styles`):
the planner's shortest paths, tours through random waypoints, and routes driven the
way people drive with the keys. Prints each route's turn share and its length against
the shortest path to its end.

Usage::

    python recipes/route_styles.py                                 # -> docs/route_styles.png
    python recipes/route_styles.py --house 3 --lengths 20 60 100 --out figures/routes.png
"""
from __future__ import annotations

import argparse

import numpy as np

from envs.expert import FORWARD, FORWARD_STEP_M
from envs.house_grid import default_grid_size_cells, house_seed
from envs.route_styles import MAX_STYLE_LENGTH, MIN_STYLE_LENGTH, ROUTE_STYLES, sample_route
from envs.scenes import build_house
from spf_rl.cli import ArgumentParser
from spf_rl.viz import plot_route_styles


def main(argv: list[str] | None = None) -> None:
    parser = ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--house", type=int, default=0, help="house base seed (default 0)")
    parser.add_argument("--lengths", type=int, nargs="+", default=[20, 30, 45], help="one route of each length, steps (default 20 30 45)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the routes (default 0)")
    parser.add_argument("--out", default="docs/route_styles.png", help="output PNG (default docs/route_styles.png)")
    args = parser.parse_args(argv)
    if args.house < 0 or args.seed < 0:
        parser.error(f"--house and --seed must be non-negative ints, got {args.house} and {args.seed}.")
    if not all(MIN_STYLE_LENGTH <= n <= MAX_STYLE_LENGTH for n in args.lengths):
        parser.error(f"--lengths must lie in [{MIN_STYLE_LENGTH}, {MAX_STYLE_LENGTH}] steps, got {args.lengths}.")
    house = build_house(house_seed(args.house, default_grid_size_cells(max(args.lengths))))
    routes = {
        style: [sample_route(style, house, np.random.default_rng([args.seed, i]), n) for i, n in enumerate(args.lengths)]
        for style in ROUTE_STYLES
    }
    for style, demos in routes.items():
        for demo in demos:
            travelled = FORWARD_STEP_M * int((demo.actions == FORWARD).sum())
            print(
                f"{style}: {demo.length} steps, turns {np.mean(demo.actions != FORWARD):.0%}, "
                f"{travelled:.1f} m driven for {demo.shortest_length_m:.1f} m from start to end"
            )
    written = plot_route_styles(house, routes, args.out, f"house {house.seed}: sample routes of each style")
    print(f"-> {written}")


if __name__ == "__main__":
    main()
