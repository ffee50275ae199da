"""Figures: training curves, trajectories on the house map, pointer plots, rollout videos."""
from __future__ import annotations

from pathlib import Path

import matplotlib
import numpy as np

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


def plot_pointer(eta: np.ndarray, nearest_demo_index: np.ndarray, memory_indices: np.ndarray, ax=None, title: str = ""):
    """The pointer eta over time against the demo index the agent is actually nearest to.

    Args:
        eta: ``(T,)`` pointer used at each step (0-based demo index).
        nearest_demo_index: ``(T,)`` index of the demo pose nearest to the agent.
        memory_indices: demo indices held in memory (drawn as horizontal ticks).
        ax: matplotlib axis (a new figure otherwise).
        title: axis title.

    Examples:
        >>> ax = plot_pointer(np.arange(5.0), np.arange(5), np.array([0, 4]))
        >>> len(ax.get_lines()) >= 2
        True
    """
    if ax is None:
        _, ax = plt.subplots(figsize=(5, 3.5))
    steps = np.arange(len(eta))
    ax.plot(steps, eta, "o-", markersize=3, label="pointer eta")
    ax.plot(steps, nearest_demo_index, "s-", markersize=3, label="nearest demo index (privileged)")
    for index in memory_indices:
        ax.axhline(index, color="grey", alpha=0.25, linewidth=0.8)
    ax.set_xlabel("step")
    ax.set_ylabel("demo index")
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title)
    return ax


def write_gif(frames: list[np.ndarray], path: str | Path, fps: int = 5) -> Path:
    """Write RGB frames ``(H, W, 3)`` uint8 as an animated GIF with imageio."""
    import imageio.v2 as imageio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    imageio.mimsave(path, frames, duration=1.0 / fps, loop=0)
    return path


def figure_to_array(fig) -> np.ndarray:
    """Render a matplotlib figure to an RGB uint8 array."""
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
