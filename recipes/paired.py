"""Paired comparison of two evaluations of the same episodes (``recipes/evaluate.py`` JSONs, a
run's ``test_episodes.json``, or ``recipes/table1.py``'s per-episode cache in ``results/eval/table1/``):
the command line of :func:`spf_rl.eval.paired.compare`.

Each side is one JSON, or several joined by commas (one per training seed: the
statistic is then pooled over seeds). Every file must hold per-episode records of
the same episodes in the same order
(the same split, seed and episode count: ``evaluate.py`` plays the same episodes for
every policy). For success, SPL and the lab code's success it writes the mean
difference A - B with a 95% interval and p-values from
:func:`spf_rl.stats.paired_bootstrap` (houses resampled, then episodes within them,
the same draws for both sides), so that an ordering claimed between two models is
backed by the episodes they share.

Usage::

    python recipes/paired.py results/eval/current/checkpoints_dagger-spf-s0.8-test-paper-seed2.json \\
        results/eval/current/checkpoints_spf-s0.8-test-paper-seed2.json \\
        --out results/eval/current/paired-dagger-spf-s0.8-vs-spf-s0.8.json
"""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

from envs.atomic_io import atomic_write_json
from spf_rl.cli import ArgumentParser
from spf_rl.eval.paired import compare, split_paths

logger = logging.getLogger("paired")


def main(argv: list[str] | None = None) -> dict:
    parser = ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("a", help="evaluation JSON(s) of model A (comma-separated: one per training seed)")
    parser.add_argument("b", help="evaluation JSON(s) of model B (same episodes)")
    parser.add_argument("--out", type=Path, required=True, help="output JSON")
    parser.add_argument("--resamples", type=int, default=10_000, help="bootstrap resamples (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the resampling (default: %(default)s)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if args.resamples < 1:
        parser.error(f"--resamples must be >= 1, got {args.resamples}")
    for path in split_paths(args.a) + split_paths(args.b):
        if not path.is_file():
            parser.error(f"no evaluation JSON at {path}")
    try:
        result = compare(args.a, args.b, args.resamples, args.seed)
    except ValueError as err:  # files without records, or of different episodes
        parser.error(str(err))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(args.out, result, default=str)
    for name, metric in result["metrics"].items():
        logger.info(
            "%s: A %.3f, B %.3f, A - B %+.3f [%+.3f, %+.3f], p (two-sided) %.3f",
            name, metric["a"], metric["b"], metric["difference"], *metric["ci95"], metric["p_two_sided"],
        )
    return result


if __name__ == "__main__":
    main()
