"""spf_rl.eval.pointer_trace and recipes/pointer_trace.py: the pointer against the agent's place on the route."""
from __future__ import annotations

import numpy as np
import pytest

from spf_rl.eval.pointer_trace import OFF_PATH_M, Trace, distance_to_path, summarize_traces, trace_routes
from spf_rl.modules import SPFConfig, SPFPolicy


def tiny_policy(pointer_update: str = "rpf") -> SPFPolicy:
    config = SPFConfig(demo_length=20, sparsity=1.0, feature_dim=16, hidden_size=16, image_size=(32, 32), pointer_update=pointer_update)
    return SPFPolicy(config).eval()


def test_distance_to_a_path_of_repeated_points_and_of_one_point():
    path = np.array([[0.0, 0.0], [0.0, 0.0], [2.0, 0.0], [2.0, 0.0]])
    assert distance_to_path(np.array([1.0, -0.5]), path) == pytest.approx(0.5)
    assert distance_to_path(np.array([3.0, 4.0]), path[:1]) == pytest.approx(5.0)


def test_traces_of_a_policy_on_driven_routes():
    traces = trace_routes(tiny_policy(), style="driven", route_lengths=(10, 20), episodes=3, seed=0)
    assert len(traces) == 3
    for trace in traces:
        steps, n = len(trace.pointer), trace.record["demo_steps"]
        assert 10 <= n <= 20 and trace.route_step.shape == trace.off_path_m.shape == (steps,)
        assert trace.record["steps"] == steps  # one entry per step of the episode
        assert (trace.pointer >= 0).all() and (trace.pointer <= n - 1 + 1e-6).all()  # RPF's rule caps it at n_i - 1
        assert (np.diff(trace.route_step) >= 0).all() and (trace.route_step <= n).all()
        assert trace.off_path_m[0] == pytest.approx(0.0, abs=1e-5) and (trace.off_path_m >= 0).all()
        far = trace.left_path_at
        assert far is None or (trace.off_path_m[far] > OFF_PATH_M and (trace.off_path_m[:far] <= OFF_PATH_M).all())
    again = trace_routes(tiny_policy(), style="driven", route_lengths=(10, 20), episodes=3, seed=0)
    assert [t.record["episode_seed"] for t in again] == [t.record["episode_seed"] for t in traces]


def test_an_anchored_policy_traces_its_anchor_in_a_changed_world():
    import dataclasses

    from spf_rl.modules.registry import build_policy

    policy = tiny_policy()
    grown = build_policy("spf", dataclasses.replace(policy.config, anchor_radius=4)).eval()
    grown.load_state_dict(policy.state_dict(), strict=False)
    traces = trace_routes(grown, style="driven", route_lengths=(10, 20), episodes=2, seed=0, conditions="light@1", memory_mismatch=1.0)
    for trace in traces:
        assert trace.anchor.shape == trace.anchor_confidence.shape == trace.pointer.shape
        assert (np.abs(trace.anchor - trace.pointer) <= 4 + 1e-5).all() and (np.abs(trace.anchor_confidence) <= 1 + 1e-5).all()
    summary = summarize_traces(traces, window=2)
    assert any("mean_abs_anchor_error" in summary[outcome] for outcome in ("success", "failure") if summary[outcome]["episodes"])
    assert trace_routes(policy, style="driven", route_lengths=(10, 20), episodes=1, seed=0)[0].anchor is None
    assert traces[0].replay_opening is None and "mean_replay_opening" not in summary["failure"]


def test_a_gated_policy_traces_the_gates_opening_and_an_open_gate_replays():
    """The replay gate's opening is traced; wide open, the pointer moves one route step per step, as blind replay."""
    import dataclasses

    import torch

    from spf_rl.modules.registry import build_policy

    policy = tiny_policy()
    gated = build_policy("spf", dataclasses.replace(policy.config, anchor_radius=4, replay_gate=True)).eval()
    gated.load_state_dict(policy.state_dict(), strict=False)
    shut = trace_routes(gated, style="driven", route_lengths=(10, 20), episodes=2, seed=0, memory_mismatch=1.0)
    assert all(np.allclose(t.replay_opening, 1 / (1 + np.exp(4.0)), atol=1e-6) for t in shut)  # weights 0: its first opening
    assert summarize_traces(shut, window=2)[("success" if shut[0].record["success"] else "failure")]["mean_replay_opening"] > 0
    with torch.no_grad():
        gated.cell.replay_gate.bias.fill_(50.0)
    for trace in trace_routes(gated, style="driven", route_lengths=(10, 20), episodes=2, seed=0, memory_mismatch=1.0):
        n = trace.record["demo_steps"]
        assert np.allclose(trace.replay_opening, 1.0) and np.array_equal(trace.pointer, np.minimum(np.arange(len(trace.pointer)), n - 1))


def test_a_policy_without_rpfs_pointer_rule_is_refused():
    with pytest.raises(ValueError, match="pointer_update == 'rpf'"):
        trace_routes(tiny_policy("paper"), style="driven", route_lengths=(10, 20), episodes=1)


def test_failures_that_stay_on_the_path_are_counted_apart():
    slow = Trace({"success": False, "demo_steps": 10}, np.arange(4.0), np.arange(4), np.full(4, 0.1))
    out = summarize_traces([slow], window=2)["failure"]
    assert out["left_path"] == 0.0 and out["pointer_error_at_leaving"] is None
    assert summarize_traces([slow], window=2)["success"]["episodes"] == 0


@pytest.mark.parametrize(
    "args, message",
    [
        (["--checkpoint", "spf-s0.8", "--styles", "zigzag"], "--styles"),
        (["--checkpoint", "spf-s0.8"], "pointer_update == 'rpf'"),
        (["--checkpoint", "spf_rpf_pointer-s0.8", "--route-lengths", "10", "30", "--sparsity", "0.4"], "--sparsity is for random-sparsity models"),
        (["--checkpoint", "spf_rpf_pointer-s0.8", "--route-lengths", "10", "100"], "route_lengths"),
        (["--checkpoint", "spf_rpf_pointer-s0.8", "--route-lengths", "10", "30", "--episodes", "0"], "--episodes must be a positive int"),
        (["--checkpoint", "spf_rpf_pointer-s0.8", "--route-lengths", "10", "30", "--conditions", "fog@1"], "--conditions: unknown condition 'fog'"),
        (["--checkpoint", "spf_rpf_pointer-s0.8", "--route-lengths", "10", "30", "--memory-mismatch", "2"], "--memory-mismatch must be a number in [0, 1]"),
    ],
)
def test_the_recipe_refuses_bad_options_before_any_work(tmp_path, args, message, run_recipe):
    out = tmp_path / "trace.json"
    status, stderr = run_recipe("pointer_trace", [*args, "--out", str(out)])
    assert status == 2 and message in stderr and not out.exists()
