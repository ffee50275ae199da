"""The README's python code blocks run as written, and its results are Table 1's JSON.

Each fenced ``python`` block runs in a fresh namespace in a temporary working
directory. A block whose first line is ``# readme-test: skip`` is not run (none of
the README's examples is marked so).
"""
from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from spf_rl.eval.table1 import summary_markdown

README = Path(__file__).resolve().parents[1] / "README.md"
TABLE1 = README.parent / "results" / "table1.json"
SKIP_MARKER = "# readme-test: skip"
BLOCK = re.compile(r"^```python\n(.*?)^```", re.DOTALL | re.MULTILINE)


def python_blocks(text: str) -> list[tuple[int, str]]:
    """``(line number, code)`` of every fenced python block of a markdown text."""
    return [(text.count("\n", 0, match.start()) + 1, match.group(1)) for match in BLOCK.finditer(text)]


BLOCKS = python_blocks(README.read_text())


def test_readme_has_the_three_examples():
    code = "\n".join(block for _, block in BLOCKS)
    assert len(BLOCKS) >= 3
    for needed in ("make_path_follow_env", "Collector(", "spf_rl.load_policy", "watch("):
        assert needed in code
    assert not any(block.startswith(SKIP_MARKER) for _, block in BLOCKS[:3])


def test_block_extraction():
    text = "intro\n```python\nx = 1\n```\n\n```bash\nls\n```\n```python\n# readme-test: skip\ny\n```\n"
    assert python_blocks(text) == [(2, "x = 1\n"), (9, "# readme-test: skip\ny\n")]


@pytest.mark.parametrize("line, code", BLOCKS, ids=[f"README.md:{line}" for line, _ in BLOCKS])
def test_readme_block_runs(line, code, tmp_path, monkeypatch):
    if code.startswith(SKIP_MARKER):
        pytest.skip(f"README.md:{line} is marked {SKIP_MARKER!r}")
    monkeypatch.chdir(tmp_path)
    exec(compile(code, f"README.md:{line}", "exec"), {"__name__": "__main__"})


def test_readme_results_are_the_committed_table1():
    """The README's results table is ``summary_markdown`` of ``results/table1.json``,
    so a rerun of ``recipes/table1.py`` that changes a number fails here until the README follows."""
    expected = summary_markdown(json.loads(TABLE1.read_text()))
    assert expected in README.read_text()
