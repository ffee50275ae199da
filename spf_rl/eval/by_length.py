"""Success against route length: checkpoints evaluated on demonstrations of several lengths
(``recipes/success_by_length.py`` is the command line).

Each checkpoint's weights run at every length (:func:`spf_rl.modules.views.policy_for_length`:
SPF's weights do not depend on the demonstration length); episodes of ``n`` steps are
sampled in houses large enough for them and end after ``ceil(5/3 n)`` steps. Every
checkpoint plays the same episodes at a length (same seed).

* :func:`label_of`: how the JSON and the figure name a checkpoint;
* :func:`load_policies`: the checkpoints' policies by label;
* :func:`success_by_length`: every policy at every length, then :data:`JSON_NAME` (the set-up and,
  per checkpoint, one row per length: success, SPL, 95% CIs, episodes, ``max_steps``, the houses'
  grid) and :data:`FIGURE_NAME` (success and SPL against the length, one line per checkpoint).
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

from envs.atomic_io import atomic_write_json

logger = logging.getLogger(__name__)

#: File names written in the output directory.
JSON_NAME, FIGURE_NAME = "success_by_length.json", "success_by_length.png"
#: The recipe named in the JSON.
RECIPE = "recipes/success_by_length.py"


def label_of(path_or_name: str) -> str:
    """How the JSON and the figure name a checkpoint: a shipped name, or ``<run dir>/<file>``.

    Examples:
        >>> label_of("spf-s0.8"), label_of("runs/bc_lengths/spf-s0.8-seed0/best.pt")
        ('spf-s0.8', 'spf-s0.8-seed0/best')
    """
    path = Path(path_or_name)
    if path.suffix != ".pt":
        return path_or_name
    return f"{path.parent.name}/{path.stem}" if path.parent.name else path.stem


def load_policies(checkpoints: Sequence[str], device: str = "cpu") -> dict:
    """``{label_of(checkpoint): policy}`` of shipped names or ``.pt`` paths, loaded on ``device``.

    Raises:
        ValueError, FileNotFoundError, CheckpointError: a checkpoint or device that cannot be loaded
            (:func:`spf_rl.hub.load_policy`).
    """
    from spf_rl.hub import load_policy

    return {label_of(name): load_policy(name, device=device).policy for name in checkpoints}


def success_by_length(policies: dict, lengths: Sequence[int], config, out: Path, progress: bool = True) -> dict:
    """Evaluate every policy at every length and write :data:`JSON_NAME` and :data:`FIGURE_NAME` to ``out``.

    Args:
        policies: ``{label: policy}`` (:func:`load_policies`).
        lengths: demonstration lengths, steps.
        config: the :class:`~spf_rl.evaluation.EvalConfig` of every length (split, episodes,
            noise, seed, agents, houses, rendering; the length's own ``demo_length`` and ``max_steps``
            are set per length).
        out: output directory (made).
        progress: show progress bars.

    Returns:
        The JSON content: ``recipe``, ``setup``, ``render`` and ``results`` (``{label: one row per length}``).
    """
    from spf_rl.evaluation import evaluate_lengths
    from spf_rl.viz import plot_if_available, plot_success_by_length

    lengths = list(lengths)
    results = {}
    for label, policy in policies.items():
        logger.info("%s at lengths %s", label, lengths)
        results[label], _ = evaluate_lengths(policy, lengths, config, progress=progress)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    e = config.episodes
    setup = {"lengths": lengths, "episodes": config.num_episodes, "split": e.split, "num_houses": e.num_houses,
             "noise": e.noise, "seed": e.seed}
    content = {"recipe": RECIPE, "setup": setup, "render": config.render, "results": results}
    atomic_write_json(out / JSON_NAME, content)
    plot_if_available(plot_success_by_length, results, out / FIGURE_NAME, title=f"success against route length ({config.episodes.noise} noise)")
    return content
