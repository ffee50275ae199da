"""A smoke run of benchmarks/bench_deploy.py: every figure is there and consistent (timings are not judged)."""
from __future__ import annotations

import json

import pytest

pytest.importorskip("spf_rl_runtime")


def test_a_short_run_writes_every_figure(tmp_path):
    import bench_deploy

    out = tmp_path / "deploy.json"
    result = bench_deploy.main(["--exports", str(tmp_path / "exports"), "--steps", "5", "--warmup", "1", "--episodes", "2",
                                "--route-episodes", "0", "--output", str(out)])
    assert json.loads(out.read_text())["model"] == "spf-s0.8"
    rows = {(r["route_steps"], r["sparsity"]): r for r in result["memory"]}
    assert len(rows) == 10 and rows[(100, 0.4)]["kept_frames"] == 40
    assert rows[(100, 0.4)]["int8_bytes"] < rows[(100, 0.4)]["float16_bytes"] < rows[(100, 0.4)]["float32_bytes"] < rows[(100, 0.4)]["raw_frames_bytes"]
    assert [r["threads"] for r in result["latency"]] == [1, 2]
    assert all(r[kind]["p50_ms"] <= r[kind]["p99_ms"] for r in result["latency"] for kind in ("runtime", "eager_tensordict", "eager_bare_tensor"))
    assert result["rss"]["imported_torch_family"] == "[]" and result["rss"]["peak_rss_mb"] > 0
    assert result["weights_bytes"]["int8"]["step.onnx"] < result["weights_bytes"]["fp32"]["step.onnx"]
    success = result["success"]
    assert success["episodes"] == 2 and "vs_fp32" in success["int8-weights-float32-memory"]
    curve = result["budget_curve"]
    assert [p["line"] for p in curve["points"]] == ["spf-s0.4", "spf-s0.6", "spf-s0.8", "rpf-s1"]
    assert all(p["int8_bytes_per_metre"] < p["float32_bytes_per_metre"] < p["raw_frames_bytes_per_metre"] for p in curve["points"])
    assert (tmp_path / "deploy.png").stat().st_size > 10_000


def test_the_route_models_cells_at_each_precision_merge_into_the_output(tmp_path, monkeypatch):
    import bench_deploy

    monkeypatch.setattr(bench_deploy, "ROUTE_SPARSITIES", (0.4,))  # of the bench's two sparsities and three buckets, the shorter
    monkeypatch.setattr(bench_deploy, "ROUTE_BUCKETS", ((10, 30), (31, 60)))
    out = tmp_path / "deploy.json"
    out.write_text(json.dumps({"model": "spf-s0.8"}))
    result = bench_deploy.main(["--exports", str(tmp_path / "exports"), "--only-routes", "--route-episodes", "1", "--output", str(out)])
    assert result["model"] == "spf-s0.8"  # the earlier figures kept
    by_sparsity = json.loads(out.read_text())["route_success"]
    assert {key: routes["sparsity"] for key, routes in by_sparsity.items() if key != "command"} == {"sparsity_0.4": 0.4}
    routes = by_sparsity["sparsity_0.4"]
    assert routes["model"] == "routes-spf" and len(routes["cells"]) == 6
    pooled = routes["pooled"]
    assert set(pooled) == {"fp32-weights-float32-memory", "fp32-weights-float16-memory", "fp32-weights-int8-memory",
                           "int8-weights-float32-memory"}
    assert all(row["episodes"] == 6 for row in pooled.values())
    assert list(routes["pooled_by_length"]) == ["10-30", "31-60"]
    assert all(row["episodes"] == 3 for bucket in routes["pooled_by_length"].values() for row in bucket.values())
    assert "vs_fp32" in pooled["fp32-weights-int8-memory"] and "vs_fp32" not in pooled["fp32-weights-float32-memory"]


def test_the_budget_curve_alone_is_redrawn_from_the_earlier_memory_rows(tmp_path, capsys):
    import bench_deploy

    out = tmp_path / "deploy.json"
    with pytest.raises(SystemExit) as info:  # nothing earlier to draw from
        bench_deploy.main(["--only-budget", "--output", str(out)])
    err = capsys.readouterr().err
    assert info.value.code == 2 and ": error: --only-budget needs an earlier --output" in err
    assert "usage" not in err  # the message alone
    memory = [{"route_steps": 30, "sparsity": s, "raw_frames_bytes": 1000 * s, "float32_bytes": 100 * s, "int8_bytes": 25 * s}
              for s in (0.4, 0.6, 0.8, 1.0)]
    out.write_text(json.dumps({"model": "spf-s0.8", "memory": memory, "latency": [1]}))
    result = bench_deploy.main(["--only-budget", "--output", str(out)])
    table = {row["name"]: row for row in json.loads(open("results/table1.json").read())["rows"]}
    saved = json.loads(out.read_text())
    assert saved["latency"] == [1] and saved["budget_curve"] == result["budget_curve"]  # the rest kept
    points = {p["line"]: p for p in saved["budget_curve"]["points"]}
    assert points["spf-s0.4"]["test_success"] == table["spf-s0.4"]["sets"]["test"]["success"]["mean"]
    metres = saved["budget_curve"]["route_metres_mean"]
    assert points["rpf-s1"]["int8_bytes_per_metre"] == pytest.approx(25 / metres)
