"""Figures of what an agent does: map with routes and memory frames, pointer plot, rollout GIF.

For a checkpoint (or ``open_loop``), plays a few test episodes and writes per episode:

* ``map_<i>.png``: the top-down map with the demonstration, the followed path and
  the positions of the memory frames;
* ``pointer_<i>.png``: the pointer eta over time against the demo index the agent
  is actually nearest to (privileged information, for the plot only);
* ``rollout_<i>.gif``: the first-person view beside the map, step by step.

Usage::

    python recipes/visualize.py runs/bc/spf-s0.8-seed0/best.pt --episodes 3 --out figures/spf08
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", help="a checkpoint file or 'open_loop'")
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--split", default="test")
    parser.add_argument("--noise", default="paper")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--out", default="figures/rollouts")
    parser.add_argument("--no-gif", action="store_true")
    args = parser.parse_args(argv)
    if args.episodes <= 0:
        parser.error(f"--episodes must be > 0, got {args.episodes}")

    import envs  # noqa: F401
    import matplotlib.pyplot as plt

    from envs.render import draw_top_down_map
    from envs.scenes import build_house
    from spf_rl.checkpoint import load_checkpoint
    from spf_rl.modules.policy import OpenLoopPolicy
    from spf_rl.train.evaluation import EvalConfig, record_rollout
    from spf_rl.train.models import build_policy
    from spf_rl.viz import figure_to_array, plot_pointer, write_gif

    if args.checkpoint == "open_loop":
        policy, label, memory_indices, image_size, demo_length = OpenLoopPolicy(), "open loop", np.zeros(0, int), 64, 30
    else:
        payload = load_checkpoint(args.checkpoint)
        config = payload["model_config"]
        policy = build_policy(payload["model_type"], config)
        policy.load_state_dict(payload["model"])
        label = f"{payload['model_type']} (sparsity {config.effective_sparsity:g})"
        memory_indices, image_size, demo_length = config.memory_indices.numpy(), config.image_size[0], config.demo_length
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for episode in range(args.episodes):
        record = record_rollout(
            policy,
            EvalConfig(split=args.split, noise=args.noise, seed=args.seed + episode, image_size=image_size, demo_length=demo_length),
        )
        house = build_house(record["house_seed"])
        demo, followed = record["demo_poses"], record["poses"]
        outcome = f"{'success' if record['success'] else 'failure'}, SPL {record['spl']:.2f}"
        ax = draw_top_down_map(
            house,
            paths={"demonstration": demo[:, :2], f"{label}": followed[:, :2]},
            points={"memory frames": demo[memory_indices, :2]} if len(memory_indices) else None,
            title=f"{label}: {outcome}",
        )
        ax.figure.savefig(out / f"map_{episode}.png", dpi=120)
        plt.close(ax.figure)
        if "eta" in record:
            nearest = np.argmin(
                np.linalg.norm(followed[:-1, None, :2] - demo[None, :-1, :2], axis=-1), axis=1
            )
            ax = plot_pointer(record["eta"], nearest, memory_indices, title=f"{label}: pointer vs position")
            ax.figure.tight_layout()
            ax.figure.savefig(out / f"pointer_{episode}.png", dpi=120)
            plt.close(ax.figure)
        if not args.no_gif:
            frames = []
            for step in range(len(record["frames"])):
                fig, (left, right) = plt.subplots(1, 2, figsize=(7, 3.5))
                left.imshow(record["frames"][step])
                left.set_axis_off()
                left.set_title(f"first-person view, step {step}")
                draw_top_down_map(house, paths={"demo": demo[:, :2], "agent": followed[: step + 2, :2]}, ax=right)
                fig.tight_layout()
                frames.append(figure_to_array(fig))
                plt.close(fig)
            write_gif(frames, out / f"rollout_{episode}.gif")
        print(f"episode {episode}: {outcome} -> {out}")


if __name__ == "__main__":
    main()
