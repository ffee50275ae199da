"""The report of ``benchmarks/bench_env.py``: machine facts, ratios, notes, JSON, plot and table.

:func:`build_output` assembles the JSON written to ``benchmarks/results/env.json``
(keys ``benchmark``, ``machine``, ``setup``, ``results``, ``profile_single_env``,
``demo_store``, ``targets``, ``notes``); :func:`write_output` writes it and draws
frames/s per path beside it (``env.png``, :func:`plot_results`). :class:`MachineLoad`
records what else used the CPUs while the benchmark ran, since the figures depend on it.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from envs.atomic_io import atomic_write_json
from spf_rl.device import machine_info

if TYPE_CHECKING:
    from bench_env_paths import BenchConfig

#: Targets of a collection path: frames/s, and frames/s over the raw loop's (one process).
TARGETS = {"fps": 3000, "ratio_to_raw": 1.0}
#: A process counts as busy during the run above this share of one core.
BUSY_CPU_SHARE = 0.05


def other_processes_cpu_seconds() -> dict[int, tuple[str, float]]:
    """CPU seconds used so far by every other process (Linux ``/proc``), by pid: (command, seconds)."""
    ticks = os.sysconf("SC_CLK_TCK")
    usage: dict[int, tuple[str, float]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            stat = (entry / "stat").read_text()
            command = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2 :].split()
        usage[int(entry.name)] = (command[:80], (int(fields[11]) + int(fields[12])) / ticks)
    return usage


@dataclass
class MachineLoad:
    """Machine facts at the start of a run and the CPU other processes use during it."""

    machine: dict
    others_before: dict[int, tuple[str, float]]
    wall_start: float

    @classmethod
    def start(cls) -> MachineLoad:
        """Call before the timed paths (the load average is read now)."""
        machine = machine_info()
        others = other_processes_cpu_seconds() if Path("/proc").exists() else {}
        return cls(machine, others, time.perf_counter())

    def finish(self) -> tuple[dict, str | None]:
        """The ``machine`` JSON entry, and a note if other processes were busy during the run.

        Processes alive at the end count the CPU they used during the run (all of it
        for those started after the benchmark began); the benchmark's own workers
        have exited by then.
        """
        load_after = [round(x, 2) for x in os.getloadavg()]
        wall = time.perf_counter() - self.wall_start
        others_after = other_processes_cpu_seconds() if self.others_before else {}
        used = {
            pid: (command, cpu - (self.others_before[pid][1] if pid in self.others_before else 0.0))
            for pid, (command, cpu) in others_after.items()
        }
        busy = {command: cpu for command, cpu in used.values() if cpu > BUSY_CPU_SHARE * wall}
        machine = {**self.machine, "other_processes_cpu_share": {command: round(cpu / wall, 2) for command, cpu in busy.items()}}
        note = None
        if busy:
            note = (
                "The machine was shared while this ran: processes started before the benchmark used "
                f"{sum(busy.values()) / wall:.2f} of the {os.cpu_count()} cores on average "
                f"({', '.join(f'{c!r}: {v / wall:.2f}' for c, v in busy.items())}), so the figures (multi-process ones "
                "most) are lower than on an idle machine."
            )
        return {**machine, "load_average_at_end": load_after}, note


def add_ratios(results: dict[str, dict]) -> None:
    """Add ``ratio_to_raw`` (and ``rendered_ratio_to_raw``) to every result, if the raw loop ran."""
    raw_fps = results.get("raw", {}).get("fps")
    if not raw_fps:
        return
    for result in results.values():
        result["ratio_to_raw"] = result["fps"] / raw_fps
        if "rendered_fps" in result:
            result["rendered_ratio_to_raw"] = result["rendered_fps"] / raw_fps


def _best_path_notes(collectors: dict[str, dict], raw_fps: float) -> list[str]:
    """The fastest collection path with demonstrations sampled at reset, and with a demo store."""
    notes = []
    sampled = [k for k in collectors if "_store" not in k]
    stored = [k for k in collectors if k not in sampled]
    for label, names in (("demonstrations sampled at reset", sampled), ("demo store", stored)):
        if not names:
            continue
        best_name = max(names, key=lambda k: collectors[k]["fps"])
        best = collectors[best_name]
        reached = best["fps"] >= TARGETS["fps"] and best["ratio_to_raw"] >= TARGETS["ratio_to_raw"]
        rendered = (
            f"; counting demonstration frames rendered at reset {best['rendered_fps']:.0f} frames/s = "
            f"{best['rendered_ratio_to_raw']:.2f}x"
            if "rendered_fps" in best
            else ""
        )
        notes.append(
            f"Best collection path ({label}): {best_name} at {best['fps']:.0f} frames/s = "
            f"{best['ratio_to_raw']:.2f}x the raw loop ({raw_fps:.0f} frames/s, {1e3 / raw_fps:.2f} ms/frame)"
            + rendered
            + f". Targets (>= {TARGETS['fps']} frames/s and >= {TARGETS['ratio_to_raw']}x raw): "
            f"{'reached' if reached else 'NOT reached'}."
        )
    return notes


def _raw_notes(collectors: dict[str, dict], profile: dict, raw_fps: float, demo_length: int) -> list[str]:
    """What the ratios compare, and what sampling demonstrations at reset bounds."""
    notes = [
        "Ratios compare each path (multi-process paths use 2 worker processes, plus the parent) with the raw loop "
        "in ONE process, as the target is defined; per process, divide the multi-process ratios by 2."
    ]
    if any("_store" not in k for k in collectors):
        notes.append(
            f"Sampling demonstrations at reset: rendering alone caps 2 processes at about {2 * raw_fps:.0f} frames/s, "
            f"and every episode of about {profile.get('steps_per_episode', float('nan')):.0f} steps also renders "
            f"{demo_length} demonstration frames and plans a route at reset (ms_per_reset in profile), so the collected "
            f"frame rate is bounded by about 2 x raw x steps/(steps + {demo_length}) even with zero Python/TorchRL "
            f"overhead; and every step's output carries the {demo_length} demonstration frames. A DemoStore removes "
            "both: demonstrations are rendered once, and envs emit demo_id (policies look the frames up in the store)."
        )
    return notes


def _store_note(store_info: dict) -> str:
    reuse = "reused from an earlier run" if store_info["reused"] else f"built in {store_info['build_seconds']:.1f} s before timing"
    return (
        f"Demo store: {store_info['num_demos']} demonstrations of the same houses in {store_info['root']}, {reuse}"
        "; store episodes pay one geodesic distance field per new route at reset (cached per env)."
    )


def _profile_note(profile: dict, demo_length: int) -> str:
    return (
        "Where a single env's step goes (ms per step, profile_single_env): total "
        f"{profile['ms_per_step_total']:.2f} = base env _step {profile['base_env_step_ms']:.2f} (of which rendering "
        f"about {profile['render_ms_per_frame_in_env']:.2f}) + resets amortised {profile['reset_ms_per_step_amortised']:.2f} "
        f"({profile['ms_per_reset']:.1f} ms per reset: {demo_length} demo frames + route planning + expert set-up) + "
        f"ActuationNoise {profile['actuation_noise_ms_per_step']:.2f} + "
        f"TorchRL {profile['torchrl_overhead_ms_per_step']:.2f}."
    )


_PARALLEL_NOTE = (
    "ParallelEnv (e): with shared-memory buffers the parent busy-polls the workers' done flags while they "
    "step (torchrl 0.14 ParallelEnv._wait_for_workers), so 2 workers + the parent are 3 busy processes on "
    "2 cores, and every step is a parent-worker round trip; with metadata_from_workers=True (pipes, the "
    "previous setting of this benchmark) step_and_maybe_reset pickles ~32 unconsolidated tensors per worker "
    "per step as shared-memory file descriptors, about 59 frames/s. Torch threads are not the cause "
    "(parent and workers run 1 thread). MultiSyncCollector has no per-step round trip."
)


def _demo_frames_note(results: dict[str, dict], demo_length: int, image_size: int) -> str:
    with_frames = results["collector_batched8"]["fps"]
    without = results["diag_batched8_no_demo_frames"]["fps"]
    return (
        f"Every step's output carries the episode's demo_frames ({demo_length}x{image_size}x{image_size}x3 "
        f"uint8 = {demo_length * 3 * image_size ** 2 / 1024:.0f} KiB per agent, {demo_length}x the frame itself), which "
        "collectors copy into every batch (and step_and_maybe_reset passes through torch.where on resets); "
        f"excluding it (diagnostic) changes Collector(batched 8) from {with_frames:.0f} to {without:.0f} frames/s."
    )


def build_notes(results: dict[str, dict], profile: dict, store_info: dict, config: BenchConfig) -> list[str]:
    """The notes explaining a run's figures (best paths, bounds, profile, diagnostics)."""
    raw_fps = results.get("raw", {}).get("fps")
    collectors = {k: v for k, v in results.items() if k != "raw" and not k.startswith("diag")}
    notes = []
    if raw_fps:
        notes += _best_path_notes(collectors, raw_fps)
        notes += _raw_notes(collectors, profile, raw_fps, config.demo_length)
    if store_info:
        notes.append(_store_note(store_info))
    if profile:
        notes.append(_profile_note(profile, config.demo_length))
    if "collector_parallel2" in results:
        notes.append(_PARALLEL_NOTE)
    if "diag_batched8_no_demo_frames" in results and "collector_batched8" in results:
        notes.append(_demo_frames_note(results, config.demo_length, config.image_size))
    return notes


def build_output(
    config: BenchConfig, machine: dict, results: dict[str, dict], profile: dict, store_info: dict, notes: list[str]
) -> dict:
    """The JSON document of a run."""
    return {
        "benchmark": "benchmarks/bench_env.py" + (" --quick" if config.quick else ""),
        "machine": machine,
        "setup": {
            "image_size": config.image_size,
            "num_houses": config.num_houses,
            "house_set": "train split, first num_houses seeds (small so per-process compilation does not dominate)",
            "demo_length": config.demo_length,
            "noise": "paper",
            "actions": "uniform over forward/left/right, no STOP (episodes end on success or after max_steps=50)",
            "statistic": f"median frames/s over {config.chunks} timed chunks after warm-up (>= 300 frames, or the first "
            "batches for collectors; multi-process collectors discard their first batch)",
            "frames": "collected env steps; rendered_fps adds the demonstration frames rendered at each reset (g)",
        },
        "results": results,
        "profile_single_env": profile,
        "demo_store": store_info,
        "targets": dict(TARGETS),
        "notes": notes,
    }


def write_output(output: dict, path: Path) -> None:
    """The JSON at ``path`` and its plot beside it (same name, ``.png``)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(path, output)
    plot_results(output, path.with_suffix(".png"))


def plot_results(output: dict, path: Path) -> None:
    """Bar chart of frames/s per collection path, with the raw loop and the 3,000 frames/s target."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    results = output["results"]
    names = [name for name in results if name != "raw"]
    fps = [results[name]["fps"] for name in names]
    colours = ["tab:green" if "_store" in name else "tab:blue" for name in names]
    fig, ax = plt.subplots(figsize=(8, 0.45 * len(names) + 1.5))
    ax.barh(names[::-1], fps[::-1], color=colours[::-1])
    if "raw" in results:
        ax.axvline(results["raw"]["fps"], color="black", linestyle="--", label=f"raw loop, 1 process ({results['raw']['fps']:.0f})")
    ax.axvline(output["targets"]["fps"], color="tab:red", linestyle=":", label=f"target ({output['targets']['fps']})")
    for row, value in enumerate(fps[::-1]):
        ax.text(value, row, f" {value:.0f}", va="center", fontsize=8)
    ax.set_xlabel(f"collected frames/s ({output['setup']['image_size']} px, 2 processes at most; green: demo store)")
    ax.legend(loc="lower right", fontsize=8)
    ax.set_title("Environment throughput (benchmarks/bench_env.py)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def print_summary(output: dict, path: Path) -> None:
    """The results table, the single env's profile and the notes, on stdout."""
    print(f"\n{'config':<24} {'frames/s':>9} {'x raw':>6} {'+demo f/s':>10} {'x raw':>6} {'frames':>7}")
    for name, result in output["results"].items():
        print(
            f"{name:<24} {result['fps']:>9.0f} {result.get('ratio_to_raw', float('nan')):>6.2f} "
            f"{result.get('rendered_fps', result['fps']):>10.0f} "
            f"{result.get('rendered_ratio_to_raw', result.get('ratio_to_raw', float('nan'))):>6.2f} {result['frames']:>7}"
        )
    if output["profile_single_env"]:
        print("profile (single env): " + ", ".join(f"{k}={v:.3g}" for k, v in output["profile_single_env"].items()))
    for note in output["notes"]:
        print("note:", note)
    print(f"wrote {path}")
