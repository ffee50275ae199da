"""Follow a taught route with an exported policy: ONNX Runtime's CPU provider and numpy, nothing else."""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import onnxruntime as ort

from spf_rl_runtime.route_memory import MEMORY_DTYPES, RouteMemory, memory_indices

#: The export layout this runtime writes for (spf-rl's ``spf_rl.export.EXPORT_FORMAT_VERSION``); it reads
#: :data:`READABLE_FORMATS` (1: the pointer and hidden state alone; 2: a step state that may carry more).
EXPORT_FORMAT_VERSION = 2
READABLE_FORMATS = (1, 2)
MANIFEST_NAME = "manifest.json"
TEACH_FILE, STEP_FILE = "teach.onnx", "step.onnx"
#: The actions a step returns.
ACTIONS = ("forward", "left", "right")


def _sha256(path: Path) -> str:  # the runtime cannot import spf-rl (spf_rl.checkpoint.file_sha256)
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


class Export:
    """An export directory, loaded: its manifest, checked file by file, and its ONNX Runtime sessions.

    Args:
        directory: an export directory (spf-rl's ``recipes/export.py``): its ``manifest.json`` and graphs.
        threads: ONNX Runtime's intra-op threads.

    Raises:
        ValueError: no export there, another export format, or a file whose SHA-256 differs from the manifest's.
    """

    def __init__(self, directory: str | os.PathLike, threads: int = 1) -> None:
        if not isinstance(threads, int) or threads < 1:
            raise ValueError(f"threads must be an int >= 1, got {threads!r}")
        directory = Path(directory)
        manifest_path = directory / MANIFEST_NAME
        if not manifest_path.is_file():
            raise ValueError(f"{directory} holds no export ({MANIFEST_NAME} is missing)")
        self.manifest = json.loads(manifest_path.read_text())
        if self.manifest.get("format_version") not in READABLE_FORMATS:
            raise ValueError(f"{manifest_path}: export format {self.manifest.get('format_version')!r}, this runtime "
                             f"reads {READABLE_FORMATS}")
        for name, digest in self.manifest["files"].items():
            if not (directory / name).is_file() or _sha256(directory / name) != digest:
                raise ValueError(f"{directory / name} is missing or differs from {MANIFEST_NAME} (SHA-256): re-export it")
        options = ort.SessionOptions()
        options.intra_op_num_threads, options.inter_op_num_threads = threads, 1
        providers = ["CPUExecutionProvider"]
        self.step_session = ort.InferenceSession(str(directory / STEP_FILE), options, providers=providers)
        self.teach_session = (ort.InferenceSession(str(directory / TEACH_FILE), options, providers=providers)
                              if self.manifest["uses_memory"] else None)
        config = self.manifest["model_config"]
        self.image_size = tuple(config["image_size"])
        self.hidden_size = int(config["hidden_size"])
        self.num_actions = int(config["num_actions"])
        self.demo_length = int(config["demo_length"])
        self.sparsity = self.manifest["sparsity"]
        self.memory_width = int(self.manifest["memory_width"])
        self.uses_memory = bool(self.manifest["uses_memory"])
        #: The identity a route memory taught by this export carries: its step graph's SHA-256.
        self.export_id = self.manifest["files"][STEP_FILE]
        self._step_inputs = {node.name for node in self.step_session.get_inputs()}
        #: The step graph's recurrent state: each state input's value at a route's start (format 1: the pointer
        #: and hidden state, zero), and the output that carries it on.
        self.initial_state = dict(self.manifest["step"].get("initial_state", {"eta": 0.0, "hidden": 0.0}))
        outputs = [node.name for node in self.step_session.get_outputs()]
        self.state_outputs = {"eta": "eta_next", "hidden": "hidden_next",
                              **{name: f"{name}_next" for name in self.initial_state if name not in ("eta", "hidden")}}
        self._output_index = {name: index for index, name in enumerate(outputs)}
        self._teach_inputs = set() if self.teach_session is None else {node.name for node in self.teach_session.get_inputs()}

    def teach_features(self, frames: np.ndarray, actions: np.ndarray) -> np.ndarray:
        """Memory features ``[N, D]`` (float32) of kept frames uint8 ``[N, H, W, 3]`` and their actions ``[N]``."""
        feed = {"frames": frames, "actions": np.asarray(actions, dtype=np.int64)}
        return self.teach_session.run(None, {k: v for k, v in feed.items() if k in self._teach_inputs})[0]

    def step(self, frame, memory, slot_indices, demo_actions, route_length, eta, hidden, **state):
        """One batched step: ``(logits [B, A], eta_next [B], hidden_next [B, Hs])``, then the next value of each
        further state input given in ``state`` (``start_match`` ``[B]`` where :attr:`initial_state` has it)."""
        missing = sorted(set(self.initial_state) - {"eta", "hidden"} - set(state))
        if missing:
            raise ValueError(f"this export's step also carries {missing}: pass them (start from initial_state)")
        feed = {"frame": frame, "memory": memory, "slot_indices": slot_indices, "demo_actions": demo_actions,
                "route_length": route_length, "eta": eta, "hidden": hidden, **state}
        outputs = self.step_session.run(None, {k: v for k, v in feed.items() if k in self._step_inputs})
        return [outputs[self._output_index[name]] for name in ("logits", "eta_next", "hidden_next")] + [
            outputs[self._output_index[self.state_outputs[key]]] for key in state]


class Follower:
    """An exported policy that is taught a route once and then follows it step by step (one robot).
    ``directory`` and ``threads`` are :class:`Export`'s, and so are its errors."""

    def __init__(self, directory: str | os.PathLike, threads: int = 1) -> None:
        self.export = Export(directory, threads)
        self.manifest = self.export.manifest
        self.image_size, self.hidden_size = self.export.image_size, self.export.hidden_size
        self.num_actions, self.sparsity, self.export_id = self.export.num_actions, self.export.sparsity, self.export.export_id
        self._state: dict[str, np.ndarray] | None = None

    # ------------------------------------------------------------------ teaching
    def teach(self, frames: np.ndarray, actions: np.ndarray, sparsity: float | None = None,
              memory_dtype: str = "float32") -> RouteMemory:
        """Encode a demonstrated route once.

        Args:
            frames: uint8 ``[n, H, W, 3]``, the route's first-person frames.
            actions: ``[n]``, the demonstrated actions (0 forward, 1 left, 2 right).
            sparsity: fraction of the frames kept, in ``(0, 1]`` (default: the export's).
            memory_dtype: ``"float32"``, ``"float16"`` or ``"int8"``: how the features are kept.

        Raises:
            ValueError: frames or actions of the wrong shape, type or values, a sparsity outside ``(0, 1]``,
                an unknown ``memory_dtype``.
        """
        frames, actions = np.asarray(frames), np.asarray(actions)
        if frames.dtype != np.uint8 or frames.ndim != 4 or tuple(frames.shape[1:]) != (*self.image_size, 3):
            raise ValueError(f"frames must be uint8 [n, {self.image_size[0]}, {self.image_size[1]}, 3], got "
                             f"{frames.dtype} {list(frames.shape)}")
        n = frames.shape[0]
        if actions.shape != (n,) or n < 2 or not np.issubdtype(actions.dtype, np.integer):
            raise ValueError(f"actions must be integers [n] for the n = {n} frames (n >= 2), got {actions.dtype} {list(actions.shape)}")
        if actions.min() < 0 or actions.max() >= self.num_actions:
            raise ValueError(f"actions must be in 0..{self.num_actions - 1}")
        if memory_dtype not in MEMORY_DTYPES:
            raise ValueError(f"memory_dtype must be one of {MEMORY_DTYPES}, got {memory_dtype!r}")
        if not self.export.uses_memory:  # a model without a visual memory: the actions alone
            empty = np.zeros((0, self.export.memory_width), np.float32)
            return RouteMemory.of(empty, np.zeros(0, np.int64), actions, self.export_id, memory_dtype)
        sparsity = self.sparsity if sparsity is None else float(sparsity)
        if not 0.0 < sparsity <= 1.0:
            raise ValueError(f"sparsity must be in (0, 1], got {sparsity!r}")
        slots = memory_indices(n, sparsity)
        features = self.export.teach_features(frames[slots], actions[slots])
        return RouteMemory.of(features, slots, actions, self.export_id, memory_dtype)

    # ------------------------------------------------------------------ following
    def start(self, memory: RouteMemory) -> None:
        """Begin following ``memory``'s route (the pointer at its start, the hidden state zero).

        Raises:
            ValueError: a memory taught by another export.
        """
        if memory.export_id != self.export_id:
            raise ValueError("this route memory was taught by another export: teach the route again with this one")
        self._state = {
            "memory": memory.dequantized()[None],
            "slot_indices": memory.slot_indices.astype(np.int64)[None],
            "demo_actions": memory.actions.astype(np.int64)[None],
            "route_length": np.array([memory.route_length], dtype=np.int64),
            "eta": np.full(1, self.export.initial_state["eta"], np.float32),
            "hidden": np.full((1, self.hidden_size), self.export.initial_state["hidden"], np.float32),
            **{key: np.full(1, value, np.float32) for key, value in self.export.initial_state.items() if key not in ("eta", "hidden")},
        }

    def step_logits(self, frame: np.ndarray) -> np.ndarray:
        """One step on the current frame (uint8 ``[H, W, 3]``): the action logits ``[A]``; the pointer and
        hidden state move on."""
        if self._state is None:
            raise RuntimeError("call start(memory) before step()")
        frame = np.asarray(frame)
        if frame.dtype != np.uint8 or tuple(frame.shape) != (*self.image_size, 3):
            raise ValueError(f"frame must be uint8 [{self.image_size[0]}, {self.image_size[1]}, 3], got {frame.dtype} {list(frame.shape)}")
        extra = [key for key in self.export.initial_state if key not in ("eta", "hidden")]
        logits, eta, hidden, *carried = self.export.step(frame[None], **self._state)
        self._state["eta"], self._state["hidden"] = eta, hidden
        self._state.update(zip(extra, carried))
        return logits[0]

    def step(self, frame: np.ndarray) -> int:
        """One step: the action to take (0 forward, 1 left, 2 right)."""
        return int(np.argmax(self.step_logits(frame)))

    @property
    def pointer(self) -> float:
        """Where on the route the policy believes it is (route steps)."""
        if self._state is None:
            raise RuntimeError("call start(memory) first")
        return float(self._state["eta"][0])
