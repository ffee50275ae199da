"""DAgger from a behaviour-cloning checkpoint: the improvement phase.

Rounds of: collect episodes with the learner driving (``beta0 = 0`` by default),
label every visited state with the expert, store the round, retrain for a fixed
number of gradient steps on the BC data plus a sliding window of recent rounds.
Scores every round on ``val`` and ``test`` and writes ``results.json`` and
``dagger.png`` to the output directory. Run it again with the same config to resume.

Usage::

    python recipes/dagger.py                                  # from the shipped checkpoint spf-s0.8
    python recipes/dagger.py --quick                          # a few-minute smoke run
    python recipes/dagger.py --preset dagger_control          # the expert drives every step: the control
    python recipes/dagger.py --preset dagger_long             # after bc.py --preset bc_long: its checkpoint and 8,000 episodes
    python recipes/dagger.py --preset dagger_rpf              # after bc.py --preset bc_row model=rpf sparsity=1
    python recipes/dagger.py --preset dagger_rpf_original     # after bc.py --preset bc_row model=rpf_original sparsity=1
    python recipes/dagger.py --preset dagger_spf_rpf_pointer  # after SPF 0.8 with RPF's pointer rule (python recipes/table1.py --rows spf_rpf_pointer-s0.8)
    python recipes/dagger.py --preset dagger_routes           # after bc.py --preset bc_routes: rounds on the routes people teach
    python recipes/dagger.py --preset dagger_routes_pointer_more seed=S   # 10 more rounds after dagger_routes_pointer seed=S
    python recipes/dagger.py --preset dagger_routes_robust seed=S  # from routes-spf seed S, repeating in changed worlds (#62)
    python recipes/dagger.py --preset dagger_routes_robust_anchor seed=S  # the same with the pointer's anchor
    python recipes/dagger.py --preset dagger_routes_robust_normalized seed=S  # and frames standardised per channel
    python recipes/dagger.py --preset dagger_routes_robust_share seed=S  # and half of every batch from the rounds
    python recipes/dagger.py --preset dagger_routes_robust_gate seed=S  # normalized, and a replay gate grown on
    python recipes/dagger.py checkpoint=runs/bc/spf-s0.8-seed0/best.pt rounds=6
    python recipes/dagger.py collector.backend=ray collector.num_collectors=2 device=cpu   # pip install '.[distributed]'
    python recipes/dagger.py device=cuda:1                    # the learner on the second GPU (default device=auto)
    torchrun --standalone --nproc_per_node 2 recipes/dagger.py   # retraining data-parallel; rank 0 collects and validates
"""
from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from spf_rl.cli import ArgumentParser
from spf_rl.config import config_or_exit, load_config

#: Presets in recipes/configs/ that --preset accepts.
PRESETS = (
    "dagger_quick", "dagger_control", "dagger_long", "dagger_rpf", "dagger_rpf_original", "dagger_spf_rpf_pointer",
    "dagger_pointer_long", "dagger_table1", "dagger_routes", "dagger_routes_pointer", "dagger_routes_pointer_more",
    "dagger_routes_robust", "dagger_routes_robust_anchor", "dagger_routes_robust_normalized", "dagger_routes_robust_share",
    "dagger_routes_robust_gate",
)


def check_start(config) -> None:
    """Refuse, before any work, a starting checkpoint that is missing, unreadable, not a checkpoint or an
    unknown shipped name (``ValueError``, one line naming the key). A resumed run (``output_dir/last.pt``)
    needs only its own state, not the starting checkpoint."""
    from spf_rl.hub import checkpoint_argument

    if not (Path(config.output_dir) / "last.pt").exists():
        checkpoint_argument(config.checkpoint, "invalid configuration: checkpoint")


def main(argv: list[str] | None = None) -> dict:
    parser = ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="small preset that runs in a few minutes (= --preset dagger_quick)")
    parser.add_argument(
        "--preset",
        choices=PRESETS,
        default=None,
        help="dagger_quick (smoke run), dagger_control (the expert drives every step: the control at equal steps), "
        "the earlier DAgger runs after Table 1's rows: dagger_long, dagger_rpf, dagger_rpf_original, dagger_spf_rpf_pointer, dagger_pointer_long, "
        "dagger_table1 (Table 1's one DAgger rule, after bc.py --preset bc_table1), "
        "dagger_routes (after bc.py --preset bc_routes: rounds on the same route mixture) "
        "dagger_routes_pointer (dagger_routes with a pointer loss, optim.pointer_coef 0.1) "
        "dagger_routes_pointer_more (10 more such rounds from dagger_routes_pointer's kept weights, on fresh routes) "
        "dagger_routes_robust (from routes-spf's weights, every round repeated in a changed world: issue #62) "
        "dagger_routes_robust_anchor (the same, the pointer's anchor grown onto the network) "
        "dagger_routes_robust_normalized (the same with every frame standardised per channel) "
        "dagger_routes_robust_share (the same with half of every retraining batch from the rounds, rounds_share 0.5) "
        "or dagger_routes_robust_gate (dagger_routes_robust_normalized with a replay gate grown on, taught to fall back "
        "on blind replay where the memory shows another route)",
    )
    parser.add_argument("overrides", nargs="*", help="key=value config overrides")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    import envs  # noqa: F401  (selects the headless GL back-end first)
    from spf_rl.train.dagger import DAggerConfig, train_dagger

    if args.quick and args.preset not in (None, "dagger_quick"):
        parser.error(f"--quick is --preset dagger_quick; it cannot be combined with --preset {args.preset}")
    config = config_or_exit(parser, load_config, DAggerConfig, "dagger", args.overrides, preset="dagger_quick" if args.quick else args.preset)
    config_or_exit(parser, check_start, config)
    results = train_dagger(config)
    if "model" not in results:  # a rank other than 0 of a torchrun run: rank 0 reports
        return results

    def scores(record: dict) -> dict:
        return {key: round(record[key], 3) for key in ("val_success", "val_spl", "test_success", "test_spl") if key in record}

    summary = {
        "model": results["model"],
        "start": scores(results["start"]),
        "final": scores(results["final"]),
        "best_round_by_val": results["best_round_by_val"],
        "output_dir": config.output_dir,
    }
    print(json.dumps(summary, indent=2))
    return results


if __name__ == "__main__":
    main()
