"""Export a policy for a robot: ONNX graphs to teach a route (once) and to step along it (every step),
with a manifest, for the torch-free runtime (``runtime/``, ``pip install ./runtime``: numpy and ONNX
Runtime only). See docs/deploy.md.

Usage::

    python recipes/export.py spf-s0.8 --out exports/spf-s0.8
    python recipes/export.py routes-spf --out exports/routes-spf --sparsity 0.4 --weights int8
    python recipes/export.py runs/bc/spf-s0.8-seed0/best.pt --out exports/mine
"""
from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from spf_rl.cli import ArgumentParser


def main(argv: list[str] | None = None) -> dict:
    from spf_rl.export import WEIGHT_PRECISIONS
    from spf_rl.hub import checkpoint_argument

    parser = ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", help="a shipped name (spf_rl.list_checkpoints()) or a checkpoint file")
    parser.add_argument("--out", type=Path, required=True, help="the export directory (made)")
    parser.add_argument("--weights", choices=WEIGHT_PRECISIONS, default="fp32", help="weight precision (default: %(default)s)")
    parser.add_argument("--sparsity", type=float, default=None,
                        help="a random-sparsity model's default sparsity, in (0, 1] (default: its config's)")
    args = parser.parse_args(argv)
    if args.sparsity is not None and not 0.0 < args.sparsity <= 1.0:
        parser.error(f"argument --sparsity: must be in (0, 1], got {args.sparsity}")
    try:
        checked = checkpoint_argument(args.checkpoint, "argument checkpoint")
    except ValueError as err:
        parser.error(str(err))
    if args.sparsity is not None:
        if checked.payload["model_type"] != "spf_random":
            parser.error(f"argument --sparsity: only a random-sparsity model (spf_random) reads its memory at another "
                         f"sparsity; {args.checkpoint} is {checked.payload['model_type']!r}")
        checked.policy.set_sparsity(args.sparsity)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    from spf_rl.export import export_policy

    manifest = export_policy(checked.policy, args.out, checked.payload["model_type"], args.weights,
                             source={"checkpoint": str(args.checkpoint)})
    print(json.dumps({"out": str(args.out), "model_type": manifest["model_type"], "weights": manifest["weights"],
                      "files": manifest["files"]}, indent=2))
    return manifest


if __name__ == "__main__":
    main()
