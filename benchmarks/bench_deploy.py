"""What a robot pays to carry a policy: the route memory's bytes, the step's latency, the teach time, the
weights' bytes, the runtime process's memory, and success at each precision (issue #63).

Exports ``--model`` (default ``spf-s0.8``) in float32 and int8 weights (:mod:`spf_rl.export`) into
``--exports``, then, in one run on idle cores:

* ``memory``: bytes of a :class:`spf_rl_runtime.RouteMemory` for routes of 30 and 100 steps at sparsity
  0.2-1, in float32, float16 and int8 (one scale per slot), against the kept raw frames (``l x 64 x 64 x 3``);
* ``latency``: one step at batch 1, p50 / p95 / p99 over ``--steps`` steps after warm-up, with 1 and 2
  threads, of the runtime (:class:`~spf_rl_runtime.Follower`), of the eager policy as a user steps it (the
  TensorDict module in step mode) and of the eager bare-tensor step (:class:`spf_rl.export.StepGraph`);
  the runtime's teach time for a 100-step route at sparsity 0.8; each graph's bytes per weight precision;
* ``rss``: the peak resident memory (``VmHWM``) of a child process that imports only the runtime,
  teaches a route and follows it;
* ``success`` (``--episodes`` > 0): the export on Table 1's test episodes at each memory precision and with
  int8 weights, paired against the float32 export on the same episodes (:func:`spf_rl.eval.paired.compare`),
  and the float32 export's per-episode success against the eager policy's (Table 1's cached records);
* ``route_success`` (``--route-episodes`` > 0): the same for ``--route-model`` (default ``routes-spf``) on the
  route bench's test cells (every style x length bucket), per cell and pooled, at each sparsity of
  :data:`ROUTE_SPARSITIES` (``{"sparsity_0.8": ..., "sparsity_0.4": ...}``), and the float32 export's
  per-episode success against the eager checkpoint's (the route bench's records of it)
  (``--only-routes``: this alone, merged into the earlier output);
* ``budget_curve``: Table 1's test success of SPF at sparsity 0.4-1 against the bytes kept per metre of
  route (``--only-budget``: this alone, from the earlier output's ``memory`` and the current
  ``results/table1.json``, merged into it: after Table 1 is rescored).

Writes ``benchmarks/results/deploy.json``. ARM boards (a Jetson, a Raspberry Pi) are not measured here.

Usage::

    python benchmarks/bench_deploy.py                         # everything (minutes; success on 1,000 episodes)
    python benchmarks/bench_deploy.py --episodes 0 --route-episodes 0 --steps 500   # bytes and latency only
    python benchmarks/bench_deploy.py --only-routes             # routes-spf's route-bench cells at each precision
    python benchmarks/bench_deploy.py --only-budget             # the budget curve again, after Table 1 changed
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import platform
import subprocess
import sys
import time
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from envs.atomic_io import atomic_write_json

RESULTS = Path("benchmarks/results/deploy.json")
SPARSITIES = (0.2, 0.4, 0.6, 0.8, 1.0)
ROUTE_LENGTHS = (30, 100)
PRECISIONS = ("float32", "float16", "int8")
logger = logging.getLogger("bench_deploy")


def percentiles(seconds: list[float]) -> dict:
    """p50 / p95 / p99 of step times, in milliseconds."""
    ms = np.asarray(seconds) * 1e3
    return {f"p{q}_ms": float(np.percentile(ms, q)) for q in (50, 95, 99)}


def memory_table(follower) -> list[dict]:
    """Route-memory bytes against raw frames for every route length, sparsity and precision."""
    from spf_rl_runtime import memory_length

    rng = np.random.default_rng(0)
    height, width = follower.image_size
    rows = []
    for n in ROUTE_LENGTHS:
        frames = rng.integers(0, 256, (n, height, width, 3), dtype=np.uint8)
        actions = rng.integers(0, 3, n)
        for sparsity in SPARSITIES:
            kept = memory_length(n, sparsity)
            row = {"route_steps": n, "sparsity": sparsity, "kept_frames": kept, "raw_frames_bytes": kept * height * width * 3 + n}
            for dtype in PRECISIONS:
                row[f"{dtype}_bytes"] = follower.teach(frames, actions, sparsity=sparsity, memory_dtype=dtype).nbytes
            rows.append(row)
    return rows


def time_steps(step, frames: np.ndarray, warmup: int, steps: int) -> list[float]:
    for frame in frames[:warmup]:
        step(frame)
    times = []
    for i in range(steps):
        start = time.perf_counter()
        step(frames[i % len(frames)])
        times.append(time.perf_counter() - start)
    return times


def latency(export_dir: Path, model: str, threads: int, steps: int, warmup: int) -> dict:
    """Step latency of the runtime, the eager TensorDict module and the eager bare-tensor step; teach time."""
    import torch
    from spf_rl_runtime import Follower
    from tensordict import TensorDict

    from spf_rl import load_policy
    from spf_rl.export import StepGraph
    from spf_rl.modules.memory import memory_indices

    torch.set_num_threads(threads)
    rng = np.random.default_rng(1)
    follower = Follower(export_dir, threads=threads)
    height, width = follower.image_size
    frames = rng.integers(0, 256, (64, height, width, 3), dtype=np.uint8)
    route = rng.integers(0, 256, (100, height, width, 3), dtype=np.uint8)
    actions = rng.integers(0, 3, 100)
    teach_times = []
    for _ in range(5):
        start = time.perf_counter()
        memory = follower.teach(route, actions, sparsity=0.8)
        teach_times.append(time.perf_counter() - start)
    follower.start(memory)
    out = {"threads": threads, "runtime": percentiles(time_steps(follower.step, frames, warmup, steps)),
           "teach_100_steps_s0.8_ms": float(np.median(teach_times) * 1e3)}

    policy, config = load_policy(model)
    n = config.demo_length
    demo = torch.from_numpy(route[:n])
    demo_actions = torch.from_numpy(actions[:n])
    state = {}

    def eager_step(frame):
        nonlocal state
        with torch.no_grad():
            td = TensorDict({"pixels": torch.from_numpy(frame)[None], "demo_frames": demo[None], "demo_actions": demo_actions[None],
                             "is_init": torch.tensor([[not state]]), **state}, [1])
            result = policy(td)
            state = {key: result["next", key] for key in result["next"].keys()}
        return int(result["logits"].argmax())

    out["eager_tensordict"] = percentiles(time_steps(eager_step, frames, warmup, steps))
    graph = StepGraph(policy).eval()
    kept = memory_indices(n, policy.sparsity)
    with torch.no_grad():
        from spf_rl.export import TeachGraph

        features = TeachGraph(policy)(demo[kept], demo_actions[kept])[None]
    tensors = {"memory": features, "slots": kept[None], "actions": demo_actions[None], "length": torch.tensor([n]),
               "eta": torch.zeros(1), "hidden": torch.zeros(1, config.hidden_size)}

    def bare_step(frame):
        with torch.no_grad():
            logits, tensors["eta"], tensors["hidden"] = graph(torch.from_numpy(frame)[None], tensors["memory"], tensors["slots"],
                                                              tensors["actions"], tensors["length"], tensors["eta"], tensors["hidden"])
        return int(logits.argmax())

    out["eager_bare_tensor"] = percentiles(time_steps(bare_step, frames, warmup, steps))
    out["runtime_speedup_over_eager_tensordict_p50"] = out["eager_tensordict"]["p50_ms"] / out["runtime"]["p50_ms"]
    return out


RSS_SCRIPT = """
import resource, sys, numpy as np
from spf_rl_runtime import Follower
f = Follower(sys.argv[1], threads=1)
rng = np.random.default_rng(0)
h, w = f.image_size
f.start(f.teach(rng.integers(0, 256, (100, h, w, 3), dtype=np.uint8), rng.integers(0, 3, 100), memory_dtype="int8"))
for frame in rng.integers(0, 256, (200, h, w, 3), dtype=np.uint8):
    f.step(frame)
# VmHWM: this process's own peak (ru_maxrss keeps the forking parent's high-water mark across exec on Linux)
status = open("/proc/self/status").read().split("VmHWM:")
peak = int(status[1].split()[0]) if len(status) > 1 else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(peak, sorted(m for m in ("torch", "torchrl", "tensordict") if m in sys.modules))
"""


def peak_rss(export_dir: Path) -> dict:
    """Peak resident memory of a child process that runs only the runtime (its ``VmHWM``: ``ru_maxrss`` would
    report the benchmark's own, kept across ``exec`` on Linux)."""
    result = subprocess.run([sys.executable, "-c", RSS_SCRIPT, str(export_dir)], capture_output=True, text=True, check=True)
    kib, imported = result.stdout.strip().split(" ", 1)
    return {"peak_rss_mb": int(kib) / 1024, "imported_torch_family": imported}


def success(exports: dict[str, Path], model: str, episodes: int) -> dict:
    """The export at each memory precision and with int8 weights on Table 1's test episodes, paired."""
    import tempfile

    from spf_rl.eval.paired import compare
    from spf_rl.eval.table1_rows import eval_sets
    from spf_rl.evaluation import evaluate_policy
    from spf_rl.modules.exported import ExportedPolicy
    from spf_rl.records_cache import write_records

    config = dataclasses.replace(eval_sets([], quick=False)["test"], num_episodes=episodes)
    files, out = {}, {"episodes": episodes}
    with tempfile.TemporaryDirectory() as tmp:
        variants = {f"fp32-weights-{dtype}-memory": (exports["fp32"], dtype) for dtype in PRECISIONS}
        variants["int8-weights-float32-memory"] = (exports["int8"], "float32")
        for name, (directory, dtype) in variants.items():
            start = time.time()
            summary, records = evaluate_policy(ExportedPolicy(directory, memory_dtype=dtype), config)
            files[name] = Path(tmp) / f"{name}.json"
            write_records(files[name], {"variant": name}, records)
            out[name] = {"success": summary["success"], "spl": summary["spl"], "seconds": time.time() - start}
            logger.info("%s: success %.3f", name, summary["success"])
        reference = files["fp32-weights-float32-memory"]
        for name, path in files.items():
            if path != reference:
                out[name]["vs_fp32"] = compare(path, reference, 10_000, 0)["metrics"]["success"]
        eager = Path("results/eval/table1/test") / f"{model}-seed{shipped_seed(model)}.json"
        if episodes == 1000 and eager.exists():
            exported = json.loads(reference.read_text())["columns"]["success"]
            cached = json.loads(eager.read_text())["columns"]["success"]
            out["fp32_vs_eager"] = {"eager_cache": str(eager), "episodes_differing": int(sum(a != b for a, b in zip(exported, cached))),
                                    "eager_success": float(np.mean(cached)), "export_success": float(np.mean(exported))}
    return out


#: The sparsities the route model's cells are played at: the route bench's, and the 8 KB target's.
ROUTE_SPARSITIES = (0.8, 0.4)
#: The length buckets of the route model's cells (``None``: the route bench's, 10-30, 31-60 and 61-100 steps).
ROUTE_BUCKETS: tuple[tuple[int, int], ...] | None = None


def route_success(exports: dict[str, Path], model: str, episodes: int, workdir: Path, sparsity: float) -> dict:
    """The route model's export at each memory precision and with int8 weights on the route bench's cells
    (test set, every style x length bucket, ``episodes`` per cell, played at ``sparsity``), each cell and
    all of them pooled paired against the float32 export on the same episodes."""
    from spf_rl.eval.route_bench import DEFAULT_BUCKETS, OPEN_LOOP, BenchModel, BenchOptions, paired_against, run_bench
    from spf_rl.modules.exported import ExportedPolicy

    variants = {f"fp32-weights-{dtype}-memory": (exports["fp32"], dtype) for dtype in PRECISIONS}
    variants["int8-weights-float32-memory"] = (exports["int8"], "float32")
    models = [BenchModel(OPEN_LOOP, None, None, {"checkpoint": None, "model_type": OPEN_LOOP})]
    for name, (directory, dtype) in variants.items():
        models.append(BenchModel(name, ExportedPolicy(directory, memory_dtype=dtype), sparsity,
                                 {"checkpoint": str(directory), "memory_dtype": dtype, "played_at_sparsity": sparsity}))
    options = BenchOptions(models=(), sets=("test",), episodes=episodes, buckets=ROUTE_BUCKETS or DEFAULT_BUCKETS,
                           out=workdir / f"route_bench_{model}_s{sparsity}_precisions.json")
    content = run_bench(options, models)
    reference = "fp32-weights-float32-memory"
    out: dict = {"model": model, "episodes_per_cell": episodes, "sparsity": sparsity, "cells": {}}
    for key, cell in content["cells"].items():
        columns = {name: cell["models"][name]["columns"] for name in variants}
        out["cells"][key] = {name: {"success": float(np.mean(columns[name]["success"]))} for name in variants}
        for name in variants:
            if name != reference:
                out["cells"][key][name]["vs_fp32"] = paired_against(columns[name], columns[reference], cell["episodes"]["house_seed"],
                                                                     10_000, metrics=("success",))["success"]
    out["fp32_vs_eager"] = route_vs_eager(model, content, ROUTE_EAGER_SOURCES.get(sparsity))
    out["pooled"] = pool_cells(content["cells"].values(), list(variants), reference)
    buckets = sorted({key.rsplit("/", 1)[1] for key in content["cells"]}, key=lambda bucket: int(bucket.split("-")[0]))
    out["pooled_by_length"] = {bucket: pool_cells([cell for key, cell in content["cells"].items() if key.endswith("/" + bucket)],
                                                  list(variants), reference) for bucket in buckets}
    for name in variants:
        logger.info("routes %s: success %.3f", name, out["pooled"][name]["success"])
    return out


def pool_cells(cells: Iterable[dict], names: list[str], reference: str) -> dict:
    """Each of ``names``' success pooled over the route-bench ``cells``, paired against ``reference``'s
    (house-level resampling over every pooled episode)."""
    from spf_rl.eval.route_bench import paired_against

    cells = list(cells)
    houses = [house for cell in cells for house in cell["episodes"]["house_seed"]]
    values = {name: [v for cell in cells for v in cell["models"][name]["columns"]["success"]] for name in names}
    out = {}
    for name in names:
        out[name] = {"success": float(np.mean(values[name])), "episodes": len(values[name])}
        if name != reference:
            out[name]["vs_fp32"] = paired_against({"success": values[name]}, {"success": values[reference]}, houses, 10_000,
                                                  metrics=("success",))["success"]
    return out


#: The route bench's runs that played the route models eagerly, on the same cells and episodes, per sparsity.
ROUTE_EAGER_SOURCES = {0.8: Path("results/route_bench_routes_more_3seeds_128ep.json"),
                       0.4: Path("results/route_bench_routes_more_3seeds_s0.4_128ep.json")}


def route_vs_eager(model: str, content: dict, source: Path | None) -> dict | None:
    """The float32 export's successes against the eager checkpoint's on the same route-bench episodes
    (the run in ``source``, the label of the file ``model`` names), cell by cell; ``None`` where there is no
    such run, or it lacks the checkpoint or played other episodes."""
    from spf_rl.hub import read_manifest

    label = read_manifest()["names"].get(model, "").removesuffix(".pt")
    if not label or source is None or not source.is_file():
        return None
    eager = json.loads(source.read_text())["cells"]
    differing = total = 0
    for key, cell in content["cells"].items():
        stored = eager.get(key, {})
        if label not in stored.get("models", {}) or stored["episodes"]["house_seed"] != cell["episodes"]["house_seed"]:
            return None
        exported = cell["models"]["fp32-weights-float32-memory"]["columns"]["success"]
        played = stored["models"][label]["columns"]["success"]
        differing += sum(a != b for a, b in zip(exported, played))
        total += len(played)
    return {"eager_source": str(source), "eager_label": label, "episodes": total, "episodes_differing": int(differing)}


def route_successes(exports: dict[str, Path], model: str, episodes: int, workdir: Path) -> dict:
    """:func:`route_success` at each sparsity of :data:`ROUTE_SPARSITIES`, keyed ``sparsity_<s>``."""
    return {f"sparsity_{sparsity}": route_success(exports, model, episodes, workdir, sparsity) for sparsity in ROUTE_SPARSITIES}


#: Table 1's lines drawn on the budget curve (their sparsity, their test success over seeds).
CURVE_LINES = ("spf-s0.4", "spf-s0.6", "spf-s0.8", "rpf-s1")
#: A run that tested on Table 1's test episodes, for the routes' lengths in metres (every line plays the same episodes).
ROUTE_METRES_SOURCE = Path("runs/table1/spf-s0.8-seed0/test_episodes.json")


def budget_curve(memory: list[dict], figure: Path) -> dict | None:
    """Table 1's test success against the bytes a robot keeps per metre of route, over the sparsities: the
    paper's claim, drawn (raw frames, float32 and int8 route memories of its 30-step routes)."""
    table = Path("results/table1.json")
    if not table.exists() or not ROUTE_METRES_SOURCE.exists():
        return None
    metres = float(np.mean(json.loads(ROUTE_METRES_SOURCE.read_text())["columns"]["shortest_path_length"]))
    rows = {row["name"]: row for row in json.loads(table.read_text())["rows"]}
    by_sparsity = {r["sparsity"]: r for r in memory if r["route_steps"] == 30}
    points = []
    for name in CURVE_LINES:
        row = rows[name]
        sizes = by_sparsity[row["sparsity"]]
        points.append({"line": name, "sparsity": row["sparsity"], "test_success": row["sets"]["test"]["success"]["mean"],
                       **{f"{kind}_bytes_per_metre": sizes[f"{kind}_bytes"] / metres for kind in ("raw_frames", "float32", "int8")}})
    from spf_rl.viz import pyplot, write_figure

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    for kind, marker in (("raw_frames", "s"), ("float32", "o"), ("int8", "^")):
        ax.plot([p[f"{kind}_bytes_per_metre"] for p in points], [p["test_success"] for p in points], marker=marker,
                label=kind.replace("_", " "))
    for p in points:
        ax.annotate(f"{p['sparsity']:g}", (p["int8_bytes_per_metre"], p["test_success"]), fontsize=7)
    ax.set_xscale("log")
    ax.set_xlabel(f"bytes kept per metre of route (Table 1's 30-step routes, {metres:.1f} m on average)")
    ax.set_ylabel("Table 1 test success (mean of 3 seeds)")
    ax.set_title("Memory against success: SPF at sparsity 0.4-1")
    ax.legend(fontsize=8)
    fig.tight_layout()
    write_figure(fig, figure, dpi=120)
    return {"route_metres_mean": metres, "points": points, "figure": str(figure)}


def shipped_seed(model: str) -> int | None:
    """The Table 1 seed a shipped name loads (its per-seed file), if it is one."""
    from spf_rl.hub import read_manifest

    target = read_manifest()["names"].get(model, "")
    return int(target.rsplit("-seed", 1)[1].removesuffix(".pt")) if "-seed" in target else None


def main(argv: list[str] | None = None) -> dict:
    from spf_rl.cli import ArgumentParser  # a refused argument: its message alone, exit status 2

    parser = ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", default="spf-s0.8", help="a shipped name (default: %(default)s)")
    parser.add_argument("--exports", type=Path, default=Path("exports"), help="where the exports go (default: %(default)s)")
    parser.add_argument("--steps", type=int, default=2000, help="timed steps per latency figure (default: %(default)s)")
    parser.add_argument("--warmup", type=int, default=100)
    parser.add_argument("--episodes", type=int, default=1000, help="Table 1 test episodes for the success figures (0: none)")
    parser.add_argument("--route-model", default="routes-spf", help="the route model whose route-bench cells are played at each precision (default: %(default)s)")
    parser.add_argument("--route-episodes", type=int, default=128, help="episodes per route-bench cell for --route-model (0: none; default: %(default)s)")
    parser.add_argument("--only-routes", action="store_true", help="only the route model's success at each precision, merged into --output")
    parser.add_argument("--only-budget", action="store_true",
                        help="only the budget curve, from --output's memory rows and results/table1.json, merged into --output")
    parser.add_argument("--output", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    if args.only_budget:  # no export, no episode: the earlier output's bytes against the current Table 1
        earlier = json.loads(args.output.read_text()) if args.output.is_file() else {}
        if not earlier.get("memory"):
            parser.error(f"--only-budget needs an earlier --output with its memory rows; {args.output} has none")
        curve = budget_curve(earlier["memory"], args.output.with_suffix(".png"))
        if curve is None:
            parser.error("--only-budget needs results/table1.json and " + str(ROUTE_METRES_SOURCE))
        earlier["budget_curve"] = curve
        atomic_write_json(args.output, earlier, default=str)
        return earlier
    if args.steps < 1 or args.warmup < 0 or args.episodes < 0 or args.route_episodes < 0:
        parser.error("--steps must be >= 1, --warmup, --episodes and --route-episodes >= 0")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    from spf_rl_runtime import Follower

    import envs  # noqa: F401  (selects the headless GL back-end first)
    from spf_rl.device import machine_info
    from spf_rl.export import export_checkpoint

    if args.only_routes:  # merged into the benchmark's earlier output
        if not args.route_episodes:
            parser.error("--only-routes needs --route-episodes > 0")
        route_exports = {weights: args.exports / f"{args.route_model}-{weights}" for weights in ("fp32", "int8")}
        for weights, path in route_exports.items():
            export_checkpoint(args.route_model, path, weights=weights)
        result = json.loads(args.output.read_text()) if args.output.is_file() else {}
        result["route_success"] = route_successes(route_exports, args.route_model, args.route_episodes, args.exports)
        result["route_success"]["command"] = "python benchmarks/bench_deploy.py " + " ".join(argv if argv is not None else sys.argv[1:])
        atomic_write_json(args.output, result, default=str)
        logger.info("wrote %s", args.output)
        return result
    exports = {weights: args.exports / f"{args.model}-{weights}" for weights in ("fp32", "int8")}
    manifests = {weights: export_checkpoint(args.model, path, weights=weights) for weights, path in exports.items()}
    result = {
        "command": "python benchmarks/bench_deploy.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "model": args.model,
        "machine": machine_info(),
        "python": platform.python_version(),
        "note": "x86 CPU of this machine only; ARM boards (Jetson, Raspberry Pi) are not measured",
        "weights_bytes": {weights: {name: (path / name).stat().st_size for name in manifests[weights]["files"]}
                          for weights, path in exports.items()},
        "memory": memory_table(Follower(exports["fp32"])),
        "latency": [latency(exports["fp32"], args.model, threads, args.steps, args.warmup) for threads in (1, 2)],
        "rss": peak_rss(exports["fp32"]),
    }
    result["budget_curve"] = budget_curve(result["memory"], args.output.with_suffix(".png"))
    if args.episodes:
        result["success"] = success(exports, args.model, args.episodes)
    if args.route_episodes:
        route_exports = {weights: args.exports / f"{args.route_model}-{weights}" for weights in ("fp32", "int8")}
        for weights, path in route_exports.items():
            export_checkpoint(args.route_model, path, weights=weights)
        result["route_success"] = route_successes(route_exports, args.route_model, args.route_episodes, args.exports)
    atomic_write_json(args.output, result, default=str)
    logger.info("wrote %s", args.output)
    return result


if __name__ == "__main__":
    main()
