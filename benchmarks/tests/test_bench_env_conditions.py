"""benchmarks/bench_env_conditions.py: a tiny smoke run of both paths under each world (not a result),
the ratios to none and the targets, and the table."""
from __future__ import annotations

import bench_env_conditions
from bench_env_paths import BenchConfig


def test_a_tiny_run_times_every_world_and_rates_it_against_none(monkeypatch):
    monkeypatch.setattr(bench_env_conditions, "WARMUP_FRAMES", 5)
    monkeypatch.setattr(bench_env_conditions, "RAW_CHUNK_FRAMES", 20)
    monkeypatch.setattr(bench_env_conditions, "ENV_CHUNK_FRAMES", 30)
    monkeypatch.setattr(bench_env_conditions, "PART_CALLS", 3)
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
    assert sum(line.startswith("| ") for line in table.splitlines()) == 1 + len(results) and "| sensor@1 |" in table
    floor = output["sensor_floor"]
    assert all(us > 0 for us in floor["parts_us"].values()) and floor["budget_us_for_render_target"] > 0
    assert 0 < floor["best_render_ratio_with_the_blur_alone"] < 1 and "sensor per frame" in table
    assert set(output["light_parts"]["parts_us"]) == {"teacher", "colour", "colour_turned", "lamp_in_its_room"}
