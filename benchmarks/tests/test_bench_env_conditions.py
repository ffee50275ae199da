"""benchmarks/bench_env_conditions.py: a tiny smoke run of both paths under each world (not a result),
the ratios to none and the targets, and the table."""
from __future__ import annotations

import bench_env_conditions
from bench_env_paths import BenchConfig


def test_a_tiny_run_times_every_world_and_rates_it_against_none(monkeypatch):
    monkeypatch.setattr(bench_env_conditions, "WARMUP_FRAMES", 5)
    monkeypatch.setattr(bench_env_conditions, "RAW_CHUNK_FRAMES", 20)
    monkeypatch.setattr(bench_env_conditions, "ENV_CHUNK_FRAMES", 30)
    output = bench_env_conditions.bench_conditions(BenchConfig(image_size=16, num_houses=1, demo_length=10, quick=True),
                                                   worlds=("none", "light@1", "furniture@1", "sensor@1"))
    results = output["results"]
    assert list(results) == ["none", "light@1", "furniture@1", "sensor@1"]
    assert results["none"]["raw_ratio_to_none"] == 1.0 and results["none"]["env_ratio_to_none"] == 1.0
    for world, row in results.items():
        assert row["raw_fps"] > 0 and row["env_steps_per_s"] > 0
        assert row["env_resets"] > 0  # 90 steps of 10-step routes (at most 17 steps each) reset
        assert row["raw_within_target"] == (row["raw_ratio_to_none"] >= bench_env_conditions.RAW_TARGET)
    table = bench_env_conditions.format_conditions(output)
    assert table.count("\n") == 1 + len(results) and "| sensor@1 |" in table
