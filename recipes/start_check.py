"""Give a trained route model a start check: replay the demonstrated actions for an episode whose first
frame does not match the memory's first frame (another route's frames; ``spf_rl.modules.replay_gate``).

It measures, on the validation houses, the cosine of the encoder's features of the repeat's first frame
and the demonstration's first frame: with the route's own memory, in the teaching world and under each
condition (light, paint, furniture, camera, sensor at strengths 0.5 and 1), and with a mismatched memory.
It picks the threshold that catches the most mismatched memories while it flags at most 5% of the route's
own under any condition (``--max-false-alarm``; ``spf_rl.eval.start_check``) and writes the checkpoint
again with ``start_check`` set (the weights unchanged) and the measurement's JSON.

Usage::

    python recipes/start_check.py runs/dagger_routes_robust_gate/spf_random-seed0/best.pt \\
        --out checkpoints/routes/mine-checked.pt --results results/start_check_mine.json
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
from pathlib import Path

from spf_rl.cli import ArgumentParser


def main(argv: list[str] | None = None) -> dict:
    from envs.scenes import SPLIT_SEED_OFFSETS

    splits = tuple(SPLIT_SEED_OFFSETS)
    from spf_rl.hub import checkpoint_argument

    parser = ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", help="a shipped name (spf_rl.list_checkpoints()) or a checkpoint file")
    parser.add_argument("--out", type=Path, required=True, help="the checkpoint written, with start_check set")
    parser.add_argument("--results", type=Path, required=True, help="the measurement's JSON")
    parser.add_argument("--split", default="val", help=f"the houses measured, one of {splits} (default: val)")
    parser.add_argument("--episodes", type=int, default=128, help="episodes per condition and strength (default: 128)")
    parser.add_argument("--seed", type=int, default=0, help="the episodes' env seed (default: 0)")
    parser.add_argument("--max-false-alarm", type=float, default=None,
                        help="the share of the route's own memories it may flag under any one condition, in [0, 1) (default: 0.05)")
    args = parser.parse_args(argv)
    if args.split not in splits:
        parser.error(f"argument --split: must be one of {splits}, got {args.split!r}")
    if args.episodes < 1:
        parser.error(f"argument --episodes: must be >= 1, got {args.episodes}")
    if args.max_false_alarm is not None and not 0.0 <= args.max_false_alarm < 1.0:
        parser.error(f"argument --max-false-alarm: must be in [0, 1), got {args.max_false_alarm}")
    if args.out.suffix != ".pt":
        parser.error(f"argument --out: must be a .pt file, got {str(args.out)!r}")
    try:
        checked = checkpoint_argument(args.checkpoint, "argument checkpoint")
    except ValueError as err:
        parser.error(str(err))
    if args.out.resolve() == checked.path.resolve():
        parser.error("argument --out: must differ from the checkpoint (it is written anew, with start_check set)")
    config = checked.policy.config
    if config.memory_mode == "none" or config.architecture != "spf":
        parser.error(f"argument checkpoint: a start check needs a model with visual memory and SPF's architecture; "
                     f"{args.checkpoint} has memory_mode={config.memory_mode!r}, architecture={config.architecture!r}")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    from envs.atomic_io import atomic_write_json
    from spf_rl.checkpoint import file_sha256, save_checkpoint
    from spf_rl.eval.start_check import MAX_FALSE_ALARM, measure

    max_false_alarm = MAX_FALSE_ALARM if args.max_false_alarm is None else args.max_false_alarm
    result = measure(checked.policy, args.split, args.episodes, args.seed, max_false_alarm=max_false_alarm)
    threshold = round(result["threshold"], 4)
    payload = {key: value for key, value in checked.payload.items() if key not in ("format_version", "model_type", "model_config")}
    save_checkpoint(args.out, checked.payload["model_type"], dataclasses.replace(config, start_check=threshold), payload)
    out = {"recipe": "recipes/start_check.py", "checkpoint": str(args.checkpoint), "checkpoint_sha256": file_sha256(checked.path),
           "out": str(args.out), "start_check": threshold, **result}
    atomic_write_json(args.results, out)
    print(json.dumps({key: out[key] for key in ("out", "start_check", "mismatch_caught", "worst_false_alarm")}, indent=2))
    return out


if __name__ == "__main__":
    main()
