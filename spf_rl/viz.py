"""Figures: training curves, trajectories on the house map, pointer plots, rollout videos."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def plot_training_curves(history: list[dict], path: str | Path, title: str = "training") -> Path:
    """Plot training loss/accuracy and validation success/SPL per epoch to a PNG.

    Args:
        history: one dict per epoch with ``epoch``, ``train_loss``, ``train_accuracy``,
            ``val_success``, ``val_spl``.
        path: output PNG.
        title: figure title.

    Examples:
        >>> import tempfile, os
        >>> out = plot_training_curves([{"epoch": 1, "train_loss": 1.0, "train_accuracy": 0.5,
        ...     "val_success": 0.2, "val_spl": 0.1}], os.path.join(tempfile.mkdtemp(), "c.png"))
        >>> out.exists()
        True
    """
    path = Path(path)
    epochs = [h["epoch"] for h in history]
    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 3.5))
    left.plot(epochs, [h["train_loss"] for h in history], "o-", label="train loss")
    left.set_xlabel("epoch")
    left.set_ylabel("cross-entropy")
    twin = left.twinx()
    twin.plot(epochs, [h["train_accuracy"] for h in history], "s--", color="tab:orange", label="train accuracy")
    twin.set_ylabel("accuracy")
    left.legend(loc="upper left", fontsize=8)
    twin.legend(loc="upper right", fontsize=8)
    right.plot(epochs, [h["val_success"] for h in history], "o-", label="val success")
    right.plot(epochs, [h["val_spl"] for h in history], "s-", label="val SPL")
    right.set_ylim(0, 1)
    right.set_xlabel("epoch")
    right.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
