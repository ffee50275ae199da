"""Paired comparison of two evaluations of the same episodes (``recipes/evaluate.py`` JSONs,
or the ``test_episodes.json`` that ``recipes/bc.py`` and ``recipes/dagger.py`` write beside a run's results).

Each side is one JSON, or several (one per training seed: the statistic is then
pooled over seeds). Every file must hold per-episode records of the same episodes in
the same order (the same split, seed and episode count: ``evaluate.py`` plays the same
episodes for every policy). For success, SPL and the lab code's success,
:func:`compare` gives the mean difference A - B with a 95% interval and p-values from
:func:`spf_rl.stats.paired_bootstrap` (houses resampled, then episodes within them,
the same draws for both sides), so that an ordering claimed between two models is
backed by the episodes they share. ``recipes/paired.py`` is its command line.
"""
from __future__ import annotations

import json
from pathlib import Path

from spf_rl.stats import paired_bootstrap

#: Per-episode fields compared (each where every record has it; the path-fidelity ones
#: where the episodes followed a demonstrated path).
COMPARED_METRICS = ("success", "spl", "success_lab", "ndtw", "sdtw")
#: Where ``recipes/evaluate.py``'s JSON lists its per-episode records.
EVALUATE_RECORDS_KEY = "episodes_records"


def load_records(path: Path) -> tuple[dict, list[dict]]:
    """``(evaluation JSON, its per-episode records)``; a clear error for a file without records.

    Records are a list under :data:`EVALUATE_RECORDS_KEY` (``recipes/evaluate.py``), or per-episode columns
    (``{"columns": {field: [...]}}``: a file of the per-episode result cache, :mod:`spf_rl.records_cache`,
    such as a run's ``test_episodes.json`` or ``results/eval/table1/<set>/<line>-seed<S>.json``).
    """
    from spf_rl.records_cache import from_columns

    payload = json.loads(Path(path).read_text())
    records = payload.get(EVALUATE_RECORDS_KEY) if isinstance(payload.get(EVALUATE_RECORDS_KEY), list) else None
    columns = payload.get("columns")
    if not records and isinstance(columns, dict) and columns:
        records = from_columns(columns)
    if not records:
        raise ValueError(
            f"{path} has no per-episode records (a list under {EVALUATE_RECORDS_KEY!r}, or per-episode 'columns'): "
            "write it with recipes/evaluate.py."
        )
    return payload, records


def checkpoint_of(payload: dict) -> str | None:
    """The checkpoint an evaluation file is of (``evaluate.py``'s key, or a cache file's ``checkpoint``)."""
    return payload.get("checkpoint")


def split_paths(paths: Path | str | list) -> list[Path]:
    """One path, a comma-joined string of paths, or a list of paths -> a list of paths."""
    if isinstance(paths, (list, tuple)):
        return [Path(path) for path in paths]
    return [Path(part) for part in str(paths).split(",") if part]


def compare(path_a: Path | str | list, path_b: Path | str | list, num_resamples: int, seed: int) -> dict:
    """The paired comparison of two sides' evaluation JSONs (A - B, pooled over each
    side's files), as written to ``--out``."""
    files = {"a": split_paths(path_a), "b": split_paths(path_b)}
    loaded = {side: [load_records(path) for path in paths] for side, paths in files.items()}
    reference = [(r["episode_seed"], r["house_seed"]) for r in loaded["a"][0][1]]
    for side, paths in files.items():
        for path, (_, records) in zip(paths, loaded[side]):
            if [(r["episode_seed"], r["house_seed"]) for r in records] != reference:
                raise ValueError(
                    f"{files['a'][0]} and {path} hold different episodes ({len(reference)} and {len(records)} records; "
                    "evaluate both with the same --split, --seed and --episodes)."
                )
    houses = [house for _, house in reference]
    records_a = [r for _, records in loaded["a"] for r in records]
    records_b = [r for _, records in loaded["b"] for r in records]
    metrics = {}
    for name in COMPARED_METRICS:
        if not all(name in r for r in records_a + records_b):
            continue
        result = paired_bootstrap(
            [[float(r[name]) for r in records] for _, records in loaded["a"]],
            [[float(r[name]) for r in records] for _, records in loaded["b"]],
            houses,
            num_resamples=num_resamples,
            seed=seed,
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
        "a": [str(path) for path in files["a"]],
        "b": [str(path) for path in files["b"]],
        "a_checkpoints": [checkpoint_of(payload) for payload, _ in loaded["a"]],
        "b_checkpoints": [checkpoint_of(payload) for payload, _ in loaded["b"]],
        "episodes": len(reference),
        "houses": len(set(houses)),
        "num_resamples": num_resamples,
        "seed": seed,
        "method": "spf_rl.stats.paired_bootstrap: houses resampled, then episodes within them; difference is A - B",
        "metrics": metrics,
    }
