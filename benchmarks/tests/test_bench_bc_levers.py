"""Tests for benchmarks/bench_bc_levers.py: options checked before any work, and the JSON it writes."""
from __future__ import annotations

import json

import bench_bc_levers
import pytest


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--repeats", "0"], "--repeats must be >= 1"),
        (["--threads", "0"], "--threads must be >= 1"),
        (["--variants", "eager_b16,fast"], "--variants: unknown ['fast']"),
    ],
)
def test_bad_options_are_refused_before_any_work(argv, message, tmp_path, capsys):
    with pytest.raises(SystemExit):
        bench_bc_levers.main([*argv, "--data-dir", str(tmp_path / "data"), "--output", str(tmp_path / "out.json")])
    assert message in capsys.readouterr().err
    assert not (tmp_path / "data").exists() and not (tmp_path / "out.json").exists()


def test_ratios_are_medians_over_the_reference(tmp_path):
    """A quick run of two variants writes each median and its ratio to the reference, which is always run."""
    out = tmp_path / "levers.json"
    results = bench_bc_levers.main(
        ["--quick", "--repeats", "2", "--threads", "1", "--variants", "eager_b32",
         "--data-dir", str(tmp_path / "data"), "--output", str(out)]
    )
    saved = json.loads(out.read_text())
    assert saved == json.loads(json.dumps(results))
    assert set(saved["variants"]) == {"eager_b16", "eager_b32"}
    for variant in saved["variants"].values():
        assert len(variant["repeats"]) == 2 and all(rate > 0 for rate in variant["repeats"])
        assert variant["median"] == pytest.approx(sum(variant["repeats"]) / 2)
    reference = saved["variants"]["eager_b16"]["median"]
    assert saved["variants"]["eager_b16"]["over_reference"] == pytest.approx(1.0)
    assert saved["variants"]["eager_b32"]["over_reference"] == pytest.approx(saved["variants"]["eager_b32"]["median"] / reference)
