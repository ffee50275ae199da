"""Table 1's statistics and reports, from per-episode records (no env, no policy).

:func:`build_table` turns the records of every line x seed x set (``recipes/table1.py``
collects them) into the table's dict: per-seed scores, mean +- sample sd over seeds,
house-level bootstrap intervals of the pooled mean, and paired bootstrap tests of the
ordering claims on the shared episodes (:mod:`spf_rl.stats`). :func:`write_reports`
writes it as ``table1.json``, ``table1.md`` and ``table1.png``; the per-episode records
are cached with :mod:`spf_rl.records_cache`.
"""
from __future__ import annotations

import dataclasses
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from envs.atomic_io import atomic_write_json, atomic_write_text
from spf_rl.pointer_pace import BACKWARD_PACE
from spf_rl.stats import hierarchical_bootstrap_ci, paired_bootstrap, seed_summary

logger = logging.getLogger("table1")

#: Scores reported per episode: our geodesic success (the headline), SPL, and the RPF lab code's Euclidean success.
TABLE1_METRICS = ("success", "spl", "success_lab")
CONFIDENCE = 0.95
#: A claim "a beats b" holds when the one-sided paired p-value is below this.
ALPHA = 0.05
#: Per-episode fields kept in Table 1's cache files (:mod:`spf_rl.records_cache`).
CACHED_FIELDS = ("episode_index", "episode_seed", "house_seed", "success", "success_lab", "spl", "steps")
STATISTICS = (
    "mean: over seeds and episodes (every seed plays the same episodes); sd: sample sd (ddof=1) of the "
    "per-seed means; ci: 95% percentile bootstrap of the pooled mean that resamples houses, then episodes "
    "within each drawn house (seeds are not resampled; conservative when houses do not differ). Claims "
    "'a beats b': paired bootstrap of mean(a) - mean(b) on the shared episodes, the same resamples for a "
    "and b, pooled over seeds; p_greater = fraction of resamples with a difference <= 0; holds when "
    "p_greater < 0.05."
)


@dataclass(frozen=True)
class Line:
    """One line of the table: a row, one evaluated sparsity of the random model, or a DAgger line."""

    name: str
    label: str
    row: str
    model: str
    sparsity: float
    memory_bytes: int
    checkpoint_stem: str
    paper_success: float | None = None
    paper_spl: float | None = None
    dagger_of: str | None = None


# ------------------------------------------------------------------------- files
def write_table_json(path: Path, payload: dict) -> None:
    """The Table 1 JSON files are indented by one space (they are long)."""
    atomic_write_json(path, payload, indent=1)


# ------------------------------------------------------------------- statistics

def shared_episodes(reference: dict, set_name: str, where: str, records: list[dict]) -> np.ndarray:
    """The houses of a set's episodes, after checking that ``records`` play the same episodes as the others."""
    seeds = [r["episode_seed"] for r in records]
    houses = np.asarray([r["house_seed"] for r in records])
    if set_name not in reference:
        reference[set_name] = (seeds, houses, where)
    elif seeds != reference[set_name][0] or not np.array_equal(houses, reference[set_name][1]):
        raise ValueError(
            f"{where} did not play the same {set_name} episodes as {reference[set_name][2]}: paired comparisons "
            "need one evaluation config for every line (delete the stale cache files and rerun)."
        )
    return houses


def metric_arrays(per_seed: dict) -> dict[str, np.ndarray]:
    """``{metric: (seeds, episodes) array}`` of ``{seed: records}``."""
    return {m: np.asarray([[float(r[m]) for r in recs] for recs in per_seed.values()]) for m in TABLE1_METRICS}


def summarize_set(per_seed: dict, houses: np.ndarray, num_resamples: int) -> dict:
    """Per-seed means, mean +- sd over seeds and the house-level interval of each metric."""
    arrays = metric_arrays(per_seed)
    out = {
        "episodes": int(houses.size),
        "houses": int(np.unique(houses).size),
        "seeds": list(per_seed),
        "per_seed": {str(seed): {m: float(arrays[m][i].mean()) for m in TABLE1_METRICS} for i, seed in enumerate(per_seed)},
    }
    for m in TABLE1_METRICS:
        summary = seed_summary(arrays[m].mean(axis=1))
        ci = hierarchical_bootstrap_ci(arrays[m], houses, CONFIDENCE, num_resamples)
        out[m] = {"mean": summary.mean, "sd": summary.sd, "ci": list(ci)}
    return out


def check_claims(claims, evaluations: dict, houses: dict, num_resamples: int) -> list[dict]:
    """Every claim on every set and metric where both sides have records (else listed with ``skipped``)."""
    results = []
    for a, b, text in claims:
        for set_name, set_houses in houses.items():
            sides = [evaluations.get(name, {}).get(set_name) or {} for name in (a, b)]
            if not all(sides):
                missing = [name for name, side in zip((a, b), sides) if not side]
                results.append({"claim": text, "a": a, "b": b, "set": set_name, "skipped": f"no records of {', '.join(missing)}"})
                continue
            arrays = [metric_arrays(side) for side in sides]
            for m in TABLE1_METRICS:
                test = paired_bootstrap(arrays[0][m], arrays[1][m], set_houses, CONFIDENCE, num_resamples)
                results.append({
                    "claim": text, "a": a, "b": b, "set": set_name, "metric": m,
                    "seeds_a": len(sides[0]), "seeds_b": len(sides[1]),
                    "difference": test.difference, "ci": list(test.ci),
                    "p_greater": test.p_greater, "p_two_sided": test.p_two_sided, "holds": test.p_greater < ALPHA,
                })
    return results


def build_table(
    lines: Sequence[Line],
    evaluations: dict,
    sets: dict,
    seeds: Sequence[int],
    claims: Sequence[tuple[str, str, str]],
    missing: Sequence[dict],
    num_resamples: int,
) -> dict:
    """The table as a dict (see the module docstring); ``evaluations`` is ``{line: {set: {seed: records}}}``.

    Raises:
        ValueError: two evaluations of one set did not play the same episodes.
    """
    from spf_rl.evaluation import config_dict

    reference: dict = {}
    rows = []
    for line in lines:
        entry = {**dataclasses.asdict(line), "seeds_expected": [] if line.model == "open_loop" else list(seeds), "sets": {}}
        present: set = set()
        for set_name in sets:
            per_seed = evaluations.get(line.name, {}).get(set_name) or {}
            if not per_seed:
                entry["sets"][set_name] = None
                continue
            for seed, records in per_seed.items():
                houses = shared_episodes(reference, set_name, f"{line.name} seed {seed}", records)
            entry["sets"][set_name] = summarize_set(per_seed, houses, num_resamples)
            present |= set(per_seed)
        entry["seeds"] = sorted(present, key=lambda s: -1 if s is None else s)
        entry["missing_seeds"] = [s for s in entry["seeds_expected"] if s not in present]
        rows.append(entry)
    houses = {name: ref[1] for name, ref in reference.items()}
    return {
        "sets": {name: config_dict(config) for name, config in sets.items()},
        "seeds": list(seeds),
        "statistics": {"description": STATISTICS, "confidence": CONFIDENCE, "alpha": ALPHA, "num_resamples": num_resamples},
        "rows": rows,
        "claims": check_claims(claims, evaluations, houses, num_resamples),
        "missing": list(missing),
    }


# ---------------------------------------------------------------------- reports
def cell(stats: dict | None, metric: str, with_ci: bool = True) -> str:
    """``mean +- sd [low, high]`` (no sd for one evaluation; no interval without ``with_ci``), or ``-``."""
    if not stats:
        return "-"
    value = stats[metric]
    sd = "" if value["sd"] is None else f" ± {value['sd']:.3f}"
    return f"{value['mean']:.3f}{sd}" + (f" [{value['ci'][0]:.3f}, {value['ci'][1]:.3f}]" if with_ci else "")


def seed_count(row: dict) -> str:
    """``"<scored> of <expected>"`` seeds of a line."""
    return f"{len(row['seeds'])} of {len(row['seeds_expected'])}"


def seeds_cell(row: dict) -> str:
    if row["model"] == "open_loop":
        return "- (not trained)"
    text = seed_count(row)
    return text + (f" (missing: {', '.join(map(str, row['missing_seeds']))})" if row["missing_seeds"] else "")


def p_text(p: float, num_resamples: int) -> str:
    return f"< {1 / num_resamples:.0e}" if p == 0 else f"{p:.4f}"


def markdown(table: dict) -> str:
    """The table, the claims and what is missing, as markdown."""
    sets = table["sets"]
    test, extended = sets.get("test"), sets.get("extended")
    first = test or extended
    dagger = {row["dagger_of"]: row for row in table["rows"] if row["dagger_of"]}
    stats = table["statistics"]
    test_text = "test split, its default houses" if test else "not run"
    extended_text = f"{extended['num_houses']} test-split houses" if extended else "not run"
    out = [
        "# Table 1",
        "",
        f"Every row is scored on the same {first['num_episodes']:,} episodes per set, `{first['noise']}` noise, "
        f"evaluation seed {first['seed']}: the test set ({test_text}) and the extended set ({extended_text}). "
        f"Training seeds {', '.join(map(str, table['seeds']))}. Success is ours (geodesic, the headline); "
        "success (lab) is the RPF lab code's Euclidean criterion. Paper: Habitat / Matterport3D.",
        "",
        f"Statistics: {stats['description']} Bootstrap resamples: {stats['num_resamples']:,}.",
        "",
        "| row | seeds | memory (bytes) | success | SPL | success (lab) | extended: success | extended: SPL "
        "| DAgger: success | paper success | paper SPL |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in (r for r in table["rows"] if not r["dagger_of"]):
        on_test, on_extended = row["sets"].get("test"), row["sets"].get("extended")
        dagger_row = dagger.get(row["name"])
        dagger_text = "-"
        if dagger_row:
            dagger_text = cell(dagger_row["sets"].get("test"), "success") + f" ({seeds_cell(dagger_row)} seeds)"
        paper = ["-" if v is None else f"{v:.3f}" for v in (row["paper_success"], row["paper_spl"])]
        out.append(
            f"| {row['label']}{marks(row, dagger_row)} | {seeds_cell(row)} | {row['memory_bytes']:,} | {cell(on_test, 'success')} | {cell(on_test, 'spl')} "
            f"| {cell(on_test, 'success_lab')} | {cell(on_extended, 'success')} | {cell(on_extended, 'spl')} | {dagger_text} "
            f"| {paper[0]} | {paper[1]} |"
        )
    budget = table.get("budget", {})
    if "bc" in budget:
        out += ["", f"Budget of every row: {budget['bc']['gradient_steps']:,} gradient steps on {budget['bc']['episodes']:,} "
                f"episodes (`--preset {budget['bc']['preset']}`); every DAgger column: {budget['dagger']['rounds']} "
                f"learner-driven rounds, {budget['dagger']['gradient_steps']:,} gradient steps (`--preset "
                f"{budget['dagger']['preset']}`)."]
    out += footnotes(table)
    out += seed_by_seed(table)
    out += ["", "## Ordering claims (paired bootstrap on the shared episodes, pooled over seeds)", "",
            "| claim | set | metric | a - b [95% CI] | p (a > b) | p (two-sided) | holds (p < 0.05) | seeds a / b |",
            "|---|---|---|---|---|---|---|---|"]
    for claim in table["claims"]:
        if "skipped" in claim:
            out.append(f"| {claim['claim']} | {claim['set']} | - | - | - | - | not tested: {claim['skipped']} | - |")
            continue
        low, high = claim["ci"]
        out.append(
            f"| {claim['claim']} | {claim['set']} | {claim['metric']} | {claim['difference']:+.3f} [{low:+.3f}, {high:+.3f}] "
            f"| {p_text(claim['p_greater'], stats['num_resamples'])} | {p_text(claim['p_two_sided'], stats['num_resamples'])} "
            f"| {'yes' if claim['holds'] else 'no'} | {claim['seeds_a']} / {claim['seeds_b']} |"
        )
    out += ["", "## Missing checkpoints", ""]
    out += [f"- {item['line']} seed {item['seed']}: no `{item['checkpoint']}`" for item in table["missing"]] or ["none"]
    return "\n".join(out) + "\n"


#: Marks a line with a seed whose pointer runs backwards (its ``pointer_pace`` below ``BACKWARD_PACE``).
BACKWARD_MARK = "‡"
#: What ``pointer_pace`` in ``results/table1.json`` is.
PACE_NOTE = (
    "each seed's checkpoint's mean pointer increment per step (demonstration steps), teacher-forced on the "
    "validation episodes of `dataset` (spf_rl.pointer_pace); below 0 the pointer runs backwards"
)


def backward_seeds(row: dict | None) -> list[int]:
    """Seeds of a table line whose pointer runs backwards (``pointer_pace`` below ``BACKWARD_PACE``)."""
    paces = (row or {}).get("pointer_pace") or {}
    return sorted(int(seed) for seed, pace in paces.items() if pace < BACKWARD_PACE)


#: Marks a line with a seed that the pointer-collapse guard restarted (:mod:`spf_rl.train.pointer_guard`).
RESTART_MARK = "§"


def restarted_seeds(row: dict | None) -> dict[str, list[dict]]:
    """``{seed: restarts}`` of a table line's runs that the pointer-collapse guard restarted (none: ``{}``)."""
    return {seed: restarts for seed, restarts in ((row or {}).get("pointer_restarts") or {}).items() if restarts}


def marks(*rows: dict | None) -> str:
    """The footnote marks of a line (``rows``: the line and its DAgger column): a pointer that runs backwards,
    a seed restarted by the pointer-collapse guard."""
    mark = f" {BACKWARD_MARK}" if any(backward_seeds(row) for row in rows) else ""
    return mark + (f" {RESTART_MARK}" if any(restarted_seeds(row) for row in rows) else "")


def footnotes(table: dict) -> list[str]:
    """The notes of the marks that some line carries (:func:`marks`), one paragraph each."""
    out = []
    found: dict[str, list[int]] = {}
    for row in table["rows"]:
        if backward_seeds(row):
            found.setdefault(row["label"].split(",")[0] + (" + DAgger" if row["dagger_of"] else ""), backward_seeds(row))
    if found:
        named = "; ".join(f"{label}: seed {', '.join(map(str, seeds))}" for label, seeds in found.items())
        out += ["", f"{BACKWARD_MARK} pointer runs backwards ({named}; `pointer_pace`): training drove the paper's "
                "tanh(b) to -1, cutting off the memory; kept in the means."]
    restarted = {row["label"].split(",")[0]: restarted_seeds(row) for row in table["rows"] if restarted_seeds(row)}
    if restarted:
        named = "; ".join(f"{label}: " + ", ".join(f"seed {seed} after epoch {r[0]['epoch']}" for seed, r in seeds.items())
                          for label, seeds in restarted.items())
        out += ["", f"{RESTART_MARK} restarted by the pointer-collapse guard ({named}): the pointer ran backwards "
                "early in training, and the run started again from a fresh initialisation (`pointer_restarts`)."]
    return out


def seed_by_seed(table: dict) -> list[str]:
    """Each trained line's success per training seed on every set, its pointer pace per seed, and the seed its
    shipped name holds (``table["shipped"]``, where the table has it), as a markdown section."""
    seeds, set_names = table["seeds"], list(table["sets"])
    shipped = table.get("shipped") or {}
    header = [f"{name}: seed {seed}" for name in set_names for seed in seeds]
    out = ["", "## Seed by seed", "",
           "Success per training seed; pointer pace per seed (below 0: runs backwards); the seed the line's name ships "
           "(best validation success).", "",
           "| line | " + " | ".join(header) + " | pointer pace | ships |", "|---" * (len(header) + 3) + "|"]
    for row in (r for r in table["rows"] if r["model"] != "open_loop"):
        cells = []
        for name in set_names:
            per_seed = (row["sets"].get(name) or {}).get("per_seed", {})
            cells += [f"{per_seed[str(seed)]['success']:.3f}" if str(seed) in per_seed else "-" for seed in seeds]
        paces = row.get("pointer_pace") or {}
        pace = " / ".join(f"{paces[str(seed)]:+.2f}" if str(seed) in paces else "-" for seed in seeds) if paces else "-"
        ship = shipped.get(row["checkpoint_stem"])
        ship_text = f"seed {ship['seed']} ({ship['val_success']:.3f})" if ship else "-"
        out.append(f"| {row['label']} | " + " | ".join(cells) + f" | {pace} | {ship_text} |")
    return out


def _sparsities_line(rows: list[dict]) -> str:
    """One summary line for a model scored at several sparsities: means side by side."""
    def means(metric: str) -> str:
        return " / ".join(f"{r['sets']['test'][metric]['mean']:.3f}" for r in rows)

    sparsities = " / ".join(f"{r['sparsity']:g}" for r in rows)
    label = f"{rows[0]['label'].split(',')[0]}, at {sparsities}" + marks(*rows)
    return (
        f"| {label} | `{rows[0]['checkpoint_stem']}` | {seed_count(rows[0])} | {means('success')} | {means('spl')} "
        f"| - | - |"
    )


def summary_markdown(table: dict) -> str:
    """The README's results table: test-set success and SPL per row (mean ± sd over seeds), the
    DAgger column and the paper's numbers (the ordering claims are in ``table1.md``).

    Examples:
        >>> stats = {"success": {"mean": 0.8, "sd": None}, "spl": {"mean": 0.75, "sd": None}}
        >>> row = {"name": "spf-s0.8", "row": "spf-s0.8", "checkpoint_stem": "spf-s0.8", "label": "SPF 0.8", "model": "spf", "dagger_of": None, "seeds": [0],
        ...        "seeds_expected": [0, 1], "missing_seeds": [1], "sets": {"test": stats},
        ...        "paper_success": 0.819, "paper_spl": 0.737}
        >>> print(summary_markdown({"rows": [row], "claims": []}).splitlines()[2])
        | SPF 0.8 | `spf-s0.8` | 1 of 2 | 0.800 | 0.750 | - | 0.819 / 0.737 |
    """
    dagger = {row["dagger_of"]: row for row in table["rows"] if row["dagger_of"]}
    out = [
        "| model | checkpoint | seeds | success | SPL | + DAgger: success | paper: success / SPL |",
        "|---|---|---|---|---|---|---|",
    ]
    untrained: dict[str, str] = {}
    lines = [r for r in table["rows"] if not r["dagger_of"]]
    for row in lines:
        test = row["sets"].get("test")
        if not test:  # no seed scored yet: named below the table, once per row
            untrained.setdefault(row["row"], row["label"].split(",")[0])
            continue
        at = [r for r in lines if r["row"] == row["row"] and r["sets"].get("test")]
        if len(at) > 1:  # one model scored at several sparsities: one line, values side by side
            if row is at[0]:
                out.append(_sparsities_line(at))
            continue
        seeds = "-" if row["model"] == "open_loop" else seed_count(row)
        dagger_row = dagger.get(row["name"])
        dagger_text = "-"
        if dagger_row and dagger_row["sets"].get("test"):
            dagger_text = f"{cell(dagger_row['sets']['test'], 'success', with_ci=False)} ({seed_count(dagger_row)})"
        paper = "-" if row["paper_success"] is None else f"{row['paper_success']:.3f} / {row['paper_spl']:.3f}"
        checkpoint = "-" if row["model"] == "open_loop" else f"`{row['checkpoint_stem']}`"
        label = row["label"] + marks(row, dagger_row)
        out.append(
            f"| {label} | {checkpoint} | {seeds} | {cell(test, 'success', with_ci=False)} | {cell(test, 'spl', with_ci=False)} "
            f"| {dagger_text} | {paper} |"
        )
    if untrained:
        out += ["", f"Not scored yet (no checkpoint of this noise model): {', '.join(untrained.values())}."]
    out += footnotes(table)
    return "\n".join(out) + "\n"


def plot(table: dict, path: Path) -> None:
    """Success and SPL per line: ours on both sets and DAgger with house-level intervals, the seeds'
    means as small dots, the paper's numbers as stars; the series are side by side within each line."""
    from spf_rl.viz import pyplot, write_figure

    plt = pyplot()
    lines = [row for row in table["rows"] if not row["dagger_of"]]
    dagger = {row["dagger_of"]: row for row in table["rows"] if row["dagger_of"]}
    series = [
        ("ours, test set", "o", lambda row: row["sets"].get("test")),
        ("ours, extended set (100 houses)", "s", lambda row: row["sets"].get("extended")),
        ("DAgger, test set", "D", lambda row: dagger[row["name"]]["sets"].get("test") if row["name"] in dagger else None),
    ]
    offsets = np.linspace(-0.3, 0.3, len(series) + 1)
    fig, axes = plt.subplots(1, 2, figsize=(max(9.0, 1.1 * len(lines) + 3), 4.8), sharey=True)
    x = np.arange(len(lines))
    for ax, metric in zip(axes, ("success", "spl")):
        for (label, marker, stats_of), offset, color in zip(series, offsets, ("C0", "C1", "C2")):
            points = [(i, stats_of(row)) for i, row in enumerate(lines) if stats_of(row)]
            if not points:
                continue
            xs = np.array([i for i, _ in points]) + offset
            means = np.array([s[metric]["mean"] for _, s in points])
            cis = np.array([s[metric]["ci"] for _, s in points])
            ax.errorbar(xs, means, yerr=[means - cis[:, 0], cis[:, 1] - means], fmt=marker, color=color, capsize=3, label=label)
            for xi, (_, s) in zip(xs, points):
                seed_means = [v[metric] for v in s["per_seed"].values()]
                ax.plot([xi + 0.07] * len(seed_means), seed_means, "o", mfc="none", color=color, alpha=0.7, markersize=3)
        paper = [(i, row[f"paper_{metric}"]) for i, row in enumerate(lines) if row[f"paper_{metric}"] is not None]
        if paper:
            xs = np.array([i for i, _ in paper]) + offsets[-1]
            ax.plot(xs, [v for _, v in paper], "*", color="k", markersize=9, label="paper (Habitat)")
        ax.set_xticks(x, [row["name"] for row in lines], rotation=40, ha="right", fontsize=8)
        name = {"success": "success", "spl": "SPL"}[metric]
        ax.set_title(f"{name} (bars: 95% house-level CI; small circles: seeds)", fontsize=9)
        ax.set_ylim(0, 1)
        ax.grid(axis="y", alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=len(labels), fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    write_figure(fig, path, dpi=120)


def write_reports(table: dict, out: Path) -> None:
    """``table1.json``, ``table1.md``, ``table1_summary.md`` (the README's table) and
    ``table1.png`` in ``out``, each written atomically."""
    out.mkdir(parents=True, exist_ok=True)
    write_table_json(out / "table1.json", table)
    text = markdown(table)
    atomic_write_text(out / "table1.md", text)
    atomic_write_text(out / "table1_summary.md", summary_markdown(table))
    plot(table, out / "table1.png")
    logger.info("wrote %s/table1.{json,md,png}\n%s", out, text)
