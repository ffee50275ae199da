"""Route benchmark: how well each policy follows routes of each style and length.

Every shipped checkpoint (by default all but ``homing-*``, trained for another task, and
``ppo-*``, trained under the older ``paper_symmetric`` noise) and open-loop replay (the
floor) play the same episodes of every cell: set (test split; test split on 100 houses)
x route style (planner, tour, driven) x length bucket (10-30, 31-60, 61-100 steps).
Per cell: success, SPL, nDTW and SDTW with house-level bootstrap intervals, and each
model's paired difference from open-loop replay (success, nDTW). Written to ``--out``
(after every evaluation: an interrupted run resumes where it stopped), with the figure
(``.png``) and the markdown table (``.md``, also printed) next to it.
The work is :mod:`spf_rl.eval.route_bench`'s.

Usage::

    python recipes/route_bench.py --quick                      # smoke run -> results/route_bench_quick.json
    python recipes/route_bench.py                              # everything -> results/route_bench.json
    python recipes/route_bench.py --models spf-s0.8,lengths-spf-s0.8 --styles driven --buckets 61-100 --out results/rb.json
    python recipes/route_bench.py --models spf-s0.8 --buckets 10-30 --conditions none light@0.5 furniture@1 mismatch --out results/rb_worlds.json
    python recipes/route_bench.py --models spf-s0.8,rpf_original-s1 --reference spf-s0.8 --out results/rb.json   # paired with spf-s0.8
"""
from __future__ import annotations

import argparse
import dataclasses
import logging

from envs.transforms import DEFAULT_NOISE
from spf_rl.checkpoint import CheckpointError
from spf_rl.cli import ArgumentParser
from spf_rl.eval.route_bench import (
    DEFAULT_BUCKETS,
    DEFAULT_EPISODES,
    DEFAULT_OUT,
    EXCLUDED_PREFIXES,
    EXTENDED_HOUSES,
    QUICK_BUCKETS,
    QUICK_EPISODES,
    QUICK_MODELS,
    QUICK_OUT,
    QUICK_SETS,
    STYLES,
    BenchOptions,
    load_models,
    parse_buckets,
    parse_list,
    run_bench,
)
from spf_rl.evaluation import TEST_SEED

#: The options' own defaults, shown in --help.
DEFAULTS = {option.name: option.default for option in dataclasses.fields(BenchOptions)}


def bucket_text(buckets: tuple[tuple[int, int], ...]) -> str:
    """``((10, 30), (31, 60))`` as ``10-30,31-60``, the form ``--buckets`` takes."""
    return ",".join(f"{lo}-{hi}" for lo, hi in buckets)


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", help="comma-separated shipped names or .pt paths (default: all shipped but "
                        + ", ".join(f"{prefix}*" for prefix in EXCLUDED_PREFIXES) + ")")
    parser.add_argument("--styles", help=f"route styles (default {','.join(STYLES)})")
    parser.add_argument("--buckets", help=f"length buckets lo-hi, steps (default {bucket_text(DEFAULT_BUCKETS)})")
    parser.add_argument("--sets", help=f"episode sets: test, extended ({EXTENDED_HOUSES} houses) (default both)")
    parser.add_argument("--episodes", type=int, help=f"episodes per cell (default {DEFAULT_EPISODES}; --quick {QUICK_EPISODES})")
    parser.add_argument("--seed", type=int, default=TEST_SEED, help=f"seed of the episodes (default {TEST_SEED}, the test seed)")
    parser.add_argument("--noise", default=DEFAULT_NOISE, help=f"actuation noise preset (default {DEFAULT_NOISE})")
    parser.add_argument("--random-sparsity", type=float, help="sparsity of random-sparsity models (default: their config's)")
    parser.add_argument("--num-resamples", type=int, default=DEFAULTS["num_resamples"],
                        help="bootstrap resamples (default %(default)s)")
    parser.add_argument("--device", default=DEFAULTS["device"], help="where the policies run: cpu, auto, cuda, cuda:N (default %(default)s)")
    parser.add_argument("--num-collectors", type=int, default=DEFAULTS["num_collectors"],
                        help="processes playing a cell's episodes (default %(default)s)")
    parser.add_argument("--out", help=f"the JSON (default {DEFAULT_OUT}; --quick: {QUICK_OUT})")
    parser.add_argument("--quick", action="store_true",
                        help=f"smoke run: {', '.join(QUICK_MODELS)} and open-loop, {QUICK_EPISODES} episodes, "
                             f"{', '.join(QUICK_SETS)} set, buckets {bucket_text(QUICK_BUCKETS)}")
    parser.add_argument("--conditions", nargs="+", metavar="WORLD",
                        help="worlds the routes are repeated in, a cell each (default: the teaching world alone): none, "
                             "repeat conditions name@strength (envs.conditions: light, paint, furniture, camera, sensor; a "
                             "mixture 'light@0.5=1,paint@1=1'), or mismatch (another route's frames with the route's own actions)")
    parser.add_argument("--reference", help="a model of --models (as given or by label, or a seed group's label) that "
                        "every other is paired with per world: success minus the reference's, with its interval")
    parser.add_argument("--progress", action="store_true", help="progress bars")
    return parser


def main(argv: list[str] | None = None) -> dict:
    """Run the recipe; returns the JSON content it writes (with the markdown ``table``)."""
    parser = build_parser()
    args = parser.parse_args(argv)

    try:
        options = BenchOptions(
            models=None if args.models is None else parse_list(args.models, None, "--models"),
            styles=STYLES if args.styles is None else parse_list(args.styles, STYLES, "--styles"),
            buckets=None if args.buckets is None else parse_buckets(args.buckets),
            sets=None if args.sets is None else parse_list(args.sets, None, "--sets"),
            episodes=args.episodes, seed=args.seed, noise=args.noise, random_sparsity=args.random_sparsity,
            num_resamples=args.num_resamples, device=args.device, num_collectors=args.num_collectors, out=args.out, quick=args.quick, progress=args.progress,
            conditions=(None,) if args.conditions is None else tuple(args.conditions), reference=args.reference,
        )
    except ValueError as err:
        parser.error(str(err))
    try:
        models = load_models(options)
    except (ValueError, FileNotFoundError, CheckpointError) as err:
        parser.error(f"argument --models: {err}")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    content = run_bench(options, models)
    print(content.get("table_by_world") or content["table"])
    if content.get("table_vs_reference"):
        print(content["table_vs_reference"])
    print(f"-> {options.out}" + (f", {content['figure']}" if content["figure"] else ""))
    return content


if __name__ == "__main__":
    main()
