"""spf_rl.eval.scripted: the expert and open-loop scores of recipes/expert_stats.py."""
from __future__ import annotations

import json
import math

import pytest
import torch

from spf_rl.eval.scripted import run_one, score

ENV = {"num_agents": 2, "num_houses": 2, "render": False, "emit_demo_frames": False, "with_expert": True, "demo_length": 10}


def test_a_run_scores_the_same_episodes_for_every_policy_and_repeats():
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        expert = run_one("train", "expert", "none", 4, ENV, seed=0, resamples=200, progress=False)
        assert torch.get_num_threads() == 2  # a run in-process leaves the caller's thread count as it was
    finally:
        torch.set_num_threads(threads)
    again = run_one("train", "expert", "none", 4, ENV, seed=0, resamples=200, progress=False)
    replay = run_one("train", "open_loop", "paper", 4, ENV, seed=0, resamples=200, progress=False)
    assert expert["episodes"] == replay["episodes"] == 4
    assert expert["episode_seeds_checksum"] == replay["episode_seeds_checksum"]  # the same episodes
    assert {k: v for k, v in expert.items() if k != "seconds"} == {k: v for k, v in again.items() if k != "seconds"}
    assert expert["success"] == 1.0  # the noise-free expert reaches every route's end
    low, high = replay["success_ci95"]
    assert low <= replay["success"] <= high


def test_score_summarises_records_with_intervals():
    records = [
        {"success": s, "spl": 0.9 * s, "steps": 10, "goal_distance": 0.5, "path_length": 3.0, "shortest_path_length": 2.7,
         "ndtw": 0.2 + 0.4 * s, "path_length_ratio": 1.0 + 0.2 * s}
        for s in (1, 0, 1, 1)
    ]
    row = score(records, seed=0, resamples=500)
    assert row["episodes"] == 4 and row["success"] == 0.75 and math.isclose(row["spl"], 0.675)
    assert row["success_ci95"][0] <= 0.75 <= row["success_ci95"][1]
    assert row["mean_path_length_m"] == 3.0
    assert math.isclose(row["ndtw"], 0.5) and math.isclose(row["mean_path_length_ratio"], 1.15)


def test_an_unknown_policy_is_refused_before_any_work():
    with pytest.raises(ValueError, match=r"policy_name must be one of \('expert', 'open_loop'\), got 'random'"):
        run_one("train", "random", "none", 4, ENV, seed=0, resamples=200, progress=False)




@pytest.mark.parametrize(
    "args, message",
    [
        (["--route-style", "bogus"], "route_style must be one of 'planner', 'tour', 'driven', got 'bogus'."),
        (["--route-style", "driven", "--route-lengths", "10", "40"], "route_lengths"),
        (["--expert", "shortest"], "argument --expert: invalid choice: 'shortest'"),
    ],
)
def test_expert_stats_refuses_bad_route_options_before_any_work(tmp_path, args, message, run_recipe):
    out = tmp_path / "stats.json"
    status, stderr = run_recipe("expert_stats", [*args, "--output", str(out)])
    assert status == 2 and message in stderr and not out.exists()


def test_expert_stats_scores_an_expert_on_a_route_style(tmp_path, run_recipe):
    out = tmp_path / "stats.json"
    args = ["--splits", "test", "--demo-length", "20", "--route-style", "driven", "--route-lengths", "10", "20",
            "--expert", "route", "--runs", "expert:none", "--episodes", "2", "--num-agents", "2", "--resamples", "50"]
    assert run_recipe("expert_stats", [*args, "--output", str(out)])[0] == 0
    content = json.loads(out.read_text())
    assert content["setup"]["expert"] == "route" and content["setup"]["route_lengths"] == [10, 20]
    row = content["results"][0]
    assert row["success"] == 1.0 and row["ndtw"] > 0.8  # noise-free, the route expert replays the route
