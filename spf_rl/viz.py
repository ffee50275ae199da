"""Figures: training curves, trajectories on the house map, pointer plots, rollout videos.

Needs the ``viz`` extra (matplotlib, imageio): ``pip install -e ".[viz]"``. The
plotting libraries are imported when a function is called, not with the module.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from envs.atomic_io import atomic_write, atomic_write_path

logger = logging.getLogger(__name__)

#: Resolution of the figures written by this module, dots per inch.
FIGURE_DPI = 110
#: How to install what this module needs.
VIZ_INSTALL_HINT = 'install the viz extra: pip install -e ".[viz]" (matplotlib, imageio)'


def pyplot():
    """:mod:`matplotlib.pyplot`, or an :class:`ImportError` that says how to install it.

    matplotlib chooses its back-end (Agg on a machine without a display).
    """
    try:
        import matplotlib.pyplot as plt
    except ImportError as err:
        raise ImportError(f"spf_rl.viz needs matplotlib: {VIZ_INSTALL_HINT}.") from err
    return plt


def plot_if_available(plot, *args, **kwargs):
    """``plot(*args, **kwargs)``, or ``None`` with a logged warning when the viz extra is
    missing: a training run still finishes (and keeps its JSON) without its figure."""
    try:
        return plot(*args, **kwargs)
    except ImportError as err:
        logger.warning("figure skipped: %s", err)
        return None


def write_figure(fig, path: str | Path, dpi: int = FIGURE_DPI) -> Path:
    """Write ``fig`` to ``path`` atomically (:func:`~envs.atomic_io.atomic_write`; the format from its
    suffix, folders created) and close it.

    Examples:
        >>> import tempfile, os
        >>> fig = pyplot().figure()
        >>> write_figure(fig, os.path.join(tempfile.mkdtemp(), "f.png")).exists()
        True
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda handle: fig.savefig(handle, dpi=dpi, format=path.suffix[1:]), binary=True)
    pyplot().close(fig)
    return path


def save_figure(fig, path: str | Path, title: str, dpi: int = FIGURE_DPI) -> Path:
    """Title ``fig``, lay it out, write it to ``path`` (a PNG; folders created) and close it."""
    fig.suptitle(title)
    fig.tight_layout()
    return write_figure(fig, path, dpi)


def plot_training_curves(history: list[dict], path: str | Path, title: str = "training") -> Path:
    """Plot training loss/accuracy and validation success/SPL per epoch to a PNG.

    Args:
        history: one dict per epoch with ``epoch``, ``train_loss``, ``train_accuracy``,
            ``val_success``, ``val_spl`` (``None`` for an epoch that was not validated).
        path: output PNG.
        title: figure title.

    Examples:
        >>> import tempfile, os
        >>> out = plot_training_curves([{"epoch": 1, "train_loss": 1.0, "train_accuracy": 0.5,
        ...     "val_success": 0.2, "val_spl": 0.1}], os.path.join(tempfile.mkdtemp(), "c.png"))
        >>> out.exists()
        True
    """
    plt = pyplot()
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
    validated = [h for h in history if h["val_success"] is not None]  # epochs a run validated (val_every)
    right.plot([h["epoch"] for h in validated], [h["val_success"] for h in validated], "o-", label="val success")
    right.plot([h["epoch"] for h in validated], [h["val_spl"] for h in validated], "s-", label="val SPL")
    right.set_ylim(0, 1)
    right.set_xlabel("epoch")
    right.legend(fontsize=8)
    return save_figure(fig, path, title)


def plot_success_by_length(results: dict[str, list[dict]], path: str | Path, title: str = "success against route length") -> Path:
    """Success and SPL (with 95% CIs) against the demonstration length, one line per model, to a PNG.

    Args:
        results: ``{model label: rows}``, a row per length with ``demo_length``, ``success``,
            ``spl`` and optionally ``success_ci`` / ``spl_ci`` (``[low, high]``), as
            :func:`spf_rl.evaluation.evaluate_lengths` gives them.
        path: output PNG.
        title: figure title.

    Examples:
        >>> import tempfile, os
        >>> rows = [{"demo_length": 30, "success": 0.8, "spl": 0.7, "success_ci": [0.7, 0.9], "spl_ci": [0.6, 0.8]},
        ...         {"demo_length": 100, "success": 0.4, "spl": 0.3}]
        >>> plot_success_by_length({"spf": rows}, os.path.join(tempfile.mkdtemp(), "l.png")).exists()
        True
    """
    plt = pyplot()
    path = Path(path)
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5), sharex=True)
    for label, rows in results.items():
        rows = sorted(rows, key=lambda row: row["demo_length"])
        lengths = [row["demo_length"] for row in rows]
        for ax, key in zip(axes, ("success", "spl")):
            values = np.array([row[key] for row in rows])
            intervals = np.array([row.get(f"{key}_ci", (row[key], row[key])) for row in rows], dtype=float)
            error = np.abs(intervals.T - values)
            ax.errorbar(lengths, values, yerr=error, fmt="o-", capsize=3, label=label)
    for ax, name in zip(axes, ("success", "SPL")):
        ax.set_xlabel("demonstration length n (steps)")
        ax.set_ylabel(f"{name} (95% CI)")
        ax.set_ylim(0, 1)
        ax.set_xticks(sorted({row["demo_length"] for rows in results.values() for row in rows}))
        ax.legend(fontsize=8)
    return save_figure(fig, path, title)


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
        _, ax = pyplot().subplots(figsize=(5, 3.5))
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
    try:
        import imageio.v2 as imageio
    except ImportError as err:
        raise ImportError(f"write_gif needs imageio: {VIZ_INSTALL_HINT}.") from err

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_path(path, lambda tmp: imageio.mimsave(tmp, frames, duration=1.0 / fps, loop=0))
    return path


def video_suffix() -> str:
    """``".mp4"`` when imageio can write MP4 here (the ``imageio-ffmpeg`` codec is installed), else ``".gif"``.

    Examples:
        >>> video_suffix() in (".mp4", ".gif")
        True
    """
    from importlib.util import find_spec

    return ".mp4" if find_spec("imageio") is not None and find_spec("imageio_ffmpeg") is not None else ".gif"


def write_video(frames: list[np.ndarray], path: str | Path, fps: int = 5) -> Path:
    """Write RGB frames ``(H, W, 3)`` uint8 as an MP4 where a codec is present, as a GIF otherwise.

    Args:
        frames: the frames, all of one size (for MP4, sides that are multiples of 16
            pixels are written as they are; others are padded by the codec).
        path: the output path; its suffix is replaced by :func:`video_suffix`'s.
        fps: frames per second.

    Returns:
        the path written (``.mp4`` or ``.gif``).

    Examples:
        >>> import tempfile, os
        >>> out = write_video([np.zeros((16, 16, 3), np.uint8)] * 2, os.path.join(tempfile.mkdtemp(), "v"))
        >>> out.exists(), out.suffix in (".mp4", ".gif")
        (True, True)
    """
    path = Path(path).with_suffix(video_suffix())
    if path.suffix == ".gif":
        return write_gif(frames, path, fps=fps)
    import imageio.v2 as imageio

    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_path(path, lambda tmp: imageio.mimsave(tmp, frames, fps=fps))
    return path


def figure_to_array(fig) -> np.ndarray:
    """Render a matplotlib figure to an RGB uint8 array."""
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()


def watch(
    policy,
    out_dir: str | Path,
    *,
    split: str = "test",
    noise: str = "paper",
    seed: int = 7,
    num_houses: int | None = None,
    index: int = 0,
    label: str = "agent",
    gif: bool = True,
) -> dict:
    """Play one greedy episode and draw what the agent does.

    Writes, in ``out_dir``:

    * ``map_<index>.png``: the top-down map with the demonstration, the path the
      agent followed and the positions of the memory frames;
    * ``pointer_<index>.png`` (policies with a pointer): the pointer over time
      against the demonstration index the agent is nearest to (privileged, for
      the plot only);
    * ``rollout_<index>.gif`` (``gif=True``): the first-person view beside the map, step by step.

    Args:
        policy: a policy (e.g. from :func:`spf_rl.load_policy`); its ``config`` gives
            the demonstration length and frame size (30 and 64 without one).
        out_dir: output directory (created).
        split: house split.
        noise: actuation-noise preset.
        seed: episode seed (the same seed plays the same episode for every policy).
        num_houses: houses of the split (``None``: its default).
        index: number in the file names.
        label: the agent's name in legends and titles.
        gif: also write the GIF.

    Returns:
        the episode's record (:func:`~spf_rl.evaluation.record_rollout`).
    """
    from envs.episode_spec import EpisodeSpec
    from envs.render import draw_top_down_map
    from envs.scenes import build_house
    from spf_rl.evaluation import EvalConfig, record_rollout
    from spf_rl.modules.memory import memory_indices

    plt = pyplot()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    episodes = EpisodeSpec(split=split, noise=noise, seed=seed, num_houses=num_houses, max_steps=50)
    config = getattr(policy, "config", None)
    indices = np.zeros(0, dtype=np.int64)
    if config is not None:
        episodes = episodes.replace(demo_length=config.demo_length, image_size=config.image_size[0])
    eval_config = EvalConfig(episodes)
    if config is not None:
        if getattr(policy, "use_memory", False):
            indices = memory_indices(config.demo_length, policy.sparsity).numpy()
    record = record_rollout(policy, eval_config)
    house = build_house(record["house_seed"])
    demo, followed = record["demo_poses"][:, :2], record["poses"][:, :2]
    outcome = f"{'success' if record['success'] else 'failure'}, SPL {record['spl']:.2f}"

    ax = draw_top_down_map(
        house,
        paths={"demonstration": demo, label: followed},
        points={"memory frames": demo[indices]} if len(indices) else None,
        title=f"{label}: {outcome}",
    )
    write_figure(ax.figure, out / f"map_{index}.png", dpi=120)
    if "eta" in record:
        nearest = np.argmin(np.linalg.norm(followed[:-1, None] - demo[None, :-1], axis=-1), axis=1)
        ax = plot_pointer(record["eta"], nearest, indices, title=f"{label}: pointer vs position")
        ax.figure.tight_layout()
        write_figure(ax.figure, out / f"pointer_{index}.png", dpi=120)
    if gif:
        fig, (left, right) = plt.subplots(1, 2, figsize=(7, 3.5))
        view = left.imshow(record["frames"][0])
        left.set_axis_off()
        left.set_title("first-person view, step 0")
        draw_top_down_map(house, paths={"demonstration": demo}, ax=right)
        (trail,) = right.plot(followed[:1, 0], followed[:1, 1], "-", linewidth=2, label=label)
        right.legend(loc="upper right", fontsize=7)
        fig.tight_layout()
        frames = []
        for step in range(len(record["frames"])):
            view.set_data(record["frames"][step])
            left.set_title(f"first-person view, step {step}")
            trail.set_data(followed[: step + 2, 0], followed[: step + 2, 1])
            frames.append(figure_to_array(fig))
        plt.close(fig)
        write_gif(frames, out / f"rollout_{index}.gif")
    return record


def plot_route_styles(house, routes: dict[str, list], path: str | Path, title: str = "route styles") -> Path:
    """One top-down map per route style, with that style's sample routes on it, to a PNG.

    Args:
        house: the :class:`~envs.scenes.House` the routes were drawn in.
        routes: ``{style: [Demonstration, ...]}`` (:mod:`envs.route_styles`).
        path: output PNG.
        title: the figure's title.
    """
    from envs.render import draw_top_down_map

    plt = pyplot()
    fig, axes = plt.subplots(1, len(routes), figsize=(4.5 * len(routes), 4.8), squeeze=False)
    for ax, (style, demos) in zip(axes[0], routes.items()):
        paths = {f"route {i}: {demo.length} steps": demo.poses[:, :2] for i, demo in enumerate(demos, 1)}
        draw_top_down_map(house, paths=paths, ax=ax, title=style)
    return save_figure(fig, path, title)


def plot_conditions(rows: dict[str, list[tuple[str, np.ndarray]]], path: str | Path, title: str = "repeat conditions") -> Path:
    """A grid of frames, one row per condition: the teaching frame beside the repeat's frames at the
    same pose (:mod:`envs.conditions`), to a PNG.

    Args:
        rows: ``{row label: [(column label, (H, W, 3) uint8 frame), ...]}``.
        path: output PNG.
        title: the figure's title.
    """
    plt = pyplot()
    columns = max(len(frames) for frames in rows.values())
    fig, axes = plt.subplots(len(rows), columns, figsize=(2.2 * columns, 2.3 * len(rows)), squeeze=False)
    for axis_row, (label, frames) in zip(axes, rows.items()):
        for ax in axis_row:
            ax.axis("off")
        for ax, (column, frame) in zip(axis_row, frames):
            ax.imshow(frame)
            ax.set_title(f"{label}: {column}" if column != "taught" else f"{label}: taught", fontsize=8)
    return save_figure(fig, path, title)


def plot_layout_change(taught, repeat, route, path: str | Path, title: str = "furniture changed") -> Path:
    """Two top-down maps, the house the route was taught in and the repeat's, with the route, to a PNG.

    Args:
        taught: the teaching :class:`~envs.scenes.House`.
        repeat: the repeat's house (:func:`envs.conditions.draw_repeat`).
        route: ``(T, 2)`` positions of the demonstrated route.
        path: output PNG.
        title: the figure's title.
    """
    from envs.render import draw_top_down_map

    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(9, 4.8))
    draw_top_down_map(taught, paths={"route": route}, ax=axes[0], title="taught")
    draw_top_down_map(repeat, paths={"route": route}, ax=axes[1], title="repeated")
    return save_figure(fig, path, title)
