"""Path-fidelity metrics (envs.path_fidelity): DTW against a naive DP, hand-computed nDTW, SDTW,
path-length ratio and wall hits, and a ValueError naming the parameter for every bad input."""
from __future__ import annotations

import math

import numpy as np
import pytest

from envs.demos import apply_motion, nominal_motion
from envs.expert import FORWARD, FORWARD_STEP_M, WALL_CONTACT_TOLERANCE_M
from envs.path_fidelity import (
    MIN_REFERENCE_LENGTH_M,
    PATH_FIDELITY_KEYS,
    drop_repeats,
    dtw_distance,
    ndtw,
    path_fidelity,
    path_length,
    path_length_ratio,
    sdtw,
    wall_hits,
)
from envs.scenes import build_house

#: The follow protocol's success radius (envs.follow.SUCCESS_RADIUS_M), the threshold callers pass.
THRESHOLD_M = 0.6
#: A 3-point straight reference, 1 m between points.
LINE = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])


def naive_dtw(path_xy: np.ndarray, reference_xy: np.ndarray) -> float:
    """Textbook DTW: the double loop over an (N+1) x (M+1) table padded with infinity."""
    n, m = len(path_xy), len(reference_xy)
    table = np.full((n + 1, m + 1), np.inf)
    table[0, 0] = 0.0
    for i in range(1, n + 1):
        for j in range(1, m + 1):
            cost = math.dist(path_xy[i - 1], reference_xy[j - 1])
            table[i, j] = cost + min(table[i - 1, j], table[i, j - 1], table[i - 1, j - 1])
    return float(table[n, m])


def l_route(spacing_m: float = FORWARD_STEP_M) -> np.ndarray:
    """(0, 0) -> (3, 0) -> (3, 3) sampled every ``spacing_m``: 21 points for 0.3 m."""
    count = round(3.0 / spacing_m)
    leg = spacing_m * np.arange(count + 1)
    return np.concatenate([np.stack([leg, np.zeros_like(leg)], axis=1), np.stack([np.full(count, 3.0), leg[1:]], axis=1)])


@pytest.mark.parametrize("n, m", [(1, 1), (1, 6), (6, 1), (2, 3), (7, 4), (4, 7), (20, 31), (31, 20), (40, 40)])
def test_dtw_equals_the_naive_double_loop(n, m):
    rng = np.random.default_rng(1000 * n + m)
    for _ in range(3):
        path = rng.uniform(-5.0, 5.0, size=(n, 2))
        reference = np.cumsum(rng.normal(0.0, 0.3, size=(m, 2)), axis=0)
        expected = naive_dtw(path, reference)
        np.testing.assert_allclose(dtw_distance(path, reference), expected, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(dtw_distance(reference, path), expected, rtol=1e-12, atol=1e-12)  # symmetric


def test_identical_paths_give_dtw_0_and_ndtw_1():
    route = l_route()
    assert dtw_distance(route, route) == 0.0
    assert ndtw(route, route, THRESHOLD_M) == 1.0
    nudged = route.copy()
    nudged[10, 1] += 0.01  # one point 1 cm off: no longer a point-by-point match
    assert ndtw(nudged, route, THRESHOLD_M) < 1.0


def test_constant_offset_of_0_3_m_from_a_3_point_reference():
    offset = LINE + [0.0, 0.3]
    assert dtw_distance(offset, LINE) == pytest.approx(0.9, abs=1e-12)  # 3 matched pairs, 0.3 m each
    assert ndtw(offset, LINE, THRESHOLD_M) == pytest.approx(math.exp(-0.9 / (3 * 0.6)), rel=1e-12)
    assert ndtw(offset, LINE, 2 * THRESHOLD_M) == pytest.approx(math.exp(-0.9 / (3 * 1.2)), rel=1e-12)


def test_waiting_on_the_spot_costs_nothing():
    waits = LINE[[0, 0, 0, 1, 1, 2, 2, 2, 2]]
    assert dtw_distance(waits, LINE) == pytest.approx(0.0, abs=1e-12)
    assert ndtw(waits, LINE, THRESHOLD_M) == pytest.approx(1.0, abs=1e-12)
    # a point-by-point (no warping) comparison would have charged the waits: 0 + 1 + 2 m at least
    assert naive_dtw(waits, LINE) == pytest.approx(0.0, abs=1e-12)


def test_a_shortcut_succeeds_on_a_shorter_path_and_scores_a_low_ndtw():
    route = l_route()
    assert len(route) == 21
    assert path_length(route) == pytest.approx(6.0)
    # the agent drives 0.3 m forward steps straight along the diagonal, then the last bit to (3, 3)
    direction = np.array([1.0, 1.0]) / math.sqrt(2.0)
    shortcut = np.concatenate([FORWARD_STEP_M * np.arange(15)[:, None] * direction, [[3.0, 3.0]]])
    success = math.dist(shortcut[-1], route[-1]) <= THRESHOLD_M
    assert success

    assert path_length_ratio(shortcut, route) == pytest.approx(3.0 * math.sqrt(2.0) / 6.0, rel=1e-12)
    distance = dtw_distance(shortcut, route)
    assert distance == pytest.approx(naive_dtw(shortcut, route), rel=1e-12)
    # every reference point is matched at least once, so DTW >= the sum of each one's distance to the
    # nearest path point; that bound alone puts nDTW below 0.5 (DTW > 21 * 0.6 * ln 2 = 8.73 m)
    nearest = np.hypot(*(route[:, None, :] - shortcut[None, :, :]).transpose(2, 0, 1)).min(axis=1)
    assert nearest.sum() > 21 * THRESHOLD_M * math.log(2.0)
    assert distance >= nearest.sum() - 1e-12
    assert distance == pytest.approx(21.3565, abs=1e-4)
    expected_ndtw = math.exp(-distance / (21 * THRESHOLD_M))
    assert expected_ndtw < 0.5
    assert ndtw(shortcut, route, THRESHOLD_M) == pytest.approx(expected_ndtw, rel=1e-12)

    scores = path_fidelity(shortcut, route, success=success, threshold_m=THRESHOLD_M)
    assert tuple(scores) == PATH_FIDELITY_KEYS
    assert scores["ndtw"] == pytest.approx(expected_ndtw, rel=1e-12)
    assert scores["sdtw"] == pytest.approx(expected_ndtw, rel=1e-12)
    assert scores["path_length_ratio"] < 1.0
    # the agent that follows the L (with a turn on the spot at the corner) scores 1 on everything
    faithful = np.concatenate([route[:11], route[10:11], route[10:]])
    assert path_fidelity(faithful, route, success=True, threshold_m=THRESHOLD_M) == {"ndtw": 1.0, "sdtw": 1.0, "path_length_ratio": 1.0}


def test_sdtw_is_0_without_success_on_scalars_and_arrays():
    assert sdtw(False, 0.9) == 0.0
    assert sdtw(True, 0.9) == 0.9
    assert sdtw(np.True_, 0.25) == 0.25
    assert isinstance(sdtw(True, 0.9), float)
    values = sdtw(np.array([True, False, True, False]), np.array([0.2, 0.9, 1.0, 0.0]))
    np.testing.assert_array_equal(values, [0.2, 0.0, 1.0, 0.0])
    np.testing.assert_array_equal(sdtw(np.array([1, 0]), 0.5), [0.5, 0.0])  # 1/0 and broadcasting
    scores = path_fidelity(LINE + [0.0, 0.3], LINE, success=False, threshold_m=THRESHOLD_M)
    assert scores["sdtw"] == 0.0
    assert scores["ndtw"] == pytest.approx(math.exp(-0.5))


def test_path_length_and_ratio():
    assert path_length(np.array([[0.0, 0.0], [3.0, 0.0], [3.0, 4.0]])) == 7.0
    assert path_length(np.array([[0.0, 0.0], [3.0, 4.0], [0.0, 0.0]])) == 10.0  # there and back
    assert path_length(np.array([[1.0, 1.0]])) == 0.0
    detour = np.array([[0.0, 0.0], [0.0, 1.0], [2.0, 1.0], [2.0, 0.0]])
    assert path_length_ratio(detour, LINE) == pytest.approx(2.0)
    assert path_length_ratio(LINE[:1], LINE) == 0.0  # never moved


def test_a_reference_that_does_not_move_is_refused():
    still = np.array([[1.0, 1.0], [1.0, 1.0], [1.0, 1.0 + MIN_REFERENCE_LENGTH_M / 10]])
    with pytest.raises(ValueError, match="reference_xy .*MIN_REFERENCE_LENGTH_M"):
        path_length_ratio(LINE, still)
    with pytest.raises(ValueError, match="reference_xy"):
        path_fidelity(LINE, still[:2], success=True, threshold_m=THRESHOLD_M)
    assert math.isfinite(path_length_ratio(LINE, np.array([[0.0, 0.0], [0.0, 10 * MIN_REFERENCE_LENGTH_M]])))


def test_path_fidelity_drops_turns_on_the_spot():
    # turns repeat a position; dropping them keeps nDTW's normalisation at the route's moving points
    with_turns = LINE[[0, 0, 0, 1, 2, 2]]
    bent = LINE.copy()
    bent[1, 1] = 0.6  # the middle point 0.6 m off the route: DTW 0.6 m
    assert drop_repeats(with_turns).tolist() == LINE.tolist()
    expected = path_fidelity(bent, LINE, success=True, threshold_m=THRESHOLD_M)
    assert expected["ndtw"] == pytest.approx(math.exp(-0.6 / (3 * 0.6)), rel=1e-12)
    assert path_fidelity(bent[[0, 1, 1, 2]], with_turns, success=True, threshold_m=THRESHOLD_M) == expected
    # without dropping, the 6 reference points would dilute the same 0.6 m
    assert ndtw(bent, with_turns, THRESHOLD_M) == pytest.approx(math.exp(-0.6 / (6 * 0.6)), rel=1e-12)
    # a return to an earlier point is not a repeat
    assert len(drop_repeats(LINE[[0, 1, 0]])) == 3


def test_wall_hits_counts_steps_cut_short_by_more_than_the_tolerance():
    requested = np.array([0.3, 0.3, 0.3, 0.0, 0.3, 0.3])
    moved = np.array([0.3, 0.0, 0.26, 0.0, 0.24, 0.1])
    assert wall_hits(requested, moved) == 2  # 0.0 and 0.1 m; 0.04 and 0.06 m glances and a turn do not count
    assert WALL_CONTACT_TOLERANCE_M == 0.15  # the default: half a step
    assert wall_hits(requested, moved, tolerance_m=0.05) == 3
    assert wall_hits(requested, moved, tolerance_m=0.25) == 1
    assert wall_hits(requested, moved, tolerance_m=0.01) == 4
    assert wall_hits(np.zeros(0), np.zeros(0)) == 0


def test_wall_hits_counts_a_simulated_step_into_a_wall():
    # a forward step into the wall at x = 7.2 (the envs.user_demos example) and a free one
    house = build_house(0)
    poses = np.array([[7.2, 1.5, math.pi], [7.5, 1.5, 0.0]])
    motion = nominal_motion(np.array([FORWARD, FORWARD]))
    _, travelled = apply_motion(house, poses, motion)
    assert wall_hits(np.hypot(motion[:, 0], motion[:, 1]), travelled) == 1


BAD_INPUTS = [
    (dtw_distance, (np.zeros((0, 2)), LINE), "path_xy"),
    (dtw_distance, (LINE, np.zeros((0, 2))), "reference_xy"),
    (dtw_distance, (np.zeros((3, 3)), LINE), "path_xy"),
    (dtw_distance, (LINE, np.zeros(4)), "reference_xy"),
    (dtw_distance, (LINE, [["a", "b"]]), "reference_xy"),
    (dtw_distance, (np.array([[0.0, np.nan]]), LINE), "path_xy"),
    (dtw_distance, (LINE, np.array([[0.0, np.inf]])), "reference_xy"),
    (ndtw, (LINE, LINE, 0.0), "threshold_m"),
    (ndtw, (LINE, LINE, -0.6), "threshold_m"),
    (ndtw, (LINE, LINE, math.nan), "threshold_m"),
    (ndtw, (LINE, LINE, math.inf), "threshold_m"),
    (ndtw, (LINE, LINE, True), "threshold_m"),
    (ndtw, (LINE, LINE, "0.6"), "threshold_m"),
    (ndtw, (np.zeros((2, 1)), LINE, 0.6), "path_xy"),
    (sdtw, (0.5, 0.9), "success"),
    (sdtw, ("yes", 0.9), "success"),
    (sdtw, (True, 1.5), "ndtw_value"),
    (sdtw, (True, -0.1), "ndtw_value"),
    (sdtw, (True, math.nan), "ndtw_value"),
    (sdtw, (np.array([True, False]), np.array([0.1, 0.2, 0.3])), "success and ndtw_value"),
    (path_length, (np.zeros((0, 2)),), "xy"),
    (path_length, (np.zeros((2, 2, 2)),), "xy"),
    (path_length_ratio, (np.zeros((1, 3)), LINE), "path_xy"),
    (path_length_ratio, (LINE, np.array([[1.0, 1.0]])), "reference_xy"),
    (wall_hits, (np.array([0.3]), np.array([0.3]), 0.0), "tolerance_m"),
    (wall_hits, (np.array([0.3]), np.array([0.3]), -0.05), "tolerance_m"),
    (wall_hits, (np.array([0.3, 0.3]), np.array([0.3])), "requested_m and moved_m"),
    (wall_hits, (np.array([[0.3]]), np.array([[0.3]])), "requested_m"),
    (wall_hits, (np.array([-0.3]), np.array([0.3])), "requested_m"),
    (wall_hits, (np.array([0.3]), np.array([np.nan])), "moved_m"),
    (path_fidelity, (LINE, LINE, np.array([True, False]), 0.6), "success"),
    (path_fidelity, (LINE, LINE, 2, 0.6), "success"),
    (path_fidelity, (LINE, LINE, True, 0.0), "threshold_m"),
    (path_fidelity, (LINE[:, :1], LINE, True, 0.6), "path_xy"),
    (path_fidelity, (LINE, LINE[:, :1], True, 0.6), "reference_xy"),
    (drop_repeats, (np.zeros((0, 2)),), "xy"),
]


@pytest.mark.parametrize("function, args, name", BAD_INPUTS, ids=[f"{f.__name__}-{i}" for i, (f, _, _) in enumerate(BAD_INPUTS)])
def test_bad_input_raises_a_value_error_naming_the_parameter(function, args, name):
    with pytest.raises(ValueError, match=rf"^{name} must"):
        function(*args)
