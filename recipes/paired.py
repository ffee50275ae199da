"""Paired comparison of two evaluations of the same episodes (``recipes/evaluate.py`` JSONs).

Both files must hold per-episode records of the same episodes in the same order
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
import json
import logging
from pathlib import Path

logger = logging.getLogger("paired")

#: Per-episode fields compared.
METRICS = ("success", "spl", "success_lab")


def load_records(path: Path) -> tuple[dict, list[dict]]:
    """``(evaluation JSON, its per-episode records)``; a clear error for a file without records."""
    payload = json.loads(Path(path).read_text())
    records = payload.get("episodes_records")
    if not records:
        raise ValueError(f"{path} has no per-episode records ('episodes_records'): write it with recipes/evaluate.py.")
    return payload, records


def compare(path_a: Path, path_b: Path, num_resamples: int, seed: int) -> dict:
    """The paired comparison of two evaluation JSONs (A - B), as written to ``--out``."""
    from spf_rl.stats import paired_bootstrap

    (a, records_a), (b, records_b) = load_records(path_a), load_records(path_b)
    episodes_a = [(r["episode_seed"], r["house_seed"]) for r in records_a]
    episodes_b = [(r["episode_seed"], r["house_seed"]) for r in records_b]
    if episodes_a != episodes_b:
        raise ValueError(
            f"{path_a} and {path_b} hold different episodes ({len(episodes_a)} and {len(episodes_b)} records; "
            "evaluate both with the same --split, --seed and --episodes)."
        )
    houses = [house for _, house in episodes_a]
    metrics = {}
    for name in METRICS:
        if not all(name in r for r in records_a + records_b):
            continue
        result = paired_bootstrap(
            [float(r[name]) for r in records_a], [float(r[name]) for r in records_b], houses,
            num_resamples=num_resamples, seed=seed,
        )
        metrics[name] = {
            "a": sum(float(r[name]) for r in records_a) / len(records_a),
            "b": sum(float(r[name]) for r in records_b) / len(records_b),
            "difference": result.difference,
            "ci95": list(result.ci),
            "p_greater": result.p_greater,
            "p_two_sided": result.p_two_sided,
        }
    return {
        "a": str(path_a),
        "b": str(path_b),
        "a_checkpoint": a.get("checkpoint"),
        "b_checkpoint": b.get("checkpoint"),
        "episodes": len(records_a),
        "houses": len(set(houses)),
        "num_resamples": num_resamples,
        "seed": seed,
        "method": "spf_rl.stats.paired_bootstrap: houses resampled, then episodes within them; difference is A - B",
        "metrics": metrics,
    }


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("a", type=Path, help="evaluation JSON of model A")
    parser.add_argument("b", type=Path, help="evaluation JSON of model B (same episodes)")
    parser.add_argument("--out", type=Path, required=True, help="output JSON")
    parser.add_argument("--resamples", type=int, default=10_000, help="bootstrap resamples (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the resampling (default: %(default)s)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    if args.resamples < 1:
        parser.error(f"--resamples must be >= 1, got {args.resamples}")
    for path in (args.a, args.b):
        if not path.is_file():
            parser.error(f"no evaluation JSON at {path}")
    result = compare(args.a, args.b, args.resamples, args.seed)
    from spf_rl.train.bc import atomic_json

    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_json(args.out, result)
    for name, metric in result["metrics"].items():
        logger.info(
            "%s: A %.3f, B %.3f, A - B %+.3f [%+.3f, %+.3f], p (two-sided) %.3f",
            name, metric["a"], metric["b"], metric["difference"], *metric["ci95"], metric["p_two_sided"],
        )
    return result


if __name__ == "__main__":
    main()
