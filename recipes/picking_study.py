"""How well does validation pick checkpoints? Score every epoch of a run on test.

A BC run trained with ``keep_epochs=true`` keeps every epoch's weights
(``<run>/epochs/epoch-NNN.pt``) beside its per-epoch validation success (``last.pt``'s
history). This recipe plays the run's test episodes (its ``config.json``'s ``test``
section; ``--episodes`` overrides the count) with every epoch's weights and reports
how validation ranks the epochs against test: Spearman's rho and Kendall's tau
(scipy), the test success of the epoch validation picks, of the best epoch on test
and of the last epoch. Writes ``<out>/<run name>.json`` and ``.png`` (validation and
test success per epoch); each epoch's test score is kept in the JSON as soon as it is
known, so an interrupted study resumes.

Usage::

    python recipes/bc.py --preset bc_row sparsity=0.4 keep_epochs=true   # bc_row validates every epoch
    python recipes/picking_study.py runs/bc_row/spf-s0.4-seed0 --episodes 1000
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
from pathlib import Path

from spf_rl.device import DEFAULT_DEVICE, DEVICE_CHOICES

logger = logging.getLogger("picking_study")


def epoch_files(run: Path) -> dict[int, Path]:
    """Epoch number -> weights file of a run kept with ``keep_epochs``."""
    from spf_rl.train.bc import EPOCHS_DIR

    return {int(path.stem.split("-")[1]): path for path in sorted((run / EPOCHS_DIR).glob("epoch-*.pt"))}


def validation_history(run: Path) -> dict[int, float]:
    """Epoch number -> validation success of the validated epochs, from the run's ``last.pt``."""
    from spf_rl.checkpoint import load_checkpoint

    history = load_checkpoint(run / "last.pt")["history"]
    return {record["epoch"]: record["val_success"] for record in history if record["val_success"] is not None}


def rank_agreement(val: list[float], test: list[float]) -> dict:
    """Spearman's rho and Kendall's tau (with p-values) between two per-epoch score lists
    (``None`` where one list is constant: no ranking to agree with)."""
    from scipy import stats

    if len(set(val)) < 2 or len(set(test)) < 2:
        return {"spearman_rho": None, "spearman_p": None, "kendall_tau": None, "kendall_p": None}
    rho, rho_p = stats.spearmanr(val, test)
    tau, tau_p = stats.kendalltau(val, test)
    return {"spearman_rho": float(rho), "spearman_p": float(rho_p), "kendall_tau": float(tau), "kendall_p": float(tau_p)}


def summarize_study(epochs: list[int], val: list[float], test: list[float]) -> dict:
    """The rank agreement and the test success of the epochs each rule picks.

    Validation picks the first epoch with the highest validation success (as training
    keeps ``best.pt``); ``oracle`` is the best epoch on test; ``last`` the final one.
    """
    picked = max(range(len(epochs)), key=lambda i: (val[i], -i))
    oracle = max(range(len(epochs)), key=lambda i: (test[i], -i))
    return {
        **rank_agreement(val, test),
        "picked_by_validation": {"epoch": epochs[picked], "val_success": val[picked], "test_success": test[picked]},
        "best_on_test": {"epoch": epochs[oracle], "val_success": val[oracle], "test_success": test[oracle]},
        "last": {"epoch": epochs[-1], "val_success": val[-1], "test_success": test[-1]},
        "regret_of_validation": test[oracle] - test[picked],
    }


def plot_study(path: Path, study: dict) -> None:
    from spf_rl.viz import pyplot

    plt = pyplot()
    rows = study["epochs"]
    epochs = [row["epoch"] for row in rows]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(epochs, [row["val_success"] for row in rows], "o-", label=f"validation ({study['val_episodes']} episodes)")
    ax.plot(epochs, [row["test_success"] for row in rows], "s-", label=f"test ({study['test_episodes']} episodes)")
    picked = study["summary"]["picked_by_validation"]["epoch"]
    ax.axvline(picked, color="grey", linestyle=":", label=f"picked by validation (epoch {picked})")
    ax.set_xlabel("epoch")
    ax.set_ylabel("success")
    rho = study["summary"]["spearman_rho"]
    ax.set_title("Spearman rho " + ("undefined (constant scores)" if rho is None else f"{rho:.2f}"), fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_json(path: Path, payload: dict) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(payload, indent=2))
    os.replace(tmp, path)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", help="a BC run directory trained with keep_epochs=true")
    parser.add_argument("--episodes", type=int, default=None, help="test episodes per epoch (default: the run's test count)")
    parser.add_argument("--out", default="results/picking", help="output directory (default results/picking)")
    parser.add_argument("--device", default=DEFAULT_DEVICE, choices=DEVICE_CHOICES)
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    run = Path(args.run)
    if args.episodes is not None and args.episodes < 1:
        parser.error(f"--episodes must be a positive number of episodes, got {args.episodes}")
    if not (run / "config.json").is_file() or not (run / "last.pt").is_file():
        parser.error(f"run {run} has no config.json and last.pt: give a BC run directory (runs/bc_row/<model>-s<sparsity>-seed<S>)")
    files = epoch_files(run)
    if len(files) < 3:
        parser.error(f"run {run} keeps {len(files)} epoch checkpoints; train it with keep_epochs=true for at least 3 epochs")

    import envs  # noqa: F401  (selects the headless GL back-end first)
    from spf_rl.hub import policy_from_checkpoint
    from spf_rl.train.evaluation import EvalConfig, evaluate_policy

    config = json.loads((run / "config.json").read_text())
    data, test_fields = config["data"], dict(config["test"])
    if args.episodes is not None:
        test_fields["num_episodes"] = args.episodes
    test = EvalConfig(**{**test_fields, "demo_length": data["demo_length"], "max_steps": data["max_steps"], "image_size": data["image_size"]})
    val = validation_history(run)
    if len(set(files) & set(val)) < 3:
        parser.error(f"run {run} validated {len(set(files) & set(val))} of its kept epochs; train it with val_every=1")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{run.parent.name}-{run.name}.json"
    study = json.loads(path.read_text()) if path.exists() else {}
    if study.get("test") != dataclasses.asdict(test):
        study = {"run": str(run), "test": dataclasses.asdict(test), "epochs": []}
    done = {row["epoch"] for row in study["epochs"]}
    for epoch, weights in files.items():
        if epoch in done or epoch not in val:
            continue
        policy, _ = policy_from_checkpoint(weights, device=args.device)
        summary, _ = evaluate_policy(policy, test, progress=not args.quiet)
        study["epochs"].append({"epoch": epoch, "val_success": val[epoch], "test_success": summary["success"], "test_spl": summary["spl"]})
        study["epochs"].sort(key=lambda row: row["epoch"])
        write_json(path, study)
        logger.info("epoch %d: validation %.3f, test %.3f", epoch, val[epoch], summary["success"])
    rows = study["epochs"]
    study["val_episodes"] = config["val"]["num_episodes"]
    study["test_episodes"] = test.num_episodes
    study["summary"] = summarize_study([r["epoch"] for r in rows], [r["val_success"] for r in rows], [r["test_success"] for r in rows])
    write_json(path, study)
    from spf_rl.viz import plot_if_available

    plot_if_available(plot_study, path.with_suffix(".png"), study)
    logger.info("%s", json.dumps(study["summary"], indent=2))
    return study


if __name__ == "__main__":
    main()
