"""The one on-disk store of the project: a memory-mapped TensorDict built in chunks, verified and resumable.

Demonstrations (:class:`~envs.demo_store.DemoStore`) and episode datasets
(:class:`~spf_rl.data.EpisodeDataset`) are both a :class:`TensorStore`: a
directory holding ::

    <root>/meta.json     kind, format version, env version, configuration,
                         SHA-256 of every tensor
    <root>/data/         the tensors, TensorDict's memmap format (no pickle)

A store is a pure function of its configuration, produced in chunks of rows
(chunk ``c`` depends only on the configuration and ``c``). :meth:`TensorStore.create`
writes the chunks into ``<root>.partial`` with a ``progress.json`` of the chunks
done and their checksums; an interrupted build resumes from there and gives the
same bytes as an uninterrupted one. When every chunk is written, ``meta.json`` is
added and the directory is renamed to ``root`` in one step, so ``root`` only ever
holds a complete store.

Opening checks, each with a :class:`StoreError` that names the directory: a
``meta.json`` that is missing, unreadable or not an object; another kind of store;
another format version; data made by another :data:`~envs.version.ENV_VERSION`; a
configuration the maker refuses; missing tensors or tensors of the wrong shape;
and (with ``verify=True``) a checksum that does not match.
"""
from __future__ import annotations

import concurrent.futures
import contextlib
import hashlib
import json
import logging
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from filelock import FileLock
from tensordict import TensorDict, TensorDictBase
from tqdm.auto import tqdm

from envs.atomic_io import atomic_write_json
from envs.version import ENV_VERSION, check_env_version
from envs.worker_processes import worker_context

logger = logging.getLogger(__name__)

#: Suffix of the directory a store is built in before it is renamed into place.
PARTIAL_SUFFIX = ".partial"
#: Suffix of the lock file that lets one process at a time build a store directory.
LOCK_SUFFIX = ".lock"
_DATA_DIR = "data"


class StoreError(RuntimeError):
    """A store directory is missing, half-written, corrupt, stale, or of another configuration."""


def tensor_checksums(data: TensorDictBase) -> dict[str, str]:
    """SHA-256 of every leaf tensor (keys joined with ``/``), hashed straight from the buffers."""
    return {
        "/".join((key,) if isinstance(key, str) else key): hashlib.sha256(data.get(key).contiguous().numpy()).hexdigest()
        for key in sorted(data.keys(include_nested=True, leaves_only=True), key=str)
    }


def chunk_checksum(chunk: TensorDictBase) -> str:
    """One SHA-256 over a chunk's keys and bytes (used to verify chunks when resuming)."""
    digest = hashlib.sha256()
    for key in sorted(chunk.keys(include_nested=True, leaves_only=True), key=str):
        digest.update(str(key).encode())
        digest.update(chunk.get(key).contiguous().numpy().tobytes())
    return digest.hexdigest()


def worker_threads(num_workers: int) -> int:
    """Torch threads for each of ``num_workers`` worker processes: their share of this machine's cores.

    A spawned process would otherwise start as many threads as there are cores, and
    workers that together run more threads than cores wait on each other (building a
    dataset with 2 workers on 2 cores ran 1.5x faster with one thread each).

    Examples:
        >>> worker_threads(os.cpu_count() or 1)
        1
    """
    return max(1, (os.cpu_count() or 1) // max(1, num_workers))


def worker_pool(num_workers: int) -> concurrent.futures.ProcessPoolExecutor:
    """``num_workers`` worker processes (:func:`envs.worker_processes.worker_context`), each with its share of the cores for
    torch's threads (:func:`worker_threads`); started at the first task submitted.

    Examples:
        >>> with worker_pool(2) as pool:
        ...     pool.submit(max, 1, 2).result()
        2
    """
    if isinstance(num_workers, bool) or not isinstance(num_workers, int) or num_workers < 1:
        raise ValueError(f"num_workers must be a positive int, got {num_workers!r}.")
    return concurrent.futures.ProcessPoolExecutor(
        num_workers, mp_context=worker_context(), initializer=torch.set_num_threads,
        initargs=(worker_threads(num_workers),),
    )


class TensorStore:
    """A complete store directory, memory-mapped; subclasses say what it holds.

    Subclasses set :attr:`KIND`, :attr:`FORMAT_VERSION`, :attr:`ERROR` (a
    :class:`StoreError` subclass) and implement :meth:`config_from_dict` (which
    validates) and :meth:`empty` (the full-size layout for a configuration). The
    store pickles as its path, so spawn workers map the same files; its tensors
    are shared maps: read them, never write to them.

    Args:
        root: the store directory.
        verify: recompute the SHA-256 of every tensor and compare with ``meta.json``.

    Examples:
        >>> import tempfile, torch
        >>> class Squares(TensorStore):
        ...     KIND, FORMAT_VERSION = "squares", 1
        ...     @staticmethod
        ...     def config_from_dict(config): return dict(config)
        ...     @staticmethod
        ...     def empty(config): return TensorDict({"x": torch.zeros(config["rows"])}, [config["rows"]])
        >>> def chunk(config, index):
        ...     return TensorDict({"x": torch.arange(2 * index, 2 * index + 2.0) ** 2}, [2])
        >>> store = Squares.create(tempfile.mkdtemp() + "/sq", {"rows": 4}, chunk, chunk_rows=2, progress=False)
        >>> store.data["x"].tolist()
        [0.0, 1.0, 4.0, 9.0]
    """

    KIND: str = "store"
    FORMAT_VERSION: int = 1
    ERROR: type[StoreError] = StoreError
    #: What each format version changed, for the message that refuses an older store.
    FORMAT_HISTORY: str = ""

    def __init__(self, root: str | os.PathLike, verify: bool = True) -> None:
        self.root = Path(root)
        self.config, self._checksums = self._read_meta()
        self.data = self._open()
        if verify:
            self.verify()

    # ------------------------------------------------------------ subclass API
    @staticmethod
    def config_from_dict(config: dict) -> Any:
        """The validated configuration object of a ``meta.json`` config dict."""
        raise NotImplementedError

    @staticmethod
    def empty(config: Any) -> TensorDict:
        """The full-size, zero-filled layout of a store of ``config``."""
        raise NotImplementedError

    @classmethod
    def layout(cls, config: Any) -> TensorDict:
        """:meth:`empty`'s tensors on the ``meta`` device: the layout's shapes and dtypes
        without its memory (a route dataset's zeros would take gigabytes)."""
        with torch.device("meta"):
            return cls.empty(config)

    @staticmethod
    def config_to_dict(config: Any) -> dict:
        """The JSON form of a configuration (a dataclass's fields by default)."""
        from dataclasses import asdict, is_dataclass

        return asdict(config) if is_dataclass(config) else dict(config)

    # ---------------------------------------------------------------- opening
    def _fail(self, message: str) -> StoreError:
        return self.ERROR(f"{self.KIND} store {self.root}: {message}")

    def _read_meta(self) -> tuple[Any, dict[str, str]]:
        try:
            meta = json.loads((self.root / "meta.json").read_text())
        except (FileNotFoundError, NotADirectoryError) as err:
            partial = self.root.with_name(self.root.name + PARTIAL_SUFFIX)
            hint = f" A half-written build is in {partial}: run the build again to resume it." if partial.exists() else ""
            raise self.ERROR(f"{self.root} is not a {self.KIND} store (no meta.json).{hint}") from err
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            raise self._fail(f"corrupt or unreadable meta.json ({err}).") from err
        if not isinstance(meta, dict):
            raise self._fail(f"corrupt meta.json (a {type(meta).__name__}, not an object).")
        if meta.get("kind", self.KIND) != self.KIND:
            raise self._fail(f"holds a {meta.get('kind')!r} store, not a {self.KIND!r} store.")
        if meta.get("format_version") != self.FORMAT_VERSION:
            raise self._fail(
                f"format version {meta.get('format_version')!r} is not {self.FORMAT_VERSION} "
                f"{self.FORMAT_HISTORY}; delete it and build it again."
            )
        try:
            check_env_version(meta.get("env_version"), f"{self.KIND} store {self.root}")
        except ValueError as err:
            raise self.ERROR(f"{err} Delete it and build it again.") from err
        try:
            return self.config_from_dict(meta["config"]), dict(meta["checksums"])
        except (KeyError, TypeError, ValueError) as err:
            raise self._fail(f"invalid meta.json ({err}).") from err

    def _open(self) -> TensorDict:
        try:
            data = TensorDict.load_memmap(self.root / _DATA_DIR)
        except Exception as err:  # any failure to map means a damaged store
            raise self._fail(f"cannot read the tensors ({err}).") from err
        expected = self.layout(self.config)
        present = set(data.keys(include_nested=True, leaves_only=True))
        for key in expected.keys(include_nested=True, leaves_only=True):
            if key not in present or data.get(key).shape != expected.get(key).shape:
                raise self._fail(
                    f"tensor {key!r} is missing or has the wrong shape (expected {tuple(expected.get(key).shape)})."
                )
        return data.lock_()

    def verify(self) -> None:
        """Recompute every tensor's checksum; raise on a mismatch."""
        actual = tensor_checksums(self.data)
        for key, digest in self._checksums.items():
            if actual.get(key) != digest:
                raise self._fail(f"tensor {key!r} is corrupt (checksum mismatch). Delete the directory and build it again.")

    def __len__(self) -> int:
        return int(self.data.batch_size[0])

    def __getstate__(self) -> dict:
        return {"root": str(self.root)}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["root"], verify=False)

    # --------------------------------------------------------------- building
    @classmethod
    def create(
        cls,
        root: str | os.PathLike,
        config: Any,
        make_chunk: Callable[[Any, int], TensorDict],
        chunk_rows: int,
        num_workers: int = 1,
        progress: bool = True,
        pool: concurrent.futures.Executor | None = None,
    ):
        """Build the store of ``config`` at ``root``, resuming a partial build, or open it if it exists.

        Args:
            root: the store directory.
            config: the configuration (validated by the caller).
            make_chunk: ``make_chunk(config, c)`` -> rows ``[c * chunk_rows, ...)``; a
                pure function, importable at module level when ``num_workers > 1``.
            chunk_rows: rows per chunk (the last chunk may be shorter).
            num_workers: ``spawn`` worker processes producing chunks (1: in this process),
                each with its share of the cores for torch's threads (:func:`worker_threads`).
            progress: show a progress bar.
            pool: an executor of worker processes (:func:`worker_pool`) to build the chunks
                in instead of ``num_workers`` new ones, e.g. shared by the stores of one
                dataset so that their workers start (imports, GL contexts, houses) once.

        A store already in place is opened without locking (read-only directories
        work). Otherwise processes building the same ``root`` take a lock file
        ``<root>.lock`` (removed once the store is in place): the first builds, and
        the others, once it is done, open what it wrote.

        Raises:
            StoreError: ``root`` holds a store of another configuration, or is a
                non-empty directory that is not a store.
        """
        root = Path(root)
        if (root / "meta.json").exists():
            return cls._create_locked(root, config, make_chunk, chunk_rows, num_workers, progress, pool)
        root.parent.mkdir(parents=True, exist_ok=True)
        lock = root.with_name(root.name + LOCK_SUFFIX)
        with FileLock(str(lock)):
            store = cls._create_locked(root, config, make_chunk, chunk_rows, num_workers, progress, pool)
            # the store is in place: whoever waits on this lock, or takes a new one, opens it
            lock.unlink(missing_ok=True)
        return store

    @classmethod
    def _create_locked(
        cls,
        root: Path,
        config: Any,
        make_chunk: Callable[[Any, int], TensorDict],
        chunk_rows: int,
        num_workers: int,
        progress: bool,
        pool: concurrent.futures.Executor | None = None,
    ) -> TensorStore:
        config_dict = cls.config_to_dict(config)
        if (root / "meta.json").exists():
            store = cls(root, verify=False)
            if cls.config_to_dict(store.config) != config_dict:
                raise cls.ERROR(
                    f"{cls.KIND} store {root} was built with another configuration "
                    f"({cls.config_to_dict(store.config)}); choose another directory or delete it."
                )
            return store
        if root.exists() and (not root.is_dir() or any(root.iterdir())):
            raise cls.ERROR(f"{root} exists and is not a {cls.KIND} store (no meta.json); choose another directory or delete it.")
        partial = root.with_name(root.name + PARTIAL_SUFFIX)
        data, done = cls._resume_or_start(partial, config, config_dict, chunk_rows)
        rows = data.batch_size[0]
        num_chunks = -(-rows // chunk_rows)
        todo = [c for c in range(num_chunks) if str(c) not in done]
        if todo:
            logger.info("building %d of %d chunks of %s", len(todo), num_chunks, root)
        bar = tqdm(total=num_chunks, initial=num_chunks - len(todo), desc=f"{cls.KIND} chunks", disable=not progress)

        def store(chunk: int, values: TensorDict) -> None:
            start = chunk * chunk_rows
            data[start : start + values.shape[0]].update_(values)
            done[str(chunk)] = chunk_checksum(values)
            atomic_write_json(partial / "progress.json", {"config": config_dict, "chunks": done}, sort_keys=True)
            bar.update(1)

        if len(todo) <= 1 or (pool is None and num_workers <= 1):
            for chunk in todo:
                store(chunk, make_chunk(config, chunk))
        else:
            with contextlib.ExitStack() as stack:
                workers = pool if pool is not None else stack.enter_context(worker_pool(num_workers))
                futures = {workers.submit(make_chunk, config, chunk): chunk for chunk in todo}
                for future in concurrent.futures.as_completed(futures):
                    store(futures[future], future.result())
        bar.close()
        meta = {
            "kind": cls.KIND,
            "format_version": cls.FORMAT_VERSION,
            "env_version": ENV_VERSION,
            "config": config_dict,
            "checksums": tensor_checksums(data),
        }
        data = None  # closes the memory-mapped files before the directory moves
        atomic_write_json(partial / "meta.json", meta, sort_keys=True)
        (partial / "progress.json").unlink()
        if root.exists():  # an empty directory the caller created
            root.rmdir()
        os.replace(partial, root)
        logger.info("wrote %s", root)
        return cls(root, verify=False)

    @classmethod
    def _resume_or_start(
        cls, partial: Path, config: Any, config_dict: dict, chunk_rows: int
    ) -> tuple[TensorDict, dict[str, str]]:
        """The partial build's tensors and its verified chunks, or a fresh build (a stale partial is replaced).

        A chunk whose bytes no longer match its checksum is built again.
        """
        try:
            state = json.loads((partial / "progress.json").read_text())
            if state.get("config") != config_dict:
                raise ValueError("another configuration")
            data = TensorDict.load_memmap(partial / _DATA_DIR)
            if data.batch_size != cls.layout(config).batch_size:
                raise ValueError("another shape")
            done = {
                str(chunk): str(digest)
                for chunk, digest in state["chunks"].items()
                if chunk_checksum(data[int(chunk) * chunk_rows : (int(chunk) + 1) * chunk_rows]) == digest
            }
            logger.info("resuming %s: %d chunks already built", partial, len(done))
            return data, done
        except (OSError, ValueError, KeyError, TypeError, AttributeError, RuntimeError):
            if partial.exists():
                shutil.rmtree(partial)
            partial.mkdir(parents=True)
            # zero-filled files made at their size (sparse): no full-size tensor in memory
            data = cls.layout(config).memmap_like(partial / _DATA_DIR)
            atomic_write_json(partial / "progress.json", {"config": config_dict, "chunks": {}}, sort_keys=True)
            return data, {}
