"""The recipes' command-line parser: a bad argument is one line naming it, and exit status 2."""
from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from typing import NoReturn

#: Exit status of a command refused for its arguments (argparse's).
USAGE_ERROR_STATUS = 2


class ArgumentParser(argparse.ArgumentParser):
    """An :class:`argparse.ArgumentParser` whose errors print ``prog: error: message`` alone
    (no usage block) to stderr and exit with :data:`USAGE_ERROR_STATUS`.

    Every recipe builds its parser with it, so argparse's own refusals (a missing value,
    a bad int) and the recipe's checks (``parser.error(...)`` before any work) read alike.

    Examples:
        >>> parser = ArgumentParser(prog="demo.py")
        >>> _ = parser.add_argument("--episodes", type=int)
        >>> try:
        ...     parser.parse_args(["--episodes", "many"])
        ... except SystemExit as exit_info:
        ...     print(exit_info.code)
        2
    """

    def error(self, message: str) -> NoReturn:
        self.exit(USAGE_ERROR_STATUS, f"{self.prog}: error: {message}\n")


def parse_names(text: str, allowed: Sequence[str], what: str) -> list[str]:
    """Comma-separated names, each one of ``allowed``; repeats dropped, the order kept.

    Raises:
        ValueError: an unknown name (or none), naming ``what`` and the allowed names.

    Examples:
        >>> parse_names("extended, test,extended", ("test", "extended"), "set")
        ['extended', 'test']
        >>> parse_names("test,val", ("test", "extended"), "set")
        Traceback (most recent call last):
        ...
        ValueError: unknown set ['val']; allowed: test, extended
    """
    items = [item.strip() for item in text.split(",") if item.strip()]
    unknown = [item for item in items if item not in allowed]
    if unknown or not items:
        raise ValueError(f"unknown {what} {unknown or text!r}; allowed: {', '.join(allowed)}")
    return list(dict.fromkeys(items))


def parse_seeds(text: str) -> list[int]:
    """Comma-separated training seeds, sorted, repeats dropped.

    Raises:
        ValueError: not comma-separated integers >= 0.

    Examples:
        >>> parse_seeds("2,0,2")
        [0, 2]
    """
    try:
        seeds = [int(item) for item in text.split(",") if item.strip()]
    except ValueError:
        seeds = []
    if not seeds or any(seed < 0 for seed in seeds):
        raise ValueError(f"seeds must be comma-separated integers >= 0 (e.g. 0,1,2), got {text!r}")
    return sorted(set(seeds))


def arg_type(parse: Callable, *params) -> Callable[[str], object]:
    """``parse(text, *params)`` as an argparse type: its ``ValueError`` is the option's one error line."""
    def parse_arg(text: str):
        try:
            return parse(text, *params)
        except ValueError as err:
            raise argparse.ArgumentTypeError(str(err)) from None

    return parse_arg
