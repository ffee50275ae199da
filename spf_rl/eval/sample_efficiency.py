"""A study of sample efficiency: how much the main job learns per gradient step and per episode under
each lever, on the main job's own budget.

The main job (``recipes/bc.py`` with its defaults) trains SPF at sparsity 0.8 for 1,500 gradient steps
on 2,000 expert episodes, validates every 3 epochs on 300 episodes and tests the best on 500. A
:class:`Lever` is a set of overrides of that config; every lever is trained with the same seeds in
``runs/sample_efficiency/<lever>-seed<S>`` and compared with ``baseline`` (no override) on the same 500
test episodes, paired (:func:`spf_rl.eval.paired.compare`: houses resampled, then episodes, pooled over
the seeds). ``recipes/sample_efficiency.py`` is the command line; it trains what is missing and writes
``results/sample_efficiency.json`` and a figure of validation success against gradient steps and
against training time.
"""
from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from envs.atomic_io import atomic_write_json
from spf_rl.eval.paired import compare
from spf_rl.records_cache import TEST_EPISODES_FILE

logger = logging.getLogger(__name__)

#: Where the study's runs live: ``<RUNS_DIR>/<lever>-seed<S>``.
RUNS_DIR = Path("runs/sample_efficiency")
DEFAULT_OUT = Path("results/sample_efficiency.json")
DEFAULT_SEEDS = (0, 1, 2)
#: Planner routes that carry the route expert's pointer labels (``route_step``), tested on the main job's episodes.
POINTER_LABELS = ("data.route_style=planner", "val.route_style=null", "test.route_style=null")


@dataclass(frozen=True)
class Lever:
    """One change to the main job's recipe: its name, its config overrides and where it comes from."""

    name: str
    overrides: tuple[str, ...]
    source: str


#: The levers studied, ``baseline`` first (the main job as it is).
LEVERS = (
    Lever("baseline", (), "the main job as it was: the paper's SPF recipe on 1,500 gradient steps"),
    Lever("rpf_rule", ("model.pointer_update=rpf",),
          "RPF's pointer rule, eta + 1 + tanh(b) (Kumar et al., Visual Memory for Robust Path Following, NeurIPS "
          "2018): the pointer moves forward by default and cannot run backwards"),
    Lever("pointer_loss", (*POINTER_LABELS, "optim.pointer_coef=0.1"),
          "progress supervision: the pointer held to the agent's place on the route, as the progress monitor of "
          "Ma et al. (Self-Monitoring Navigation Agent via Auxiliary Progress Estimation, ICLR 2019)"),
    Lever("rpf_rule+pointer_loss", ("model.pointer_update=rpf", *POINTER_LABELS, "optim.pointer_coef=0.1"),
          "the two together"),
    Lever("lr3e-3", ("optim.lr=0.003",),
          "the schedule: a 3x larger peak learning rate under the same cosine decay (Smith and Topin, "
          "Super-Convergence, 2018)"),
    Lever("pointer_loss1", (*POINTER_LABELS, "optim.pointer_coef=1.0"),
          "the progress supervision weighted 10x (pointer_coef 1.0): the pointer's error counts as much as the actions'"),
    Lever("pointer_loss+lr3e-3", (*POINTER_LABELS, "optim.pointer_coef=0.1", "optim.lr=0.003"),
          "the progress supervision and the larger learning rate together"),
)
LEVER_BY_NAME = {lever.name: lever for lever in LEVERS}


def run_dir(lever: str, seed: int) -> Path:
    """A lever's run directory for one seed."""
    return RUNS_DIR / f"{lever}-seed{seed}"


def lever_config(lever: Lever, seed: int):
    """The main job's config with the lever's overrides, the seed and the run directory."""
    from spf_rl.config import load_config
    from spf_rl.train.bc import BCConfig

    return load_config(BCConfig, "bc", [*lever.overrides, f"seed={seed}", f"output_dir={run_dir(lever.name, seed)}",
                                        "progress=false"])


def train_missing(levers: Sequence[Lever], seeds: Sequence[int]) -> None:
    """Train (or resume) every lever x seed without a finished run, seed by seed."""
    from spf_rl.train.bc import train_bc

    for seed in seeds:
        for lever in levers:
            if not (run_dir(lever.name, seed) / "results.json").exists():
                logger.info("training %s seed %d in %s", lever.name, seed, run_dir(lever.name, seed))
                train_bc(lever_config(lever, seed))


def curve(history: list[dict]) -> dict:
    """A run's validation curve: gradient steps, cumulative training seconds and success at each validated epoch."""
    seconds = np.cumsum([record["train_seconds"] for record in history])
    points = [(r["step"], float(s), r["val_success"]) for r, s in zip(history, seconds) if r["val_success"] is not None]
    return {"steps": [p[0] for p in points], "train_seconds": [p[1] for p in points], "val_success": [p[2] for p in points]}


def summarize_lever(lever: Lever, seeds: Sequence[int], num_resamples: int) -> dict | None:
    """One lever's per-seed and pooled test success, worst seed, wall time, curves, and its paired
    difference from ``baseline`` on the same episodes; ``None`` where a seed has no finished run."""
    runs = {seed: run_dir(lever.name, seed) for seed in seeds}
    if not all((path / "results.json").exists() for path in runs.values()):
        return None
    results = {seed: json.loads((path / "results.json").read_text()) for seed, path in runs.items()}
    per_seed = {str(seed): results[seed]["test"]["success"] for seed in seeds}
    entry = {
        "overrides": list(lever.overrides),
        "source": lever.source,
        "test_success_per_seed": per_seed,
        "test_success": float(np.mean(list(per_seed.values()))),
        "worst_seed": float(min(per_seed.values())),
        "wall_seconds_mean": float(np.mean([r["wall_seconds_this_run"] for r in results.values()])),
        "train_seconds_mean": float(np.mean([sum(h["train_seconds"] for h in r["history"]) for r in results.values()])),
        "pointer_restarts": {str(seed): r.get("pointer_restarts", []) for seed, r in results.items()},
        "curves": {str(seed): curve(r["history"]) for seed, r in results.items()},
        "machines": sorted({r["machine_this_run"].get("cpu_model", "?") for r in results.values()}),
    }
    baseline = [run_dir("baseline", seed) / TEST_EPISODES_FILE for seed in seeds]
    if lever.name != "baseline" and all(path.exists() for path in baseline):
        paired = compare([path / TEST_EPISODES_FILE for path in runs.values()], baseline, num_resamples, 0)
        entry["vs_baseline"] = paired["metrics"]["success"]
    return entry


def study(levers: Sequence[Lever], seeds: Sequence[int], num_resamples: int) -> dict:
    """The study's JSON content: every lever with finished runs for every seed (others listed as missing)."""
    out = {"recipe": "python recipes/sample_efficiency.py", "seeds": list(seeds), "runs_dir": str(RUNS_DIR),
           "budget": "the main job's: 12 epochs of 2,000 episodes at 16 a batch (1,500 gradient steps)",
           "statistics": "test success on the main job's 500 test episodes; vs_baseline: paired bootstrap of the "
                         "difference on the same episodes, houses then episodes resampled, pooled over seeds",
           "levers": {}, "missing": []}
    for lever in levers:
        entry = summarize_lever(lever, seeds, num_resamples)
        if entry is None:
            out["missing"].append(lever.name)
        else:
            out["levers"][lever.name] = entry
    return out


def plot(content: dict, path: Path) -> Path | None:
    """Validation success (mean over seeds) against gradient steps and against training seconds, per lever."""
    from spf_rl.viz import pyplot, write_figure

    if not content["levers"]:
        return None
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), sharey=True)
    for name, entry in content["levers"].items():
        curves = list(entry["curves"].values())
        steps = curves[0]["steps"]
        success = np.mean([c["val_success"] for c in curves], axis=0)
        seconds = np.mean([c["train_seconds"] for c in curves], axis=0)
        label = f"{name} (test {entry['test_success']:.3f})"
        style = {"color": "black", "linestyle": "--"} if name == "baseline" else {"linestyle": "-"}
        axes[0].plot(steps, success, marker="o", label=label, **style)
        axes[1].plot(seconds, success, marker="o", label=label, **style)
    axes[0].set_xlabel("gradient steps")
    axes[1].set_xlabel("training seconds (this machine)")
    axes[0].set_ylabel(f"validation success (mean of {len(content['seeds'])} seeds)")
    axes[0].legend(fontsize=7)
    fig.suptitle("Sample efficiency of the main job's levers")
    fig.tight_layout()
    return write_figure(fig, path, dpi=120)


def run_study(levers: Sequence[Lever], seeds: Sequence[int], out: Path, num_resamples: int, train: bool = True) -> dict:
    """Train what is missing (with ``train``), then write the study's JSON and figure to ``out`` (``.png`` beside it)."""
    if train:
        train_missing(levers, seeds)
    content = study(levers, seeds, num_resamples)
    figure = plot(content, out.with_suffix(".png"))
    content["figure"] = None if figure is None else str(figure)
    atomic_write_json(out, content, indent=1)
    return content


__all__ = ["LEVERS", "LEVER_BY_NAME", "Lever", "curve", "lever_config", "run_study", "study"]
