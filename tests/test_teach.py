"""recipes/teach.py: headless teach and repeat, input validation, the keyboard's key handling."""
from __future__ import annotations

import curses
import json
import re
from pathlib import Path

import numpy as np
import pytest
import teach

from envs import RouteRecorder, demonstration_from_actions, demonstration_from_waypoints
from envs.expert import FORWARD, TURN_LEFT
from envs.scenes import build_house
from spf_rl.teach.keyboard import NO_KEY, ascii_map, decode_escape, handle_key
from spf_rl.teach.repeat import DEFAULT_CHECKPOINT, DEFAULT_HOMING_CHECKPOINT, route_letters

HOUSE = "0"
START = "7.5,1.5,0"
#: 30 steps in house 0 from (7.5, 1.5) facing +x: along the corridor, then north up the x = 9 m column.
ROUTE = "FFFFFFLLLFLFLFFRFFLFFRFFLFFRFR"
WAYPOINTS = "7.5,1.5;9.5,1.5;9.5,5.5;12.5,5.5"


def headless(out: Path, *extra: str) -> list[str]:
    return ["--house", HOUSE, "--start", START, "--out", str(out), "--quiet", *extra]


@pytest.fixture(scope="session")
def taught(shared_build):
    """A headless run's directory and its teach.json, made once in the test session (read only)."""
    out = shared_build("teach", lambda directory: teach.main(headless(directory, "--actions", ROUTE, "--repeats", "4", "--seed", "3")))
    return out, json.loads((out / "teach.json").read_text())


def test_headless_run_writes_video_map_and_json(taught):
    out, content = taught
    files = sorted(p.name for p in out.iterdir())
    assert "teach.json" in files and "teach_map.png" in files
    assert ("teach.gif" in files) or ("teach.mp4" in files)
    assert content["files"]["video"] in files
    saved = json.loads((out / "teach.json").read_text())
    assert saved == json.loads(json.dumps(content))
    assert [r["repeat"] for r in saved["repeats"]] == [1, 2, 3, 4]
    for record in saved["repeats"]:
        assert isinstance(record["success"], bool) and 0.0 <= record["spl"] <= 1.0
        assert record["spl"] > 0 or not record["success"]
    assert saved["route"]["actions"] == ROUTE and saved["route"]["steps"] == 30
    assert saved["checkpoint"] == DEFAULT_CHECKPOINT and saved["noise"] == "paper"
    assert saved["summary"]["episodes"] == 4
    # four repeats under their own noise are not all the same path
    assert len({r["path_length"] for r in saved["repeats"]}) > 1


def test_the_video_is_an_mp4_where_the_codec_is_installed(taught):
    pytest.importorskip("imageio_ffmpeg", reason="the MP4 codec comes with the viz extra")
    import imageio.v2 as imageio

    out, content = taught
    video = out / content["files"]["video"]
    assert video.suffix == ".mp4"
    frames = imageio.mimread(video)
    # one frame per step of the longer of the demonstration (30 frames) and repeat 1 (steps + 1 frames)
    assert len(frames) == max(30, content["repeats"][0]["steps"] + 1)
    assert frames[0].ndim == 3 and frames[0].shape[2] == 3 and frames[0].std() > 0


def test_video_falls_back_to_gif_without_the_codec(tmp_path, monkeypatch):
    import importlib.util

    from spf_rl.viz import write_video

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "imageio_ffmpeg" else real(name, *a))
    frames = [np.full((16, 32, 3), 40 * i, np.uint8) for i in range(3)]
    path = write_video(frames, tmp_path / "clip.mp4")
    assert path.suffix == ".gif" and path.exists() and not (tmp_path / "clip.mp4").exists()


def test_same_seed_same_json(taught, tmp_path):
    _, first = taught
    again = teach.main(headless(tmp_path, "--actions", ROUTE, "--repeats", "4", "--seed", "3", "--no-video"))
    first = {k: v for k, v in first.items() if k != "files"}
    again = {k: v for k, v in again.items() if k != "files"}
    assert json.dumps(first) == json.dumps(again)


def test_homing_brings_the_route_back_to_its_start(tmp_path):
    content = teach.main(headless(tmp_path, "--actions", ROUTE, "--repeats", "2", "--seed", "3", "--no-video", "--homing"))
    route, home = content["route"], content["homing"]
    assert content["task"] == "homing" and content["max_steps"] == 50 and route["actions"] == ROUTE
    assert content["checkpoint"] == DEFAULT_HOMING_CHECKPOINT  # the homing policy brings routes home
    # the env's homing demonstration: from the route's end, facing back, to the route's start
    taught = demonstration_from_actions(0, (7.5, 1.5, 0.0), ROUTE)
    np.testing.assert_allclose(home["start"][:2], taught.poses[-1, :2])
    assert home["start"][2] == pytest.approx((np.degrees(taught.poses[-1, 2]) + 360) % 360 - 180)
    np.testing.assert_allclose(home["end_xy_m"], [7.5, 1.5])
    assert home["actions"] == "".join({"F": "F", "L": "R", "R": "L"}[c] for c in ROUTE[::-1])
    assert [r["repeat"] for r in content["repeats"]] == [1, 2] and (tmp_path / "teach_map.png").exists()
    again = teach.main(headless(tmp_path / "again", "--actions", ROUTE, "--repeats", "2", "--seed", "3", "--no-video", "--homing"))
    assert json.dumps({**content, "files": None}) == json.dumps({**again, "files": None})


def route_of(argv: list[str]):
    """The demonstration the CLI builds from ``argv`` (no repeats)."""
    parser = teach.build_parser()
    args = parser.parse_args(argv)
    _, demo, _, _ = teach.setup(parser, args)
    return demo


def test_waypoints_give_the_planned_route(tmp_path):
    demo = route_of(["--house", HOUSE, "--waypoints", WAYPOINTS, "--out", str(tmp_path)])
    points = [tuple(float(v) for v in p.split(",")) for p in WAYPOINTS.split(";")]
    planned = demonstration_from_waypoints(0, points)  # the whole plan: a route keeps its length
    assert demo.length == planned.length > 30 and demo.actions.tolist() == planned.actions.tolist()
    np.testing.assert_allclose(demo.poses, planned.poses)
    # the planned route, typed as --actions, is the same route
    assert route_letters(demo)[:30] == ROUTE
    typed = route_of(["--house", HOUSE, "--start", START, "--actions", route_letters(demo)])
    assert typed.poses.tolist() == demo.poses.tolist()
    # a route of another length than the policy's 30 steps is taught as it is (24 steps here)
    assert route_of(["--house", HOUSE, "--start", START, "--actions", ROUTE[:24]]).length == 24


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--actions", ROUTE, "--noise", "loud"], "--noise must be one of locobot, none, paper"),
        (["--actions", ROUTE, "--repeats", "0"], r"--repeats must be in \[1, 64\]"),
        (["--actions", ROUTE, "--checkpoint", "nope"], "--checkpoint: unknown checkpoint name 'nope'"),
        (["--actions", ROUTE, "--start", "7.5,1.5"], r"--start \(x m, y m, heading deg\): expected 3"),
        (["--actions", "FFQ"], "action 3 is 'Q'"),
        (["--waypoints", "7.5,1.5;9.5"], "--waypoints point 2: expected 2"),
        (["--actions", ROUTE, "--start", "16,1.5,0"], r"--start \(16\.00, 1\.50\) is outside the house"),
        (["--actions", ROUTE, "--start", "7.5,0.5,0"], r"--start \(7\.50, 0\.50\) is inside a wall"),
        (["--actions", "FFF" + ROUTE[3:], "--start", "7.5,1.5,180"], r"--actions: step 2 of 30 \(F, forward\) .* runs into a wall"),
        (["--actions", "LR" * 15], "--actions: the route is too short"),
        (["--actions", "F" * 198], "--actions: step 17 of 198 .* runs into a wall"),
        (["--waypoints", "7.5,1.5;20,1.5"], r"--waypoints: waypoint 2 \(20\.00, 1\.50\) is outside the house"),
        (["--actions", "LR" * 100], "--actions: the route has 200 steps; a taught route may have at most 198"),
        (["--actions", ROUTE, "--conditions", "dusk@1"], "--conditions: unknown condition 'dusk'; allowed names are none, light"),
        (["--actions", ROUTE, "--conditions", "light@2"], r"--conditions: the strength of 'light' must be a number in \[0, 1\], got 2.0"),
    ],
)
def test_bad_input_is_refused_before_any_work(argv, message, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        route_of(["--house", HOUSE, "--out", str(tmp_path / "out"), *argv])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert re.search(message, err), err
    assert not (tmp_path / "out").exists()


def test_keys_drive_undo_and_finish():
    recorder = RouteRecorder(0, (7.5, 1.5, 0.0), max_steps=30)
    assert handle_key(recorder, curses.KEY_UP, 30).message == ""
    assert recorder.actions.tolist() == [FORWARD]
    handle_key(recorder, curses.KEY_LEFT, 30)
    assert recorder.actions.tolist() == [FORWARD, TURN_LEFT]
    handle_key(recorder, curses.KEY_BACKSPACE, 30)
    assert recorder.length == 1
    assert handle_key(recorder, 10, 30).message.startswith("the route is too short")  # Enter on 0.3 m
    assert handle_key(recorder, ord("q"), 30).cancelled
    assert "unknown key" in handle_key(recorder, ord("z"), 30).message
    recorder.undo()
    for letter in ROUTE:
        outcome = handle_key(recorder, ord(letter.lower()), 30)
    assert "30 steps, the most a route may have: press Enter" in outcome.message
    assert "already has 30 steps" in handle_key(recorder, curses.KEY_UP, 30).message
    finished = handle_key(recorder, curses.KEY_ENTER, 30)
    assert finished.demonstration is not None
    expected = demonstration_from_actions(0, (7.5, 1.5, 0.0), ROUTE)
    assert finished.demonstration.poses.tolist() == expected.poses.tolist()


def test_keyboard_with_a_required_length_refuses_a_shorter_route():
    short = "FFLRFFLRFFRFFLFFFFFFRLRF"  # 24 steps, a valid route from this start
    recorder = RouteRecorder(0, (7.5, 1.5, 0.0), max_steps=30)
    for letter in short:
        handle_key(recorder, ord(letter.lower()), 30, exact=True)
    refused = handle_key(recorder, curses.KEY_ENTER, 30, exact=True)
    assert refused.demonstration is None and recorder.length == 24
    assert refused.message.startswith("the route has 24 steps; demonstrations must have exactly 30 steps")
    assert handle_key(recorder, curses.KEY_ENTER, 30).demonstration.length == 24  # without a required length


def test_raw_escape_arrows_are_decoded():
    assert decode_escape([ord("["), ord("A")]) == curses.KEY_UP
    assert decode_escape([ord("O"), ord("D")]) == curses.KEY_LEFT
    assert decode_escape([NO_KEY, NO_KEY]) == NO_KEY  # a lone Esc does nothing
    recorder = RouteRecorder(0, (7.5, 1.5, 0.0), max_steps=30)
    assert handle_key(recorder, NO_KEY, 30).message == "" and recorder.length == 0


def test_keys_refuse_a_wall_and_keep_the_route():
    recorder = RouteRecorder(0, (7.5, 1.5, 180.0), max_steps=30)
    handle_key(recorder, curses.KEY_UP, 30)
    outcome = handle_key(recorder, curses.KEY_UP, 30)
    assert "runs into a wall" in outcome.message and recorder.length == 1


def test_keys_too_short_route_is_not_finished():
    recorder = RouteRecorder(0, (7.5, 1.5, 0.0), max_steps=2)
    handle_key(recorder, curses.KEY_LEFT, 2)
    handle_key(recorder, curses.KEY_RIGHT, 2)
    outcome = handle_key(recorder, 13, 2)
    assert outcome.demonstration is None and "too short" in outcome.message


def test_ascii_map_shows_walls_route_and_agent():
    demo = demonstration_from_actions(0, (7.5, 1.5, 0.0), ROUTE)
    lines = ascii_map(build_house(0), demo.poses)
    assert len(lines) == 30 and all(len(line) == 30 for line in lines)
    assert lines[0] == "#" * 30  # the outer wall at the top
    text = "".join(lines)
    assert text.count("S") == 1 and "." in text
    assert sum(text.count(arrow) for arrow in "^/\\<>v") >= 1


def test_teach_refuses_an_unknown_device(tmp_path, capsys):
    import teach

    with pytest.raises(SystemExit):
        teach.main(["--actions", "F" * 30, "--device", "tpu", "--out", str(tmp_path)])
    assert "--device" in capsys.readouterr().err


def test_a_repeat_at_dusk_sees_the_changed_world_and_says_so(taught, tmp_path):
    _, plain = taught
    content = teach.main(headless(tmp_path, "--actions", ROUTE, "--repeats", "4", "--seed", "3", "--conditions", "light@1", "--no-video"))
    assert content["conditions"] == "light@1.0=1.0" and "conditions" not in plain
    assert content["route"] == plain["route"]  # the same taught route, repeated in another world
    assert (tmp_path / "teach_map.png").is_file()


def test_repeats_in_a_changed_world_keep_the_taught_memory(tmp_path):
    from spf_rl.hub import load_policy
    from spf_rl.teach.repeat import repeat_route

    demo = demonstration_from_actions(build_house(0), np.array([7.5, 1.5, 0.0]), ROUTE)
    policy, config = load_policy(DEFAULT_CHECKPOINT)
    repeats, demo_frames, _ = repeat_route(policy.eval(), demo, repeats=2, noise="paper", seed=1, max_steps=50,
                                           image_size=config.image_size[0], progress=False, demo_length=config.demo_length,
                                           conditions="furniture@1")
    assert all(r.house.seed == 0 and r.house is not build_house(0) for r in repeats)
    dusk, _, _ = repeat_route(policy.eval(), demo, repeats=1, noise="paper", seed=1, max_steps=5, image_size=config.image_size[0],
                              progress=False, demo_length=config.demo_length, conditions="light@1")
    assert dusk[0].frames[0].mean() < 0.8 * demo_frames[0].mean()  # the first pose, seen at dusk
    assert not np.array_equal(repeats[0].house.occupancy.occupied, build_house(0).occupancy.occupied)
    plain, plain_frames, _ = repeat_route(policy.eval(), demo, repeats=2, noise="paper", seed=1, max_steps=50,
                                          image_size=config.image_size[0], progress=False, demo_length=config.demo_length)
    assert np.array_equal(demo_frames, plain_frames)  # the memory is the taught one
    assert np.array_equal(plain[0].frames[0], demo_frames[0])  # in the teaching world the agent starts on the taught view
