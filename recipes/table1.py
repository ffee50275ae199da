"""Reproduce the paper's Table 1: SPF at sparsity 0.4 / 0.6 / 0.8, RPF (full memory),
RPF action-only, and open-loop replay, under ``paper`` noise on the test split.

Beyond the paper, one more model, ``spf_random``, is trained once with a sparsity
drawn per episode from ``model.sparsity_range`` (default 0.2-1.0; checkpoint
``checkpoints/spf_random-s0.2-1.pt``) and evaluated at each of
:data:`RANDOM_EVAL_SPARSITIES` (rows without paper numbers). With
``--from-checkpoints`` and no such checkpoint, those rows are skipped with a warning.

Trains each missing model with ``recipes/bc.py``'s pipeline (all rows share one
dataset), evaluates every row on the same test episodes, copies each row's best
checkpoint to ``checkpoints/`` and writes:

* ``results/table1.md`` and ``results/table1.json``: ours beside the paper's numbers;
* ``results/table1.png``: success and SPL against sparsity and against memory bytes.

Usage::

    python recipes/table1.py                      # trains what is missing (hours on 2 CPU cores)
    python recipes/table1.py --from-checkpoints   # only evaluates the shipped checkpoints
    python recipes/table1.py optim.epochs=4 data.num_episodes=1500
    python recipes/table1.py device=cuda optim.amp=true   # train and evaluate on a GPU (default device=auto)

``device=`` (as for ``bc.py``) places training and the evaluated policies; envs stay on the CPU.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import shutil
import sys
from collections.abc import Sequence
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from config_utils import load_config  # noqa: E402

#: (row label, model name, sparsity, paper success, paper SPL); paper: Table 1 (Habitat, MP3D).
ROWS = [
    ("SPF sparsity 0.4", "spf", 0.4, 0.782, 0.683),
    ("SPF sparsity 0.6", "spf", 0.6, 0.803, 0.724),
    ("SPF sparsity 0.8", "spf", 0.8, 0.819, 0.737),
    ("RPF action only", "action_only", 0.0, 0.782, 0.648),
    ("RPF (full memory)", "rpf", 1.0, 0.833, 0.752),
    ("open-loop replay", "open_loop", 0.0, None, None),
]
#: Sparsities the one random-sparsity model (``spf_random``) is evaluated at.
RANDOM_EVAL_SPARSITIES = (0.4, 0.6, 0.8, 1.0)
RANDOM_MODEL = "spf_random"


def checkpoint_name(model: str, sparsity: float | Sequence[float]) -> str:
    """File name of a model's checkpoint: ``spf-s0.4.pt``, or ``spf_random-s0.2-1.pt``
    for a sparsity range ``(0.2, 1.0)``."""
    if isinstance(sparsity, Sequence):
        return f"{model}-s" + "-".join(f"{s:g}" for s in sparsity) + ".pt"
    return f"{model}-s{sparsity:g}.pt"


def load_or_train(path: Path, config, train: bool):
    """The policy in checkpoint ``path``, on ``config.device``; if it is missing and ``train``,
    first train ``config`` (a ``BCConfig``) with ``train_bc`` and copy its best checkpoint to ``path``."""
    from spf_rl.hub import policy_from_checkpoint
    from spf_rl.train.bc import train_bc

    model = config.model.name
    if train and not path.exists():
        train_bc(config)
        shutil.copyfile(Path(config.output_dir) / "best.pt", path)
    return policy_from_checkpoint(path, expected_model_type=model, device=config.device)[0]


def make_row(
    label: str,
    model: str,
    sparsity: float,
    memory: int,
    summary: dict,
    paper: tuple[float | None, float | None] = (None, None),
    **extra,
) -> dict:
    """One table row: the label, the model, its memory, the paper's (success, SPL) and our summary."""
    return {
        "row": label,
        "model": model,
        "sparsity": sparsity,
        "memory_bytes": memory,
        "paper_success": paper[0],
        "paper_spl": paper[1],
        **extra,
        **summary,
    }


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--from-checkpoints", action="store_true", help="evaluate checkpoints/ without training")
    parser.add_argument("--checkpoints", default="checkpoints")
    parser.add_argument("--out", default="results")
    parser.add_argument("overrides", nargs="*", help="key=value overrides applied to every row (as for bc.py)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    import envs  # noqa: F401
    from spf_rl.device import resolve_device
    from spf_rl.modules.policy import OpenLoopPolicy
    from spf_rl.train.bc import BCConfig, model_memory_bytes
    from spf_rl.train.evaluation import evaluate_policy

    base = load_config(BCConfig, "bc", args.overrides, preset="table1")
    logging.info("training and evaluating on %s", resolve_device(base.device))  # a missing CUDA fails here, first
    checkpoints, out = Path(args.checkpoints), Path(args.out)
    checkpoints.mkdir(parents=True, exist_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    test_config = dataclasses.replace(
        base.test, demo_length=base.data.demo_length, max_steps=base.data.max_steps, image_size=base.data.image_size
    )
    rows: list[dict] = []

    def row_config(model: str, sparsity: float, path: Path):
        model_config = dataclasses.replace(base.model, name=model, sparsity=sparsity)
        return dataclasses.replace(base, model=model_config, output_dir=f"runs/table1/{path.stem}")

    def evaluate(label, model, sparsity, policy, memory, paper=(None, None), **extra):
        summary, _ = evaluate_policy(policy, test_config, progress=base.progress)
        rows.append(make_row(label, model, sparsity, memory, summary, paper, **extra))
        logging.info("%s: success %.3f SPL %.3f", label, summary["success"], summary["spl"])

    for label, model, sparsity, paper_success, paper_spl in ROWS:
        if model == "open_loop":
            policy, memory = OpenLoopPolicy(), base.data.demo_length
        else:
            shipped = checkpoints / checkpoint_name(model, sparsity)
            train_sparsity = sparsity if model == "spf" else base.model.sparsity
            policy = load_or_train(shipped, row_config(model, train_sparsity, shipped), not args.from_checkpoints)
            memory = model_memory_bytes(model, base.data.demo_length, sparsity, base.data.image_size)
        evaluate(label, model, sparsity, policy, memory, (paper_success, paper_spl))

    sparsity_range = tuple(base.model.sparsity_range)
    shipped = checkpoints / checkpoint_name(RANDOM_MODEL, sparsity_range)
    if args.from_checkpoints and not shipped.exists():
        logging.warning("%s is missing: skipping the %s rows (run without --from-checkpoints to train it).", shipped, RANDOM_MODEL)
    else:
        policy = load_or_train(shipped, row_config(RANDOM_MODEL, base.model.sparsity, shipped), not args.from_checkpoints)
        span = "-".join(f"{s:g}" for s in sparsity_range)
        for sparsity in RANDOM_EVAL_SPARSITIES:
            policy.set_sparsity(sparsity)
            memory = model_memory_bytes(RANDOM_MODEL, base.data.demo_length, sparsity, base.data.image_size)
            label = f"SPF random sparsity {span}, at {sparsity:g}"
            evaluate(label, RANDOM_MODEL, sparsity, policy, memory, sparsity_range=list(sparsity_range))
    (out / "table1.json").write_text(json.dumps({"rows": rows, "test": dataclasses.asdict(test_config)}, indent=2))
    (out / "table1.md").write_text(markdown_table(rows, test_config))
    plot_rows(rows, out / "table1.png")
    print(markdown_table(rows, test_config))
    return rows


def markdown_table(rows: list[dict], test_config) -> str:
    def fmt(value):
        return "-" if value is None else f"{value:.3f}"

    lines = [
        f"Test split, {test_config.num_episodes} episodes, `{test_config.noise}` noise, seed {test_config.seed}. "
        "95% bootstrap confidence intervals in brackets. Paper: Habitat / Matterport3D.",
        "",
        "| model | memory (bytes) | success | SPL | paper success | paper SPL |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        s_low, s_high = row["success_ci"]
        p_low, p_high = row["spl_ci"]
        lines.append(
            f"| {row['row']} | {row['memory_bytes']:,} | {row['success']:.3f} [{s_low:.3f}, {s_high:.3f}] "
            f"| {row['spl']:.3f} [{p_low:.3f}, {p_high:.3f}] | {fmt(row['paper_success'])} | {fmt(row['paper_spl'])} |"
        )
    return "\n".join(lines) + "\n"


def plot_rows(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (by_sparsity, by_bytes) = plt.subplots(1, 2, figsize=(10, 4))
    learned = [r for r in rows if r["model"] not in ("open_loop", RANDOM_MODEL)]
    random_rows = [r for r in rows if r["model"] == RANDOM_MODEL]
    for metric, marker in (("success", "o"), ("spl", "s")):
        xs = [r["sparsity"] for r in learned]
        by_sparsity.plot(xs, [r[metric] for r in learned], marker, label=f"ours {metric}")
        paper = [(r["sparsity"], r[f"paper_{metric}"]) for r in learned if r[f"paper_{metric}"] is not None]
        by_sparsity.plot(*zip(*paper), marker, mfc="none", label=f"paper {metric}")
        by_bytes.plot([r["memory_bytes"] for r in learned], [r[metric] for r in learned], marker, label=metric)
        if random_rows:  # one model at several sparsities: a separate series, joined by a line
            label = f"one random-sparsity model {metric}"
            ys = [r[metric] for r in random_rows]
            by_sparsity.plot([r["sparsity"] for r in random_rows], ys, marker + ":", label=label)
            by_bytes.plot([r["memory_bytes"] for r in random_rows], ys, marker + ":", label=label)
    open_loop = [r for r in rows if r["model"] == "open_loop"]
    if open_loop:
        by_sparsity.axhline(open_loop[0]["success"], color="grey", linestyle="--", label="open-loop success")
    by_sparsity.set_xlabel("memory sparsity (0 = action only)")
    by_bytes.set_xlabel("memory per demonstration (bytes)")
    by_bytes.set_xscale("symlog")
    for ax in (by_sparsity, by_bytes):
        ax.set_ylim(0, 1)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
