"""Record a route with the keyboard in a terminal (curses; no display needed).

Up arrow (or ``f``) drives forward 0.3 m, left / right arrows (or ``l`` / ``r``)
turn 20 degrees, Backspace (or ``u``) undoes the last step, Enter finishes and
``q`` cancels. The top-down map is drawn as text: ``#`` walls and furniture,
``.`` the route so far, ``S`` its start and an arrow for the agent.

:func:`handle_key` (what a key does to a :class:`~envs.user_demos.RouteRecorder`)
and :func:`ascii_map` are pure functions; :func:`record_with_keyboard` is the
curses loop around them.
"""
from __future__ import annotations

import curses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from envs.demos import Demonstration
from envs.expert import FORWARD, TURN_LEFT, TURN_RIGHT
from envs.scenes import House
from envs.user_demos import RouteError, RouteRecorder

#: Keys that drive the agent.
KEY_ACTIONS: dict[int, int] = {
    curses.KEY_UP: FORWARD,
    curses.KEY_LEFT: TURN_LEFT,
    curses.KEY_RIGHT: TURN_RIGHT,
    ord("f"): FORWARD,
    ord("l"): TURN_LEFT,
    ord("r"): TURN_RIGHT,
}
#: Enter (line feed, carriage return, keypad Enter) finishes the route.
FINISH_KEYS = frozenset({10, 13, curses.KEY_ENTER})
#: Backspace (curses, DEL, ^H) or ``u`` undoes the last step.
UNDO_KEYS = frozenset({curses.KEY_BACKSPACE, 127, 8, ord("u")})
#: ``q`` cancels.
QUIT_KEYS = frozenset({ord("q")})
#: Escape; terminals outside keypad mode send arrows as Esc ``[`` or Esc ``O`` and a letter.
ESCAPE = 27
ESCAPE_PREFIXES = frozenset({ord("["), ord("O")})
ESCAPE_ARROWS = {ord("A"): curses.KEY_UP, ord("B"): curses.KEY_DOWN, ord("C"): curses.KEY_RIGHT, ord("D"): curses.KEY_LEFT}
#: What ``getch`` returns when no key is waiting.
NO_KEY = -1
#: Text cells per metre of the house on the map (a house of 15 m is 30 cells wide).
MAP_CELLS_PER_M = 2
#: Arrows for the agent's heading, one per 45-degree sector counter-clockwise from +x.
HEADING_ARROWS = (">", "/", "^", "\\", "<", "/", "v", "\\")
HELP_LINE = "Up: forward  Left/Right: turn  Backspace: undo  Enter: finish  q: quit"


@dataclass(frozen=True)
class KeyOutcome:
    """What a key did.

    Attributes:
        message: a line for the user ("" when there is nothing to say).
        demonstration: the finished demonstration (Enter on a valid route), else ``None``.
        cancelled: the user quit.

    Examples:
        >>> outcome = handle_key(RouteRecorder(0, (7.5, 1.5, 0.0), max_steps=3), ord("q"), 3)
        >>> outcome.cancelled, outcome.demonstration is None, outcome.message
        (True, True, 'cancelled')
    """

    message: str = ""
    demonstration: Demonstration | None = None
    cancelled: bool = False


def handle_key(recorder: RouteRecorder, key: int, max_length: int, exact: bool = False) -> KeyOutcome:
    """Apply one key press to ``recorder`` (a route of at most ``max_length`` steps; Enter ends it).

    A refused step (into a wall, past ``max_length``) or a refused end (a route too short
    to follow, or with ``exact`` fewer than ``max_length`` steps) leaves the route as it
    was and says why.

    Examples:
        >>> recorder = RouteRecorder(0, (7.5, 1.5, 0.0), max_steps=3)
        >>> handle_key(recorder, curses.KEY_UP, 3).message, recorder.length
        ('', 1)
        >>> handle_key(recorder, 10, 3).message.startswith("the route is too short")
        True
        >>> handle_key(recorder, 10, 3, exact=True).message.startswith("the route has 1 steps")
        True
    """
    if key == NO_KEY:
        return KeyOutcome()
    if key in QUIT_KEYS:
        return KeyOutcome(message="cancelled", cancelled=True)
    if key in UNDO_KEYS:
        return KeyOutcome(message="" if recorder.undo() else "nothing to undo")
    if key in FINISH_KEYS:
        try:
            return KeyOutcome(message="done", demonstration=recorder.demonstration(length=max_length if exact else None))
        except RouteError as err:
            return KeyOutcome(message=str(err))
    if key in KEY_ACTIONS:
        try:
            recorder.step(KEY_ACTIONS[key])
        except RouteError as err:
            return KeyOutcome(message=str(err))
        if recorder.length == max_length:
            return KeyOutcome(message=f"{max_length} steps, the most a route may have: press Enter to finish (Backspace to undo).")
        return KeyOutcome()
    return KeyOutcome(message=f"unknown key; {HELP_LINE}")


def decode_escape(following: Sequence[int]) -> int:
    """The key of an escape sequence from the two codes after Esc (an arrow), else :data:`NO_KEY`.

    Examples:
        >>> decode_escape([ord("["), ord("A")]) == curses.KEY_UP, decode_escape([NO_KEY, NO_KEY])
        (True, -1)
    """
    if len(following) == 2 and following[0] in ESCAPE_PREFIXES and following[1] in ESCAPE_ARROWS:
        return ESCAPE_ARROWS[following[1]]
    return NO_KEY


def read_key(screen) -> int:
    """The next key, with arrows that arrive as raw escape sequences decoded (a lone Esc is ignored)."""
    key = screen.getch()
    if key != ESCAPE:
        return key
    screen.nodelay(True)
    try:
        following = [screen.getch(), screen.getch()]
    finally:
        screen.nodelay(False)
    return decode_escape(following)


def ascii_map(house: House, poses: np.ndarray, cells_per_m: int = MAP_CELLS_PER_M) -> list[str]:
    """The house from above as text lines (top line = largest y), with a route on it.

    Args:
        house: the house.
        poses: ``(k + 1, 3)`` poses (x m, y m, heading rad) of the route; the last is the agent.
        cells_per_m: text cells per metre.

    Examples:
        >>> from envs.scenes import build_house
        >>> lines = ascii_map(build_house(0), np.array([[7.5, 1.5, 0.0], [8.1, 1.5, 0.0]]))
        >>> len(lines), len(lines[0]), lines[-4][15:17]
        (30, 30, 'S>')
    """
    occupied = house.occupancy.occupied
    width, depth = house.size_m
    cols, rows = int(round(width * cells_per_m)), int(round(depth * cells_per_m))
    block_r, block_c = occupied.shape[0] // rows, occupied.shape[1] // cols
    blocked = occupied[: rows * block_r, : cols * block_c].reshape(rows, block_r, cols, block_c).any(axis=(1, 3))
    grid = np.where(blocked, "#", " ").astype("<U1")

    def cell(xy: Sequence[float]) -> tuple[int, int]:
        return min(max(int(xy[1] * cells_per_m), 0), rows - 1), min(max(int(xy[0] * cells_per_m), 0), cols - 1)

    for pose in poses[1:-1]:
        grid[cell(pose)] = "."
    grid[cell(poses[0])] = "S"
    sector = int(round(math.degrees(poses[-1, 2]) / 45.0)) % len(HEADING_ARROWS)
    grid[cell(poses[-1])] = HEADING_ARROWS[sector]  # the agent, over the start when it is there
    return ["".join(row) for row in grid[::-1]]


def status_lines(recorder: RouteRecorder, max_length: int, message: str) -> list[str]:
    """The lines under the map: step count, pose, the last message and the keys."""
    x, y, heading = recorder.pose
    return [
        f"house {recorder.house.seed}  step {recorder.length} (at most {max_length})  "
        f"pose ({x:.2f} m, {y:.2f} m) heading {math.degrees(heading) % 360:.0f} deg",
        message,
        HELP_LINE,
    ]


def record_with_keyboard(house: House, start: Sequence[float], max_length: int, exact: bool = False) -> Demonstration | None:
    """Let the user drive a route of up to ``max_length`` steps (with ``exact``: of exactly ``max_length``)
    from ``start`` (x m, y m, heading deg) in the terminal.

    Returns:
        the demonstration, or ``None`` when the user cancels.
    """
    recorder = RouteRecorder(house, start, max_steps=max_length)

    def loop(screen) -> Demonstration | None:
        screen.keypad(True)
        message = ""
        while True:
            screen.erase()
            height, width = screen.getmaxyx()
            lines = ascii_map(house, recorder.poses) + [""] + status_lines(recorder, max_length, message)
            for row, line in enumerate(lines[: height - 1]):
                screen.addstr(row, 0, line[: width - 1])
            screen.refresh()
            outcome = handle_key(recorder, read_key(screen), max_length, exact)
            if outcome.cancelled or outcome.demonstration is not None:
                return outcome.demonstration
            message = outcome.message

    return curses.wrapper(loop)
