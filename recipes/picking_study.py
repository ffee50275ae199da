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
import json
import logging
from pathlib import Path

from envs.atomic_io import atomic_write_json
from spf_rl.cli import ArgumentParser
from spf_rl.device import DEFAULT_DEVICE, DEVICE_CHOICES
from spf_rl.eval.picking import epoch_files, plot_study, summarize_study, validation_history

logger = logging.getLogger("picking_study")


def main(argv: list[str] | None = None) -> dict:
    parser = ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
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
    from envs.episode_spec import from_flat
    from spf_rl.checkpoint import CheckpointError
    from spf_rl.evaluation import EvalConfig, config_dict, evaluate_policy
    from spf_rl.hub import checkpoint_argument, policy_from_checkpoint

    config = json.loads((run / "config.json").read_text())
    data, test_fields = config["data"], dict(config["test"])
    if args.episodes is not None:
        test_fields["num_episodes"] = args.episodes
    sizes = {key: data[key] for key in ("demo_length", "max_steps", "image_size")}  # the policy's episodes
    test = from_flat(EvalConfig, {**test_fields, **sizes})
    try:  # the run's checkpoints load, before any episode is played or file written
        val = validation_history(run)
        for epoch in set(files) & set(val):
            checkpoint_argument(files[epoch], f"run {run}")
    except CheckpointError as err:  # last.pt unreadable
        parser.error(f"run {run}: {err}")
    except KeyError:
        parser.error(f"run {run}: its last.pt holds no validation history: give a BC run directory")
    except ValueError as err:  # an epoch's checkpoint, named by checkpoint_argument
        parser.error(str(err))
    if len(set(files) & set(val)) < 3:
        parser.error(f"run {run} validated {len(set(files) & set(val))} of its kept epochs; train it with val_every=1")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{run.parent.name}-{run.name}.json"
    study = json.loads(path.read_text()) if path.exists() else {}
    if study.get("test") != config_dict(test):
        study = {"run": str(run), "test": config_dict(test), "epochs": []}
    done = {row["epoch"] for row in study["epochs"]}
    for epoch, weights in files.items():
        if epoch in done or epoch not in val:
            continue
        policy, _ = policy_from_checkpoint(weights, device=args.device)
        summary, _ = evaluate_policy(policy, test, progress=not args.quiet)
        study["epochs"].append({"epoch": epoch, "val_success": val[epoch], "test_success": summary["success"], "test_spl": summary["spl"]})
        study["epochs"].sort(key=lambda row: row["epoch"])
        atomic_write_json(path, study)
        logger.info("epoch %d: validation %.3f, test %.3f", epoch, val[epoch], summary["success"])
    rows = study["epochs"]
    study["val_episodes"] = config["val"]["num_episodes"]
    study["test_episodes"] = test.num_episodes
    study["summary"] = summarize_study([r["epoch"] for r in rows], [r["val_success"] for r in rows], [r["test_success"] for r in rows])
    atomic_write_json(path, study)
    from spf_rl.viz import plot_if_available

    plot_if_available(plot_study, path.with_suffix(".png"), study)
    logger.info("%s", json.dumps(study["summary"], indent=2))
    return study


if __name__ == "__main__":
    main()
