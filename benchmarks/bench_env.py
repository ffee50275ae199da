"""Benchmark: frames/s of the first-person render loop, the env and TorchRL collectors.

Writes ``benchmarks/results/env.json`` and prints a table. Every figure is a
median over timed chunks, after a warm-up (house compilation and GL context
creation happen once per process and are not counted; for multi-process
collectors the first batch is discarded). Frames are 64x64 (``--image-size``),
actions are uniformly random over forward/left/right (no STOP), actuation noise
is the ``paper`` preset, and a small house set (``--num-houses``, default 4) is
used so that per-process house compilation does not dominate.

Configurations, each reported with its ratio to the raw loop measured in the
same run:

a. ``raw``: pose update + :class:`~envs.render.FirstPersonRenderer` + torch
   uint8 ``[H, W, 3]`` tensor (the env's ``pixels`` layout), one house, no TorchRL;
b. ``env_step``: one unbatched env stepped with ``step_and_maybe_reset``;
c. ``collector_single``: the same env through :class:`torchrl.collectors.Collector`;
d. ``collector_batched8``: a batched env (``num_agents=8``) through ``Collector``;
e. ``collector_parallel2``: ``ParallelEnv(2, make_env)`` through ``Collector``;
f. ``multisync_2x_batched8``: ``MultiSyncCollector`` over two batched envs.

Each env episode starts with a newly sampled demonstration whose frames are
rendered at reset (``demo_length`` frames plus route planning), so each config
also reports ``rendered_fps`` (g): collected frames plus demonstration frames
per second, and the profile section reports the reset cost in ms.

The same collection paths with a :class:`~envs.demo_store.DemoStore` (1,000
demonstrations of the same houses, built once before timing and reused from
``--demo-store``; its build time is reported): episodes draw a pre-rendered
demonstration, and the env emits ``demo_id`` instead of the 30 frames
(``emit_demo_frames=False``):

h. ``collector_batched8_store``: (d) with the store;
i. ``multisync_2x_batched8_store``: (f) with the store;
i'. ``multisync_2x_batched32_store``: (i) with 32 agents per env (TorchRL's
   per-step cost is paid once for more frames);
i''. ``multisync_2x_batched32_store_lookup``: (i') with a policy that looks the
   frames up in the store (``store.lookup_module(only_where="is_init")`` in
   front of a random actor, ``selected_out_keys=["action"]``): how a policy
   collecting from store envs gets the demonstration frames at episode starts
   without them entering the collected batch;
j. ``multisync_2x_batched8_store_frames``: (f) with the store but the frames
   still emitted at every step (``emit_demo_frames=True``).
k. ``dmc`` (only when named in ``--only``): ``benchmarks/bench_dmc.py``, the dm_control
   face beside ``PathFollowEnv``, written to ``benchmarks/results/dmc.json``.

The paths are in ``benchmarks/bench_env_paths.py``, the JSON, plot and notes in
``benchmarks/bench_env_report.py``.

Usage::

    python benchmarks/bench_env.py            # about 4-5 minutes
    python benchmarks/bench_env.py --quick    # about 1 minute
    python benchmarks/bench_env.py --plot-only  # redraw env.png from env.json
    python benchmarks/bench_env.py --conditions # the repeat conditions against none -> env_conditions.json
"""
from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import torch
from bench_env_paths import DESCRIPTIONS, BenchConfig, BenchPaths
from bench_env_report import (
    MachineLoad,
    add_ratios,
    build_notes,
    build_output,
    plot_results,
    print_summary,
    write_output,
)

from envs.render import select_gl_backend

logger = logging.getLogger("bench_env")

RESULTS_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "results" / "env.json"
CONDITIONS_PATH = RESULTS_PATH.with_name("env_conditions.json")


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="about 1 minute instead of about 5")
    parser.add_argument("--image-size", type=int, default=64)
    parser.add_argument("--num-houses", type=int, default=4)
    parser.add_argument("--demo-length", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--only", nargs="*", default=None, help="subset of configs (raw env_step ...; dmc if named)")
    parser.add_argument(
        "--demo-store",
        type=Path,
        default=BenchConfig.demo_store_prefix,
        help="demo store directory prefix: the store goes to <prefix>-h<houses>-n<demo length>-s<size> "
        "(built on first use, then reused)",
    )
    parser.add_argument("--output", type=Path, default=RESULTS_PATH)
    parser.add_argument("--plot-only", action="store_true", help="redraw the PNG from an existing --output JSON")
    parser.add_argument("--conditions", action="store_true",
                        help=f"time the repeat conditions instead (bench_env_conditions.py) -> {CONDITIONS_PATH.relative_to(RESULTS_PATH.parents[2])}")
    return parser.parse_args()


def main() -> None:
    args = parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    torch.set_num_threads(1)
    if args.plot_only:
        plot_results(json.loads(args.output.read_text()), args.output.with_suffix(".png"))
        print(f"wrote {args.output.with_suffix('.png')}")
        return
    # the GL back-end goes into the process environment now: recorded in the JSON, inherited by workers
    select_gl_backend()
    config = BenchConfig(args.image_size, args.num_houses, args.demo_length, args.seed, args.quick, args.demo_store)
    if args.conditions:
        from bench_env_conditions import bench_conditions, format_conditions

        from envs.atomic_io import atomic_write_json

        load = MachineLoad.start()
        output = bench_conditions(config)
        output["machine"], load_note = load.finish()
        output["notes"] = [load_note] if load_note else []
        atomic_write_json(CONDITIONS_PATH, output, indent=1)
        print(format_conditions(output))
        print(f"-> {CONDITIONS_PATH}")
        return
    paths = BenchPaths(config)
    wanted = set(args.only) if args.only else set(DESCRIPTIONS)
    if "dmc" in wanted:  # optional path (only when named): benchmarks/bench_dmc.py, writes benchmarks/results/dmc.json
        from bench_dmc import bench_dmc, write_results

        write_results(bench_dmc(args.image_size, args.num_houses, args.demo_length, args.seed, args.quick))
        if wanted == {"dmc"}:
            return

    load = MachineLoad.start()
    results: dict[str, dict] = {}
    profile: dict = {}
    for name in (name for name in DESCRIPTIONS if name in wanted):
        logger.info("running %s", name)
        results[name], path_profile = paths.run(name)
        profile.update(path_profile)  # only env_step profiles the env
        results[name]["description"] = DESCRIPTIONS[name]
        logger.info("%s: %.0f frames/s", name, results[name]["fps"])
    add_ratios(results)
    notes = build_notes(results, profile, paths.store_info, config)
    machine, load_note = load.finish()
    notes += [load_note] if load_note else []
    output = build_output(config, machine, results, profile, paths.store_info, notes)
    write_output(output, args.output)
    print_summary(output, args.output)


if __name__ == "__main__":
    main()
