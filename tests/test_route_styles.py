"""Route styles (envs.route_styles): exact lengths, determinism, taught-route checks, the expert, statistics, mixtures."""
from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from torchrl.envs import TransformedEnv

import envs.route_styles as route_styles
from envs.demos import apply_motion, default_min_route_length_m, drive_expert, nominal_motion, sample_demonstration
from envs.episodes import run_episodes
from envs.expert import FORWARD, FORWARD_STEP_M, TURN_LEFT, TURN_RIGHT, WALL_CONTACT_TOLERANCE_M
from envs.follow import SUCCESS_RADIUS_M, default_max_steps
from envs.house_grid import MAX_DEMO_LENGTH, default_grid_size_cells
from envs.nav_env import PathFollowEnv
from envs.route_styles import (
    DRIVEN,
    PLANNER,
    ROUTE_STYLES,
    TOUR,
    TURN_AROUND_STEPS,
    DrivenStyle,
    RouteMixture,
    parse_route_style,
    sample_route,
)
from envs.scenes import build_house, split_seeds
from envs.scripted import ExpertPolicy
from envs.transforms import ActuationNoise
from envs.user_demos import MIN_USER_ROUTE_M, demonstration_from_actions

STYLES = tuple(ROUTE_STYLES)
LENGTHS = (10, 30, 100)
#: Routes per (style, length) in the property tests: two houses x two seeds.
HOUSES_PER_LENGTH = 2
SEEDS = (0, 1)
#: Routes of the statistics tests (default-grid train houses, 30 steps).
STATISTICS_ROUTES = 40
STATISTICS_LENGTH = 30


def houses(length: int) -> list[int]:
    """Train houses of the grid routes of ``length`` steps are sampled in (51 cells for 100 steps)."""
    return split_seeds("train", HOUSES_PER_LENGTH, grid_size_cells=default_grid_size_cells(length))


@functools.lru_cache(maxsize=None)
def route(style: str, house_seed: int, length: int, seed: int):
    return sample_route(style, build_house(house_seed), np.random.default_rng(seed), length)


def routes(style: str, length: int) -> list:
    return [route(style, house_seed, length, seed) for house_seed in houses(length) for seed in SEEDS]


def start_degrees(demo) -> tuple[float, float, float]:
    x, y, heading = demo.start_pose
    return float(x), float(y), math.degrees(float(heading))


def turn_arounds(actions: np.ndarray) -> bool:
    """Whether ``actions`` hold a turn-around: 180 degrees of turns to one side in a row."""
    letters = "".join("FLR"[a] for a in actions.tolist())
    return "L" * TURN_AROUND_STEPS in letters or "R" * TURN_AROUND_STEPS in letters


def path_length_m(demo) -> float:
    return float(np.hypot(*np.diff(demo.poses[:, :2], axis=0).T).sum())


def revisits(demo, radius_m: float = FORWARD_STEP_M, away_m: float = 2.0) -> bool:
    """Whether the route comes back within ``radius_m`` of a place it drove more than ``away_m`` before."""
    xy = demo.poses[:, :2]
    travelled = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    close = np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1)) < radius_m
    return bool((close & (travelled[:, None] - travelled[None] > away_m)).any())


@pytest.mark.parametrize("length", LENGTHS)
@pytest.mark.parametrize("style", STYLES)
def test_routes_have_exactly_length_actions(style, length):
    for house_seed, demo in zip([h for h in houses(length) for _ in SEEDS], routes(style, length)):
        assert demo.actions.shape == (length,) and demo.actions.dtype == np.int64
        assert demo.poses.shape == (length + 1, 3)
        assert demo.house_seed == house_seed and demo.task == "follow"
        assert set(demo.actions.tolist()) <= {FORWARD, TURN_LEFT, TURN_RIGHT}


@pytest.mark.parametrize("style", STYLES)
def test_same_seed_same_route_other_seed_other_route(style):
    house = build_house(houses(30)[0])
    first, again, other = (sample_route(style, house, np.random.default_rng(seed), 30) for seed in (5, 5, 6))
    assert np.array_equal(first.poses, again.poses) and np.array_equal(first.actions, again.actions)
    assert first.shortest_length_m == again.shortest_length_m
    assert not np.array_equal(first.poses, other.poses)


@pytest.mark.parametrize("length", LENGTHS)
@pytest.mark.parametrize("style", STYLES)
def test_noise_free_replay_reproduces_the_poses(style, length):
    for demo in routes(style, length):
        house = build_house(demo.house_seed)
        pose = demo.start_pose[None]
        for step, action in enumerate(demo.actions):
            pose, _ = apply_motion(house, pose, nominal_motion(action[None]))
            np.testing.assert_allclose(pose[0], demo.poses[step + 1], atol=1e-9, err_msg=f"step {step + 1}")


@pytest.mark.parametrize("length", LENGTHS)
@pytest.mark.parametrize("style", STYLES)
def test_routes_pass_the_checks_of_a_taught_route(style, length):
    for demo in routes(style, length):
        taught = demonstration_from_actions(demo.house_seed, start_degrees(demo), demo.actions, length=length)
        np.testing.assert_allclose(taught.poses, demo.poses, atol=1e-9)
        assert taught.shortest_length_m == pytest.approx(demo.shortest_length_m)


def test_planner_routes_are_todays_routes():
    # exactly sample_demonstration's routes for the same rng (what episodes play today) ...
    for length in LENGTHS:
        house = build_house(houses(length)[0])
        demo = sample_route(PLANNER, house, np.random.default_rng(3), length)
        today = sample_demonstration(house, np.random.default_rng(3), length, default_min_route_length_m(length))
        assert np.array_equal(demo.poses, today.poses) and np.array_equal(demo.actions, today.actions)
    # ... which may glance along a wall (a forward step shortened by up to 0.13 m), as a taught
    # route may (WALL_CONTACT_TOLERANCE_M), but never run into one
    for seed in range(STATISTICS_ROUTES):
        demo = route(PLANNER, split_seeds("train")[seed % 4], STATISTICS_LENGTH, seed)
        steps = np.hypot(*np.diff(demo.poses[:, :2], axis=0).T)[demo.actions == FORWARD]
        assert FORWARD_STEP_M - steps.min() <= WALL_CONTACT_TOLERANCE_M


@pytest.mark.parametrize("length", LENGTHS)
@pytest.mark.parametrize("style", STYLES)
def test_the_noise_free_expert_reaches_the_end(style, length):
    for demo in routes(style, length):
        house = build_house(demo.house_seed)
        poses, _ = drive_expert(house, demo.end_field, demo.start_pose, default_max_steps(length), SUCCESS_RADIUS_M)
        assert demo.end_field.at(poses[-1, :2]) <= SUCCESS_RADIUS_M


def test_the_expert_follows_every_style_under_paper_noise():
    """As tests/test_expert.py: the privileged expert in the env, under the paper's actuation noise."""
    per_style = 8
    seeds = split_seeds("train")[:4]
    demos = [route(style, seeds[i % 4], STATISTICS_LENGTH, i) for style in STYLES for i in range(per_style)]
    env = TransformedEnv(
        PathFollowEnv(
            house_seeds=seeds,
            demo_length=STATISTICS_LENGTH,
            num_agents=len(demos),
            with_expert=True,
            render=False,
            emit_demo_frames=False,
            demonstrations=demos,
        ),
        ActuationNoise("paper"),
    )
    env.set_seed(0)
    records = run_episodes(env, ExpertPolicy(), len(demos))
    env.close()
    success = np.array([r["success"] for r in records], dtype=float).reshape(len(STYLES), per_style)
    assert [r["house_seed"] for r in records] == [d.house_seed for d in demos]  # each plays its route
    assert (success.mean(axis=1) >= 7 / 8).all(), dict(zip(STYLES, success.mean(axis=1)))


def statistics_routes(style: str) -> list:
    train = split_seeds("train")
    return [route(style, train[seed % 8], STATISTICS_LENGTH, 100 + seed) for seed in range(STATISTICS_ROUTES)]


def test_driven_routes_drive_like_people():
    driven = statistics_routes(DRIVEN)
    turns = np.mean([np.mean(d.actions != FORWARD) for d in driven])
    assert 0.45 <= turns <= 0.7
    turned_around = np.mean([turn_arounds(d.actions) for d in driven])
    assert turned_around >= 0.2
    ends = np.array([d.shortest_length_m for d in driven])
    assert np.mean(ends < 2.5) >= 0.2 and ends.min() > MIN_USER_ROUTE_M
    # the planner's shortest routes turn less, and turn around only where they start facing away
    planned = statistics_routes(PLANNER)
    assert turns > np.mean([np.mean(d.actions != FORWARD) for d in planned])
    assert turned_around > np.mean([turn_arounds(d.actions) for d in planned]) + 0.1


def test_long_driven_routes_come_back_to_places():
    long_routes = [route(DRIVEN, house_seed, 100, seed) for house_seed in houses(100) for seed in range(100, 108)]
    assert 0.45 <= np.mean([np.mean(d.actions != FORWARD) for d in long_routes]) <= 0.7
    assert np.mean([revisits(d) for d in long_routes]) >= 0.5
    assert np.mean([d.shortest_length_m < 2.5 for d in long_routes]) >= 0.1
    assert not any(revisits(d) for d in routes(PLANNER, 100))


def test_driven_routes_turn_in_open_space():
    """Not every turn is forced: many turns follow a forward step that was free."""
    house = build_house(split_seeds("train")[0])
    free_before_turn = []
    for seed in range(10):
        demo = sample_route(DRIVEN, house, np.random.default_rng(seed), STATISTICS_LENGTH)
        for step in range(1, demo.length):
            if demo.actions[step - 1] == FORWARD and demo.actions[step] != FORWARD:
                _, travelled = apply_motion(house, demo.poses[step][None], nominal_motion(np.array([FORWARD])))
                free_before_turn.append(travelled[0] >= FORWARD_STEP_M - DrivenStyle().glance_m)
    assert len(free_before_turn) >= 20 and np.mean(free_before_turn) >= 0.5


def test_tours_bend():
    tours = statistics_routes(TOUR)
    ratio = np.mean([path_length_m(d) / d.shortest_length_m for d in tours])
    planned = np.mean([path_length_m(d) / d.shortest_length_m for d in statistics_routes(PLANNER)])
    assert ratio > 1.2 and ratio > planned + 0.2


def test_mixture_draws_styles_by_weight_and_lengths_in_bounds():
    mixture = RouteMixture({PLANNER: 0.5, TOUR: 0.25, DRIVEN: 0.25}, min_length=10, max_length=13)
    rng = np.random.default_rng(0)
    house = build_house(0)
    draws = [mixture.sample(house, rng) for _ in range(120)]
    styles = [style for style, _ in draws]
    for style, weight in mixture.probabilities.items():
        assert abs(styles.count(style) / len(draws) - weight) < 0.12, style
    assert {demo.length for _, demo in draws} == {10, 11, 12, 13}
    again = RouteMixture({PLANNER: 0.5, TOUR: 0.25, DRIVEN: 0.25}, 10, 13).sample(house, np.random.default_rng(0))
    assert again[0] == draws[0][0] and np.array_equal(again[1].actions, draws[0][1].actions)


def test_parse_route_style_round_trips():
    as_string = parse_route_style("planner=0.5, tour=0.25,driven=0.25")
    as_mapping = parse_route_style({"driven": 0.25, "planner": 0.5, "tour": 0.25})
    assert as_string == as_mapping and hash(as_string) == hash(as_mapping)
    assert parse_route_style(as_string.spec) == as_string and parse_route_style(as_string) is as_string
    assert as_string.probabilities == {PLANNER: 0.5, TOUR: 0.25, DRIVEN: 0.25}
    assert parse_route_style("driven").probabilities == {DRIVEN: 1.0}
    fixed = parse_route_style("planner", min_length=30, max_length=30)
    assert (fixed.min_length, fixed.max_length) == (30, 30)
    assert fixed.sample(0, np.random.default_rng(0))[1].length == 30


@pytest.mark.parametrize(
    "call, message",
    [
        (lambda h, r: sample_route("zigzag", h, r, 30), r"style must be one of 'planner', 'tour', 'driven', got 'zigzag'"),
        (lambda h, r: sample_route(DRIVEN, h, r, 9), r"length must be an int in \[10, 100\] \(steps\), got 9"),
        (lambda h, r: sample_route(DRIVEN, h, r, 101), r"length must be an int in \[10, 100\]"),
        (lambda h, r: sample_route(TOUR, h, r, MAX_DEMO_LENGTH), r"length must be an int in \[10, 100\]"),
        (lambda h, r: sample_route(PLANNER, h, r, 30.0), r"length must be an int"),
        (lambda h, r: sample_route(PLANNER, h, r, True), r"length must be an int"),
        (lambda h, r: sample_route(DRIVEN, h, 0, 30), r"rng must be a numpy.random.Generator"),
        (lambda h, r: ROUTE_STYLES[TOUR](h, np.random.RandomState(0), 30), r"rng must be a numpy.random.Generator"),
        (lambda h, r: ROUTE_STYLES[DRIVEN](h, r, 5), r"length must be an int in \[10, 100\]"),
        (lambda h, r: sample_route(DRIVEN, "house", r, 30), r"house must be an envs.scenes.House or a house seed"),
        (lambda h, r: RouteMixture({PLANNER: 1.0}).sample(h, 7), r"rng must be a numpy.random.Generator"),
        (lambda h, r: RouteMixture({"walk": 1.0}), r"weights key 'walk': a style must be one of 'planner', 'tour', 'driven'"),
        (lambda h, r: RouteMixture({PLANNER: -0.5, DRIVEN: 1.0}), r"weights\['planner'\] must be a finite number >= 0, got -0.5"),
        (lambda h, r: RouteMixture({PLANNER: 0.0, DRIVEN: 0.0}), r"weights must sum to more than 0"),
        (lambda h, r: RouteMixture({PLANNER: float("nan")}), r"weights\['planner'\] must be a finite number"),
        (lambda h, r: RouteMixture({}), r"weights must be a non-empty mapping"),
        (lambda h, r: RouteMixture({PLANNER: 1.0}, min_length=5), r"min_length must be an int in \[10, 100\]"),
        (lambda h, r: RouteMixture({PLANNER: 1.0}, max_length=200), r"max_length must be an int in \[10, 100\]"),
        (lambda h, r: RouteMixture({PLANNER: 1.0}, 40, 30), r"min_length must be at most max_length \(30\), got 40"),
        (lambda h, r: parse_route_style("walk"), r"route_style must be one of 'planner', 'tour', 'driven', got 'walk'"),
        (lambda h, r: parse_route_style("planner=0.5,walk=0.5"), r"route_style must be one of 'planner', 'tour', 'driven'"),
        (lambda h, r: parse_route_style("planner=half"), r"route_style must be a style \(one of 'planner', 'tour', 'driven'\) or"),
        (lambda h, r: parse_route_style("planner=1,planner=2"), r"route_style names 'planner' twice"),
        (lambda h, r: parse_route_style("planner=-1"), r"weights\['planner'\] must be a finite number >= 0"),
        (lambda h, r: parse_route_style(3), r"route_style must be a style name, a mapping"),
        (lambda h, r: DrivenStyle(wander_prob=1.5), r"wander_prob must be a probability in \[0, 1\], got 1.5"),
        (lambda h, r: DrivenStyle(turn_steps=(2, 12)), r"turn_steps must be \(low, high\) with 1 <= low <= high <= 9"),
        (lambda h, r: ROUTE_STYLES[DRIVEN](h, r, 30, style="fast"), r"style must be a DrivenStyle"),
    ],
)
def test_bad_inputs_raise_before_any_work(monkeypatch, call, message):
    def no_work(*args, **kwargs):
        raise AssertionError("work started before the arguments were checked")

    for name in ("house_of", "sample_demonstration", "_route_candidates", "demonstration_from_waypoints", "RouteRecorder"):
        monkeypatch.setattr(route_styles, name, no_work)
    with pytest.raises(ValueError, match=message):
        call(0, np.random.default_rng(0))
