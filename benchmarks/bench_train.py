"""Training throughput benchmark: samples/s, time waiting on data, memory bytes per demonstration.

A "sample" is one labelled step of a follow episode (what the cross-entropy is
computed on); images/s also counts the memory frames encoded once per episode.
"Waiting on data" is the time spent drawing a batch from the replay buffer, moving
it to the device and laying it out for the policy, against the
forward/backward/update time.

``--device cpu`` (or ``auto`` on a machine without CUDA) measures the CPU and writes
``benchmarks/results/train.json``. ``--device cuda`` measures, in the same run on the
same machine, the CPU (float32), then CUDA in float32 (no TF32, as training without
``amp`` runs) and with bf16 autocast (``amp``), and
writes ``benchmarks/results/train-cuda.json``: every run labelled with its device,
precision and threads, and each CUDA run's speed-up over the CPU run per model.

Usage::

    python benchmarks/bench_train.py                  # about 2-3 minutes on 2 CPU cores
    python benchmarks/bench_train.py --quick
    python benchmarks/bench_train.py --device cuda    # CPU and GPU in one run
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np

from envs.atomic_io import atomic_write_json
from envs.episode_spec import EpisodeSpec
from spf_rl.device import DEFAULT_DEVICE, DEVICE_CHOICES, exact_float32, resolve_device

#: (model name, sparsity) of the benchmarked models.
MODELS = (("spf", 0.8), ("spf", 0.4), ("rpf", 1.0), ("action_only", 0.0))


def bench_models(dataset, device, amp: bool, steps: int, batch_size: int = 16) -> dict:
    """BC gradient steps of every model in :data:`MODELS` on ``device``; throughput per model."""
    import torch

    from spf_rl.device import to_device
    from spf_rl.modules.registry import ModelConfig, build_policy, spf_config
    from spf_rl.modules.views import episodes_to_sequence
    from spf_rl.train.bc import bc_loss

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    warmup = 1 if device.type == "cpu" else 3  # CUDA: kernel selection and allocator warm-up
    models = {}
    for name, sparsity in MODELS:
        torch.manual_seed(0)
        policy = build_policy(name, spf_config(ModelConfig(name=name, sparsity=max(sparsity, 0.1)), 30, 64)).to(device)
        optimizer = torch.optim.Adam(policy.parameters(), lr=1e-3)
        buffer = dataset.replay_buffer(batch_size, seed=0)
        data_seconds, compute_seconds, samples, images = [], [], 0, 0
        for step in range(steps + warmup):
            sync()
            start = time.perf_counter()
            batch = to_device(buffer.sample(), device)
            episodes_to_sequence(batch)  # the layout cost, counted as data time
            sync()
            loaded = time.perf_counter()
            loss, _ = bc_loss(policy, batch, amp=amp)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            sync()
            done = time.perf_counter()
            if step < warmup:
                continue
            data_seconds.append(loaded - start)
            compute_seconds.append(done - loaded)
            valid = int(batch["steps", "mask"].sum())
            samples += valid
            images += valid + batch.shape[0] * policy.memory_length
        total = sum(data_seconds) + sum(compute_seconds)
        key = f"{name}" + (f"_{sparsity}" if name == "spf" else "")
        models[key] = {
            "samples_per_s": samples / total,
            "images_per_s": images / total,
            "episodes_per_s": batch_size * steps / total,
            "gradient_steps_per_s": steps / total,
            "data_wait_share": sum(data_seconds) / total,
            "median_step_s": float(np.median(np.add(data_seconds, compute_seconds))),
            "parameters": sum(p.numel() for p in policy.parameters()),
        }
        print(f"{device.type}{' bf16' if amp else ''} {key}", json.dumps(models[key]), flush=True)
    return models


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--data-dir", default="data/bench-train")
    parser.add_argument(
        "--device", default=DEFAULT_DEVICE, help=f"{DEVICE_CHOICES}; with CUDA the CPU is measured too (default: %(default)s)"
    )
    parser.add_argument("--out", default=None, help="default: benchmarks/results/train.json (CPU) or train-cuda.json")
    args = parser.parse_args(argv)
    try:
        device = resolve_device(args.device, name="--device")  # before any work: a missing GPU fails here
    except ValueError as err:
        parser.error(str(err))

    import torch

    import envs  # noqa: F401
    from spf_rl.data import DatasetConfig, EpisodeDataset
    from spf_rl.modules.views import model_memory_bytes

    data_config = DatasetConfig(EpisodeSpec(num_houses=4, max_steps=50, seed=123), num_episodes=64, chunk_size=16)
    dataset = EpisodeDataset.build(args.data_dir, data_config, num_workers=2, progress=True)
    batch_size, steps = 16, (3 if args.quick else 8)
    cpu = torch.device("cpu")
    results = {"batch_size_episodes": batch_size, "timed_steps": steps, "device": "cpu"}
    results["models"] = bench_models(dataset, cpu, False, steps, batch_size)
    if device.type == "cuda":
        results["device"] = str(device)
        results["runs"] = [{"device": "cpu", "precision": "float32", "torch_threads": torch.get_num_threads(), "models": results["models"]}]
        for amp in (False, True):  # as the training loops run: full float32 (no TF32), or bf16 autocast
            with exact_float32(device, enabled=not amp):
                models = bench_models(dataset, device, amp, steps, batch_size)
            results["runs"].append(
                {"device": str(device), "device_name": torch.cuda.get_device_name(device),
                 "precision": "bf16-autocast" if amp else "float32", "models": models}
            )
        results["speedup_over_cpu"] = {
            f"{run['device']} {run['precision']}": {
                key: run["models"][key]["samples_per_s"] / results["models"][key]["samples_per_s"] for key in run["models"]
            }
            for run in results["runs"][1:]
        }
        print("speed-up over the CPU (labelled steps/s):", json.dumps(results["speedup_over_cpu"], indent=2))
    results["memory_bytes_per_demo"] = {
        str(s): model_memory_bytes("spf", 30, s, 64) for s in (0.2, 0.4, 0.6, 0.8, 1.0)
    }
    results["memory_bytes_per_demo"]["action_only"] = model_memory_bytes("action_only", 30, 0.0, 64)
    results["machine"] = {
        "cpus": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
        "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
    }
    out = Path(args.out or ("benchmarks/results/train-cuda.json" if device.type == "cuda" else "benchmarks/results/train.json"))
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out, results)
    print(f"wrote {out}")
    return results


if __name__ == "__main__":
    main()
