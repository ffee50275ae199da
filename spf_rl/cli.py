"""The recipes' command-line parser: a bad argument is one line naming it, and exit status 2."""
from __future__ import annotations

import argparse
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
