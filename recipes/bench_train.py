"""Training throughput benchmark: samples/s, time waiting on data, memory bytes per demonstration.

Writes ``benchmarks/results/train.json``. A "sample" is one labelled step of a
follow episode (what the cross-entropy is computed on); images/s also counts the
memory frames encoded once per episode. "Waiting on data" is the time spent
drawing a batch from the replay buffer and laying it out for the policy,
against the forward/backward/update time.

Usage::

    python recipes/bench_train.py            # about 2-3 minutes on 2 CPU cores
    python recipes/bench_train.py --quick
"""
from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--data-dir", default="data/bench-train")
    parser.add_argument("--out", default="benchmarks/results/train.json")
    args = parser.parse_args(argv)

    import envs  # noqa: F401
    import torch

    from spf_rl.data import DatasetConfig, EpisodeDataset
    from spf_rl.train.bc import bc_loss, episodes_to_sequence, model_memory_bytes
    from spf_rl.train.models import ModelConfig, build_policy, spf_config

    data_config = DatasetConfig(num_episodes=64, num_houses=4, chunk_size=16, seed=123)
    dataset = EpisodeDataset.build(args.data_dir, data_config, num_workers=2, progress=True)
    batch_size, steps = 16, (3 if args.quick else 8)
    results = {"batch_size_episodes": batch_size, "timed_steps": steps, "models": {}}
    for name, sparsity in (("spf", 0.8), ("spf", 0.4), ("rpf", 1.0), ("action_only", 0.0)):
        torch.manual_seed(0)
        policy = build_policy(name, spf_config(ModelConfig(name=name, sparsity=max(sparsity, 0.1)), 30, 64))
        optimizer = torch.optim.Adam(policy.parameters(), lr=1e-3)
        buffer = dataset.replay_buffer(batch_size, seed=0)
        data_seconds, compute_seconds, samples, images = [], [], 0, 0
        for step in range(steps + 1):
            start = time.perf_counter()
            batch = buffer.sample()
            episodes_to_sequence(batch)  # the layout cost, counted as data time
            loaded = time.perf_counter()
            loss, _ = bc_loss(policy, batch)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            done = time.perf_counter()
            if step == 0:
                continue  # warm-up
            data_seconds.append(loaded - start)
            compute_seconds.append(done - loaded)
            valid = int(batch["steps", "mask"].sum())
            samples += valid
            images += valid + batch.shape[0] * policy.memory_length
        total = sum(data_seconds) + sum(compute_seconds)
        key = f"{name}" + (f"_{sparsity}" if name == "spf" else "")
        results["models"][key] = {
            "samples_per_s": samples / total,
            "images_per_s": images / total,
            "episodes_per_s": batch_size * steps / total,
            "data_wait_share": sum(data_seconds) / total,
            "median_step_s": float(np.median(np.add(data_seconds, compute_seconds))),
            "parameters": sum(p.numel() for p in policy.parameters()),
        }
        print(key, json.dumps(results["models"][key]))
    results["memory_bytes_per_demo"] = {
        str(s): model_memory_bytes("spf", 30, s, 64) for s in (0.2, 0.4, 0.6, 0.8, 1.0)
    }
    results["memory_bytes_per_demo"]["action_only"] = model_memory_bytes("action_only", 30, 0.0, 64)
    results["machine"] = {
        "cpus": __import__("os").cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "torch": torch.__version__,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2))
    print(f"wrote {out}")
    return results


if __name__ == "__main__":
    main()
