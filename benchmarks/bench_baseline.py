"""Benchmarks against a baseline commit: its git worktree, child processes, interleaved repeats.

The baseline and the working tree share package names (``envs``, ``spf_rl``), so
they cannot be imported into one process: each tree's code runs in a child process
whose ``PYTHONPATH`` is the tree (:func:`run_json_child`), the baseline from a
``git worktree`` of its commit (:func:`baseline_worktree`). Figures are taken over
repeats interleaved between the trees (:func:`interleaved_runs`: old, new, old,
new, ...), so drifts in the machine's speed hit both. Used by
``benchmarks/bench_pipeline.py`` (the training baseline) and ``benchmarks/bench_main_job.py --baseline``.
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Callable, Iterator, Sequence, TypeVar

logger = logging.getLogger(__name__)

T = TypeVar("T")
#: main when issue #30 (collection and training speed) was filed: the speed baseline of
#: ``bench_pipeline.py`` (training) and ``bench_main_job.py --baseline`` (the main job).
BASELINE_COMMIT = "a5a7302"
#: Where the baseline's worktree is made (and reused by later runs; ignored by git).
BASELINE_DIR = Path(__file__).resolve().parents[1] / "runs" / "bench_pipeline" / "baseline"
#: The two trees of a comparison, in the order each repeat runs them.
SIDES = ("old", "new")
#: Characters of a failed child's stderr quoted in the error.
STDERR_TAIL_CHARS = 4000


def _git(repo: Path, *args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["git", *args], cwd=repo, check=check, capture_output=True, text=True)


def resolve_commit(rev: str, repo: Path) -> str:
    """The full SHA of commit ``rev`` in the repository at ``repo``.

    Raises:
        ValueError: ``rev`` names no commit there.
    """
    result = _git(repo, "rev-parse", "--verify", "--quiet", f"{rev}^{{commit}}", check=False)
    if result.returncode != 0 or not result.stdout.strip():
        raise ValueError(f"{rev!r} is not a commit of the repository at {repo}.")
    return result.stdout.strip()


def worktree_commit(path: Path) -> str | None:
    """The commit checked out in the worktree whose top directory is ``path`` (``None``: not one, or modified).

    A directory inside another checkout (not a worktree of its own) and a worktree
    with modified tracked files both give ``None``.
    """
    if not (path / ".git").exists():
        return None
    top = _git(path, "rev-parse", "--show-toplevel", check=False)
    if top.returncode != 0 or Path(top.stdout.strip()).resolve() != path.resolve():
        return None
    if _git(path, "status", "--porcelain", "--untracked-files=no", check=False).stdout.strip():
        return None
    head = _git(path, "rev-parse", "HEAD", check=False)
    return head.stdout.strip() if head.returncode == 0 else None


def ensure_worktree(repo: Path, sha: str, path: Path) -> bool:
    """A clean detached worktree of ``sha`` at ``path``: reused if it is one already, else (re)created.

    Returns:
        whether an existing worktree was reused.

    Raises:
        ValueError: ``path`` exists but is not a worktree of ``repo`` (it is left alone).
    """
    if worktree_commit(path) == sha:
        return True
    if path.exists():
        listed = _git(repo, "worktree", "list", "--porcelain").stdout.splitlines()
        if f"worktree {path.resolve()}" not in listed:
            raise ValueError(f"{path} exists and is not a git worktree of {repo}: remove it or choose another directory.")
        _git(repo, "worktree", "remove", "--force", str(path))
    _git(repo, "worktree", "prune")
    path.parent.mkdir(parents=True, exist_ok=True)
    _git(repo, "worktree", "add", "--detach", str(path), sha)
    logger.info("baseline worktree of %s at %s", sha[:12], path)
    return False


@contextlib.contextmanager
def baseline_worktree(repo: Path, sha: str, path: Path | None = None) -> Iterator[Path]:
    """A worktree of ``sha``: at ``path`` (reused if already there, kept afterwards for the next
    run), or with ``path=None`` in a temporary directory removed afterwards."""
    if path is not None:
        ensure_worktree(repo, sha, path)
        yield path
        return
    with tempfile.TemporaryDirectory() as scratch:
        worktree = Path(scratch) / "baseline"
        ensure_worktree(repo, sha, worktree)
        try:
            yield worktree
        finally:
            _git(repo, "worktree", "remove", "--force", str(worktree), check=False)


def run_json_child(argv: Sequence[str], tree: Path, timeout: float | None = None, after: Sequence[Path] = ()) -> dict:
    """Run ``python argv...`` with the tree's packages (``PYTHONPATH=tree``, then the folders ``after``,
    e.g. the benchmarks' own; working directory ``tree``) and parse the last line of its standard
    output as JSON.

    Raises:
        RuntimeError: the child failed (its exit status and the end of its stderr are in the message).
    """
    environment = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tree), *map(str, after)])}
    result = subprocess.run(
        [sys.executable, *argv], env=environment, cwd=tree, capture_output=True, text=True, timeout=timeout
    )
    lines = [line for line in result.stdout.splitlines() if line.strip()]
    if result.returncode != 0 or not lines:
        raise RuntimeError(
            f"child in {tree} failed (exit status {result.returncode}): {' '.join(argv)[:300]}\n"
            f"{result.stderr[-STDERR_TAIL_CHARS:]}"
        )
    return json.loads(lines[-1])


def interleaved_runs(run: Callable[[str, int], T], repeats: int, sides: Sequence[str] = SIDES) -> dict[str, list[T]]:
    """``run(side, repeat)`` for every repeat and side, interleaved (old, new, old, new, ...).

    Examples:
        >>> order = []
        >>> interleaved_runs(lambda side, repeat: order.append((side, repeat)) or repeat, 2)
        {'old': [0, 1], 'new': [0, 1]}
        >>> order
        [('old', 0), ('new', 0), ('old', 1), ('new', 1)]
    """
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats!r}.")
    runs: dict[str, list[T]] = {side: [] for side in sides}
    for repeat in range(repeats):
        for side in sides:
            runs[side].append(run(side, repeat))
    return runs


__all__ = [
    "BASELINE_COMMIT",
    "BASELINE_DIR",
    "SIDES",
    "baseline_worktree",
    "ensure_worktree",
    "interleaved_runs",
    "resolve_commit",
    "run_json_child",
    "worktree_commit",
]
