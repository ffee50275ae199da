"""How well does validation pick checkpoints? The picking study's statistics and figure.

A BC run trained with ``keep_epochs=true`` keeps every epoch's weights
(``<run>/epochs/epoch-NNN.pt``) beside its per-epoch validation success (``last.pt``'s
history). ``recipes/picking_study.py`` scores every epoch on test; this module ranks
the epochs by validation against test (Spearman's rho and Kendall's tau, scipy) and
reports the test success of the epoch each rule picks.
"""
from __future__ import annotations

from pathlib import Path

from scipy import stats as scipy_stats

from spf_rl.checkpoint import load_checkpoint
from spf_rl.train.run import EPOCHS_DIR


def epoch_files(run: Path) -> dict[int, Path]:
    """Epoch number -> weights file of a run kept with ``keep_epochs``."""
    return {int(path.stem.split("-")[1]): path for path in sorted((run / EPOCHS_DIR).glob("epoch-*.pt"))}


def validation_history(run: Path) -> dict[int, float]:
    """Epoch number -> validation success of the validated epochs, from the run's ``last.pt``."""
    history = load_checkpoint(run / "last.pt")["history"]
    return {record["epoch"]: record["val_success"] for record in history if record["val_success"] is not None}


def rank_agreement(val: list[float], test: list[float]) -> dict:
    """Spearman's rho and Kendall's tau (with p-values) between two per-epoch score lists
    (``None`` where one list is constant: no ranking to agree with)."""
    if len(set(val)) < 2 or len(set(test)) < 2:
        return {"spearman_rho": None, "spearman_p": None, "kendall_tau": None, "kendall_p": None}
    rho, rho_p = scipy_stats.spearmanr(val, test)
    tau, tau_p = scipy_stats.kendalltau(val, test)
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
    """Validation and test success per epoch, the epoch validation picks marked."""
    from spf_rl.viz import pyplot, write_figure

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
    write_figure(fig, path, dpi=120)
