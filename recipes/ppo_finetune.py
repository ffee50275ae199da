"""PPO fine-tuning of a behaviour-cloned SPF policy on the env's dense reward (issue #5).

Loads a BC checkpoint, scores it on ``val`` and ``test``, fine-tunes it with
recurrent PPO (TorchRL's ``ClipPPOLoss`` + ``GAE``, a value head on the policy's
GRU features, episodes collected by a TorchRL collector, local or on Ray),
validates every few iterations, keeps the best checkpoint by val success and
evaluates it on ``test``. Writes ``results.json`` (start vs after, with 95% CIs),
``ppo.png``, ``best.pt`` (readable by ``recipes/evaluate.py``) and ``last.pt``
to the output directory. Run it again with the same config to resume.

Usage::

    python recipes/ppo_finetune.py                          # from the shipped checkpoint spf-s0.8, ~15 min on 2 CPU cores
    python recipes/ppo_finetune.py --quick                  # the whole pipeline in a few minutes
    python recipes/ppo_finetune.py checkpoint=runs/bc/spf-s0.8-seed0/best.pt total_frames=25000
    python recipes/ppo_finetune.py kl_coef=0.05 bc_coef=0.1 noise=locobot
    python recipes/ppo_finetune.py collector.backend=ray collector.num_collectors=2 collector.num_agents=8 device=cpu
    python recipes/ppo_finetune.py device=cuda amp=true     # GPU learner, bf16 mixed precision (default device=auto)
"""
from __future__ import annotations

import argparse
import json
import logging

from spf_rl.cli import ArgumentParser
from spf_rl.config import config_or_exit, load_config

#: Shorthands of this recipe, expanded before the generic ones of ``spf_rl.config``.
PPO_SHORTHANDS = {"noise": ["env.noise", "val.noise", "test.noise"], "epochs": ["ppo_epochs"]}


def expand_shorthands(overrides: list[str]) -> list[str]:
    """Expand ``noise=`` (training env, val and test) and ``epochs=`` (PPO epochs).

    Examples:
        >>> expand_shorthands(["noise=none", "lr=0.001"])
        ['env.noise=none', 'val.noise=none', 'test.noise=none', 'lr=0.001']
    """
    expanded = []
    for item in overrides:
        key, sep, value = item.partition("=")
        targets = PPO_SHORTHANDS.get(key) if sep else None
        expanded.extend(f"{target}={value}" for target in targets) if targets else expanded.append(item)
    return expanded


def check_start(config) -> None:
    """Refuse, before any work, a starting checkpoint that is missing, unreadable, not a checkpoint or an
    unknown shipped name, or whose sizes differ from ``env``'s (``ValueError``, one line naming the key)."""
    from spf_rl.hub import checkpoint_argument
    from spf_rl.train.ppo_config import checked_env_config

    start = checkpoint_argument(config.checkpoint, "invalid configuration: checkpoint").payload["model_config"]
    try:
        checked_env_config(config, start)
    except ValueError as err:
        raise ValueError(f"invalid configuration: {err}") from None


def main(argv: list[str] | None = None) -> dict:
    parser = ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="small preset that runs in a few minutes")
    parser.add_argument("overrides", nargs="*", help="key=value config overrides")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    import envs  # noqa: F401  (selects the headless GL back-end first)
    from spf_rl.train.ppo import train_ppo
    from spf_rl.train.ppo_config import PPOConfig

    config = config_or_exit(parser, load_config, PPOConfig, "ppo", expand_shorthands(args.overrides), preset="ppo_quick" if args.quick else None)
    config_or_exit(parser, check_start, config)
    results = train_ppo(config)

    def scores(split_summary: dict) -> dict:
        return {
            "success": round(split_summary["success"], 3),
            "success_ci95": [round(x, 3) for x in split_summary["success_ci"]],
            "spl": round(split_summary["spl"], 3),
            "spl_ci95": [round(x, 3) for x in split_summary["spl_ci"]],
            "episodes": split_summary["episodes"],
        }

    summary = {
        "model": results["model"],
        "start_checkpoint": results["start_checkpoint"],
        "start_test": scores(results["start"]["test"]),
        "after_test": scores(results["after"]["test"]),
        "best_iteration": results["best_iteration"],
        "iterations": results["iterations"],
        "frames": results["frames"],
        "output_dir": config.output_dir,
    }
    print(json.dumps(summary, indent=2))
    return results


if __name__ == "__main__":
    main()
