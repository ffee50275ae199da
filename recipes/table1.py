"""Reproduce the paper's Table 1 over training seeds, with house-level statistics.

Rows (``--rows`` names them; each is also the stem of its shipped checkpoint):

* ``spf-s0.4``, ``spf-s0.6``, ``spf-s0.8``: SPF at sparsity 0.4 / 0.6 / 0.8;
* ``rpf-s1``: SPF at sparsity 1 (RPF as SPF: full memory, SPF's network);
* ``rpf_original-s1``: the original RPF (the RPF lab code's memory network);
* ``spf_rpf_pointer-s0.8``: SPF 0.8 with RPF's pointer rule (beyond the paper);
* ``action_only-s0``: RPF action only; ``open_loop``: open-loop replay (no training);
* ``spf_random-s0.2-1``: one model trained with a random sparsity per episode in [0.2, 1], evaluated at each of
  :data:`~spf_rl.eval.table1_rows.RANDOM_EVAL_SPARSITIES` (one table line each).

One budget for every row: each learned row is trained with each of ``--seeds`` (default 0, 1, 2) under the
``paper`` noise on ``--preset bc_table1`` (``bc_long``'s 20,000 gradient steps on 8,000 episodes, best epoch by
validation), and the rows with a DAgger column (SPF 0.8, SPF at sparsity 1, the original RPF, the pointer rule)
then get one DAgger rule, ``--preset dagger_table1`` (10 learner-driven rounds, the round picked on fresh
validation episodes), from their own BC run. Seed 0 of every row comes first, then seed 1, then seed 2. Run
directories ``runs/table1/<row>-seed<S>`` and ``runs/table1/dagger-<row>-seed<S>``; an interrupted run resumes.
A finished run's ``best.pt`` is copied to ``checkpoints/table1/<line>-seed<S>.pt`` (replacing an earlier run's
file there), and once every seed of a line has finished (seeds 0, 1 and 2, and any other ``--seeds``: a run of
``--seeds 2`` alone still ships the best of the three), the seed with the best validation success becomes the
line's shipped name (``checkpoints/manifest.json`` maps the name to that file). Per-seed files that are not this
recipe's runs are scored as they are.
``--from-checkpoints`` trains nothing, but still copies and ships what finished runs left. ``key=value``
overrides reach every BC run; ``device=`` and ``optim.amp=`` reach the DAgger runs too.

Every checkpoint is scored on the same episodes: the ``test`` set (``bc_long``'s test config: 1,000 episodes of
the 18 test houses, seed 2, ``paper`` noise) and the ``extended`` set (the same with 100 test-split houses).
Per-episode records are cached in ``results/eval/table1/<set>/<line>-seed<S>.json`` (:mod:`spf_rl.records_cache`:
keyed by the episodes and a hash of the weights, not of the file), so a rerun evaluates only what is missing or
changed; a finished run's own test records of the same weights on the same episodes (its ``test_episodes.json``)
are taken as they are. Seeds
without a checkpoint are listed as missing, never silently dropped.

Writes ``results/table1.json``, ``results/table1.md`` and ``results/table1.png`` (:mod:`spf_rl.eval.table1`); a
part of the table (``--rows``, ``--seeds`` or ``--sets`` leaving some out) goes to ``runs/table1_part/`` instead
(or ``--out``), so that it never overwrites the whole table. The table holds:
mean +- sd over seeds, house-level bootstrap intervals, paired bootstrap tests of the ordering claims
(:data:`~spf_rl.eval.table1_rows.CLAIMS`), both success criteria, and each checkpoint's pointer pace (its
pointer's mean step on 64 validation episodes, teacher-forced: :mod:`spf_rl.pointer_pace`); a line with a seed
whose pointer runs backwards is marked.

Usage::

    python recipes/table1.py --from-checkpoints          # score checkpoints/table1/ and finished runs (no training)
    python recipes/table1.py                             # train what is missing, then score
    python recipes/table1.py --rows spf-s0.8,action_only-s0 --seeds 0,1 --sets test   # a part, in runs/table1_part/
    python recipes/table1.py --quick --from-checkpoints --rows open_loop   # smoke run under runs/table1_quick/
    python recipes/table1.py device=cuda optim.amp=true   # key=value overrides reach every training run
"""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

from spf_rl.cli import ArgumentParser, arg_type, parse_names, parse_seeds
from spf_rl.eval.table1_rows import (
    DEFAULT_SEEDS,
    QUICK_DIR,
    QUICK_EPISODES,
    ROW_BY_NAME,
    SETS,
    Table1Options,
    reproduce,
)


def parse_args(argv: list[str] | None) -> Table1Options:
    """The options, all checked before any work (a bad one exits with a message naming it)."""
    parser = ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--from-checkpoints", action="store_true",
        help="train nothing: score the checkpoints there are (finished runs are still copied and shipped)",
    )
    parser.add_argument("--rows", type=arg_type(parse_names, tuple(ROW_BY_NAME), "row"), default=list(ROW_BY_NAME))
    parser.add_argument("--seeds", type=arg_type(parse_seeds), default=list(DEFAULT_SEEDS))
    parser.add_argument("--sets", type=arg_type(parse_names, SETS, "set"), default=list(SETS))
    parser.add_argument(
        "--quick", action="store_true",
        help=f"smoke run: {QUICK_EPISODES} episodes per set, bc_quick training, all under {QUICK_DIR}/",
    )
    parser.add_argument("--checkpoints", type=Path, default=None, help="default checkpoints/ (quick: under runs/table1_quick/)")
    parser.add_argument("--eval-dir", type=Path, default=None, help="per-episode cache, default results/eval/table1/")
    parser.add_argument(
        "--out", type=Path, default=None,
        help="where table1.{json,md,png} go, default results/ (a part of the table: runs/table1_part/)",
    )
    parser.add_argument("--num-resamples", type=int, default=10_000, help="bootstrap resamples")
    parser.add_argument("overrides", nargs="*", help="key=value overrides for every training run (as for bc.py)")
    args = parser.parse_args(argv)
    try:
        return Table1Options(
            rows=args.rows, seeds=args.seeds, sets=args.sets, overrides=args.overrides, quick=args.quick,
            from_checkpoints=args.from_checkpoints, checkpoints=args.checkpoints, eval_dir=args.eval_dir, out=args.out,
            num_resamples=args.num_resamples,
        )
    except ValueError as err:
        parser.error(str(err))


def main(argv: list[str] | None = None) -> dict:
    options = parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    return reproduce(options)


if __name__ == "__main__":
    main()
