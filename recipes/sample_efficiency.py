"""The sample-efficiency study of the main job: each lever (:data:`spf_rl.eval.sample_efficiency.LEVERS`)
trained on the main job's budget with 3 seeds, paired against the main job as it was on the same 500 test
episodes (:mod:`spf_rl.eval.sample_efficiency`).

Trains what is missing in ``runs/sample_efficiency/<lever>-seed<S>`` (each about one main job), then writes
``results/sample_efficiency.json`` and ``results/sample_efficiency.png`` (validation success against gradient
steps and against training time).

Usage::

    python recipes/sample_efficiency.py                          # every lever, seeds 0, 1, 2
    python recipes/sample_efficiency.py --levers baseline,rpf_rule --seeds 0
    python recipes/sample_efficiency.py --no-train               # the report from the finished runs only
"""
from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from spf_rl.cli import ArgumentParser, arg_type, parse_names, parse_seeds
from spf_rl.eval.sample_efficiency import DEFAULT_OUT, DEFAULT_SEEDS, LEVER_BY_NAME, LEVERS, run_study


def main(argv: list[str] | None = None) -> dict:
    parser = ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--levers", type=arg_type(parse_names, tuple(LEVER_BY_NAME), "lever"),
                        default=[lever.name for lever in LEVERS],
                        help="comma-separated levers (default: all): " + ", ".join(LEVER_BY_NAME))
    parser.add_argument("--seeds", type=arg_type(parse_seeds), default=list(DEFAULT_SEEDS),
                        help="comma-separated training seeds (default: 0,1,2)")
    parser.add_argument("--no-train", action="store_true", help="report the finished runs only")
    parser.add_argument("--num-resamples", type=int, default=10_000, help="bootstrap resamples (default: %(default)s)")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="the JSON (default: %(default)s; the figure beside it)")
    args = parser.parse_args(argv)
    names, seeds = args.levers, args.seeds
    if args.num_resamples < 1:
        parser.error(f"argument --num-resamples: must be >= 1, got {args.num_resamples}")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    import envs  # noqa: F401  (selects the headless GL back-end first)

    # the baseline always: every lever is paired against it
    levers = [LEVER_BY_NAME["baseline"], *(LEVER_BY_NAME[name] for name in names if name != "baseline")]
    content = run_study(levers, seeds, args.out, args.num_resamples, train=not args.no_train)
    rows = {name: {"test_success": round(e["test_success"], 3), "worst_seed": round(e["worst_seed"], 3),
                   "vs_baseline": e.get("vs_baseline", {}).get("difference")} for name, e in content["levers"].items()}
    print(json.dumps({"levers": rows, "missing": content["missing"], "out": str(args.out)}, indent=2))
    return content


if __name__ == "__main__":
    main()
