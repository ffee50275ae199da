"""Benchmark: levers on behaviour-cloning throughput, each against eager batch-16 training in one run.

Labelled steps per second (valid follow steps through the cross-entropy, backward
and Adam step) of SPF 0.8 in sequence mode, for:

* ``eager_b16``: the training loops as they run (eager, 16 episodes a batch), the reference;
* ``compile_encoder_b16``: the image encoder (the convolutions, most of a step)
  under ``torch.compile(dynamic=True)``; compilation is warmed up outside the timing;
* ``compile_unroll_b16``: the recurrent unroll (attention and GRU cell over the steps,
  ``SPFPolicy._unroll``) under ``torch.compile``, forward and backward; warmed up likewise;
* ``eager_b32``: 32 episodes a batch (each batch the union of two of the reference's);
* ``bf16_b16``: bf16 autocast (``optim.amp=true``); ``bf16_compile_encoder_b16``: both.

Every variant trains its own copy of one initialisation on the same batches; the
variants run interleaved, ``--repeats`` times, and each figure is the median.
Writes ``benchmarks/results/bc_levers.json`` (``--output``): per variant the
median rate and its ratio to ``eager_b16``.

Usage::

    python benchmarks/bench_bc_levers.py --threads 1        # a few minutes on 2 CPU cores
    python benchmarks/bench_bc_levers.py --quick
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import statistics
import time
from pathlib import Path

from envs.atomic_io import atomic_write_json
from envs.episode_spec import EpisodeSpec
from spf_rl.device import machine_info

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "bc_levers.json"
#: variant -> (episodes a batch, what is compiled: None, "encoder" or "unroll", bf16 autocast)
VARIANTS = {
    "eager_b16": (16, None, False),
    "compile_encoder_b16": (16, "encoder", False),
    "compile_unroll_b16": (16, "unroll", False),
    "eager_b32": (32, None, False),
    "bf16_b16": (16, None, True),
    "bf16_compile_encoder_b16": (16, "encoder", True),
}
REFERENCE = "eager_b16"


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="4 batches of 16 a repeat, 3 repeats")
    parser.add_argument("--repeats", type=int, default=None, help="interleaved repeats (default 5, --quick 3)")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    parser.add_argument(
        "--variants", default=",".join(VARIANTS),
        help=f"comma-separated, among {', '.join(VARIANTS)} ({REFERENCE} is always run; default: all)",
    )
    parser.add_argument("--data-dir", default="data/bench-train")
    parser.add_argument("--output", default=str(RESULTS))
    args = parser.parse_args(argv)
    repeats = args.repeats if args.repeats is not None else (3 if args.quick else 5)
    if repeats < 1:
        parser.error(f"--repeats must be >= 1, got {repeats}")
    if args.threads is not None and args.threads < 1:
        parser.error(f"--threads must be >= 1, got {args.threads}")
    chosen = [name.strip() for name in args.variants.split(",") if name.strip()]
    unknown = [name for name in chosen if name not in VARIANTS]
    if unknown:
        parser.error(f"--variants: unknown {unknown}; allowed: {', '.join(VARIANTS)}")
    variants = {name: VARIANTS[name] for name in VARIANTS if name in chosen or name == REFERENCE}

    import torch

    import envs  # noqa: F401  (selects the headless GL back-end first)
    from spf_rl.data import DatasetConfig, EpisodeDataset
    from spf_rl.modules.encoder import ImageEncoder
    from spf_rl.modules.registry import ModelConfig, build_policy, spf_config
    from spf_rl.train.bc import bc_loss

    if args.threads is not None:
        torch.set_num_threads(args.threads)
    dataset = EpisodeDataset.build(
        args.data_dir, DatasetConfig(EpisodeSpec(num_houses=4, max_steps=50, seed=123), num_episodes=64, chunk_size=16), num_workers=1
    )
    pairs = 2 if args.quick else 4
    small = [dataset.replay_buffer(16, seed=seed).sample() for seed in range(2 * pairs)]
    batches = {16: small, 32: [torch.cat(small[i : i + 2], 0) for i in range(0, len(small), 2)]}

    torch.manual_seed(0)
    initial = build_policy("spf", spf_config(ModelConfig(name="spf", sparsity=0.8), 30, 64))
    learners, compile_seconds = {}, {}
    for name, (batch_size, compiled, amp) in variants.items():
        policy = copy.deepcopy(initial)
        if compiled == "encoder":
            for module in policy.modules():
                if isinstance(module, ImageEncoder):
                    module.compile(dynamic=True)
        elif compiled == "unroll":  # the attention and the cell over all steps (SPFPolicy._unroll)
            policy._unroll = torch.compile(policy._unroll)
        learners[name] = (policy, torch.optim.Adam(policy.parameters(), lr=1e-3), batches[batch_size], amp)

    def run(name: str, warm_up: bool = False) -> float:
        policy, optimizer, todo, amp = learners[name]
        start, labelled = time.perf_counter(), 0
        for batch in todo[:1] if warm_up else todo:
            loss, _ = bc_loss(policy, batch, amp=amp)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            labelled += int(batch["steps", "mask"].sum())
        return labelled / (time.perf_counter() - start)

    for name in variants:  # compilation (and its recompiles for other lengths) outside the timing
        start = time.perf_counter()
        run(name, warm_up=True)
        run(name)
        if variants[name][1]:
            compile_seconds[name] = time.perf_counter() - start
    rates: dict[str, list[float]] = {name: [] for name in variants}
    for repeat in range(repeats):  # interleaved, the order reversed every other repeat
        for name in list(variants)[:: 1 if repeat % 2 == 0 else -1]:
            rates[name].append(run(name))
    reference = statistics.median(rates[REFERENCE])
    results = {
        "benchmark": "bc_levers",
        "quick": args.quick,
        "unit": "labelled steps/s",
        "repeats": repeats,
        "reference": REFERENCE,
        "variants": {
            name: {
                "median": statistics.median(values),
                "over_reference": statistics.median(values) / reference,
                "repeats": values,
            }
            for name, values in rates.items()
        },
        "compile_warm_up_seconds": compile_seconds,
        "bf16_supported": bool(torch.ops.mkldnn._is_mkldnn_bf16_supported()),
        "machine": {**machine_info(), "cpus": os.cpu_count(), "torch_threads": torch.get_num_threads()},
    }
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(out, results)
    print(json.dumps({name: round(v["over_reference"], 3) for name, v in results["variants"].items()}))
    return results


if __name__ == "__main__":
    main()
