"""The first-person renderer: several renderers in one process keep their own GL state."""
from __future__ import annotations

import numpy as np

from envs.render import FirstPersonRenderer
from envs.scenes import build_house


def views(renderer, house, count=3):
    x, y = house.spawn_xy
    return [renderer.render(house, np.array([x, y, heading])) for heading in np.linspace(0, 2, count)]


def test_interleaved_renderers_draw_what_a_lone_renderer_draws():
    first_house, second_house, third_house = build_house(seed=0), build_house(seed=1), build_house(seed=2)
    alone = FirstPersonRenderer(32, 32)
    expected = {seed: views(alone, house) for seed, house in ((0, first_house), (1, second_house), (2, third_house))}
    alone.close()

    collector_side, evaluation_side = FirstPersonRenderer(32, 32), FirstPersonRenderer(32, 32)
    a = views(collector_side, first_house)
    b = views(evaluation_side, second_house)  # the other renderer's context becomes current
    a_again = views(collector_side, first_house)
    evaluation_side.close()  # frees its context while the other renderer lives on
    c = views(collector_side, third_house)  # a new house (new GL resources) after the other one closed
    collector_side.close()
    for got, want in ((a, expected[0]), (b, expected[1]), (a_again, expected[0]), (c, expected[2])):
        for frame, reference in zip(got, want):
            np.testing.assert_array_equal(frame, reference)
    assert not np.array_equal(expected[0][0], expected[1][0])


def test_renderer_survives_another_gl_context_being_freed():
    from envs.render import create_gl_context

    house = build_house(seed=0)
    renderer = FirstPersonRenderer(32, 32)
    expected = views(renderer, house)
    stray = create_gl_context(32, 32)  # e.g. a context of an env nobody closed ...
    stray.free()  # ... freed later by the garbage collector: eglReleaseThread unbinds the current context
    new_house = views(renderer, build_house(seed=2))  # new GL resources
    assert new_house[0].any()
    for frame, reference in zip(views(renderer, house), expected):
        np.testing.assert_array_equal(frame, reference)
    renderer.close()


def test_render_many_matches_one_frame_at_a_time_across_houses():
    houses = [build_house(seed=0), build_house(seed=1), build_house(seed=0), build_house(seed=2)]
    poses = np.array([[*house.spawn_xy, heading] for house, heading in zip(houses, (0.0, 1.0, 2.0, -1.0))])
    single = FirstPersonRenderer(32, 32)
    expected = [single.render(house, pose) for house, pose in zip(houses, poses)]
    single.close()
    batched = FirstPersonRenderer(32, 32)
    chw = np.zeros((len(houses), 3, 32, 32), dtype=np.uint8)
    frames = batched.render_many(houses, poses, out=chw.transpose(0, 2, 3, 1))  # a strided output view
    fresh = batched.render_many(houses[::-1], poses[::-1])
    batched.close()
    for row, reference in enumerate(expected):
        np.testing.assert_array_equal(frames[row], reference)
        np.testing.assert_array_equal(chw[row].transpose(1, 2, 0), reference)
        np.testing.assert_array_equal(fresh[len(houses) - 1 - row], reference)
    assert not np.array_equal(expected[0], expected[1])


def test_unclosed_renderers_exit_without_gl_errors():
    """Envs nobody closed: their GL contexts are freed before EGL shuts down at exit."""
    import subprocess
    import sys

    script = (
        "import envs, numpy as np\n"
        "from envs.render import FirstPersonRenderer\n"
        "from envs.scenes import build_house\n"
        "house = build_house(0)\n"
        "for size in (32, 48):\n"
        "    FirstPersonRenderer(size, size).render(house, np.array([*house.spawn_xy, 0.0]))\n"
        "kept = FirstPersonRenderer(32, 32); kept.render(house, np.array([*house.spawn_xy, 1.0]))\n"
        "print('rendered')\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert "rendered" in result.stdout
    assert "Exception ignored" not in result.stderr and "EGLError" not in result.stderr, result.stderr
