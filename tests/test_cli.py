"""The recipes' parser: a refused argument is one line naming it, exit status 2."""
from __future__ import annotations

import pytest

from spf_rl.cli import USAGE_ERROR_STATUS, ArgumentParser


@pytest.mark.parametrize("argv", [["--episodes", "many"], ["--unknown"], []])
def test_errors_are_one_line_without_usage(argv, capsys):
    parser = ArgumentParser(prog="demo.py")
    parser.add_argument("--episodes", type=int, required=True)
    with pytest.raises(SystemExit) as info:
        parser.parse_args(argv)
    err = capsys.readouterr().err
    assert info.value.code == USAGE_ERROR_STATUS
    assert err.startswith("demo.py: error: ") and err.count("\n") == 1 and "usage" not in err


def test_a_recipe_check_reads_like_argparse(capsys):
    parser = ArgumentParser(prog="demo.py")
    with pytest.raises(SystemExit) as info:
        parser.error("--episodes must be > 0, got 0")
    assert info.value.code == 2 and capsys.readouterr().err == "demo.py: error: --episodes must be > 0, got 0\n"
