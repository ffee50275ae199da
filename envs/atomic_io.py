"""Atomic file writes: a reader sees the old file or the new one, never half of one.

Each write goes to a hidden temporary file beside the target, is flushed and fsynced,
then moved over the target with :func:`os.replace` (atomic on POSIX file systems), so a
crash or an interrupt never leaves a torn results file, store index or checkpoint.
Every file the project writes for later reading goes through :func:`atomic_write`.

Examples:
    >>> import json, tempfile
    >>> from pathlib import Path
    >>> path = Path(tempfile.mkdtemp()) / "results.json"
    >>> atomic_write_json(path, {"success": 0.8})
    >>> json.loads(path.read_text())
    {'success': 0.8}
    >>> sorted(p.name for p in path.parent.iterdir())  # no temporary file left behind
    ['results.json']
"""
from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any


def atomic_write(path: str | os.PathLike, write: Callable[[IO], Any], binary: bool = False) -> None:
    """Call ``write(handle)`` on a temporary file beside ``path``, then move it over ``path``.

    The temporary file keeps ``path``'s suffix (``.tmp`` goes before it), so writers that
    read the format from the name (matplotlib's ``savefig``) still find it. It is removed
    if ``write`` raises.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    try:
        with open(tmp, "wb" if binary else "w") as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write_path(path: str | os.PathLike, write: Callable[[Path], Any]) -> None:
    """Call ``write(temporary_path)`` for writers that take a file name (a video encoder), then move
    the file over ``path``; the temporary name keeps ``path``'s suffix. It is removed if ``write`` raises.

    Examples:
        >>> import tempfile
        >>> path = Path(tempfile.mkdtemp()) / "frames.bin"
        >>> atomic_write_path(path, lambda tmp: tmp.write_bytes(b"abc"))
        >>> path.read_bytes(), sorted(p.name for p in path.parent.iterdir())
        (b'abc', ['frames.bin'])
    """
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically."""
    atomic_write(path, lambda handle: handle.write(text))


def atomic_write_json(
    path: str | os.PathLike, payload: Any, indent: int = 2, sort_keys: bool = False, default: Callable | None = None
) -> None:
    """Write ``payload`` as JSON (with a final newline) to ``path`` atomically.

    ``default`` is :func:`json.dumps`'s, e.g. ``str`` for paths and other plain values.
    """
    atomic_write_text(path, json.dumps(payload, indent=indent, sort_keys=sort_keys, default=default) + "\n")
