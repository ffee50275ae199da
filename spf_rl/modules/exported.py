"""An exported policy (:mod:`spf_rl.export`) run by ONNX Runtime inside the TorchRL world: a TensorDict
module over a batch of agents, with its recurrent state primed like the eager policy's, so that
:func:`~spf_rl.evaluation.evaluate_policy` and ``recipes/evaluate.py DIR`` play it through exactly the
episodes the eager policy plays. It needs the runtime (``pip install ./runtime``, the ``deploy`` extra).
"""
from __future__ import annotations

import os

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Unbounded
from torchrl.envs import TensorDictPrimer

from spf_rl.modules.memory import memory_indices, memory_length

#: The recurrent state an exported policy carries between steps (its primer zeroes it at every reset).
MEMORY_KEY, SLOTS_KEY, ETA_KEY, HIDDEN_KEY = "exported_memory", "exported_slots", "exported_eta", "exported_hidden"
#: The further state of an export with a start check (set to the manifest's initial value where ``is_init``).
START_KEY = "exported_start_match"


def is_export(path: str | os.PathLike) -> bool:
    """Whether ``path`` is an export directory (:mod:`spf_rl.export`: a ``manifest.json`` beside ``step.onnx``).

    Examples:
        >>> is_export("checkpoints")
        False
    """
    from pathlib import Path

    return (Path(path) / "manifest.json").is_file() and (Path(path) / "step.onnx").is_file()


class ExportedPolicy(TensorDictModuleBase):
    """An export directory as a TorchRL policy: reads ``pixels``, ``demo_frames`` (where ``is_init``),
    ``demo_actions``, ``is_init`` and, for padded routes, ``demo_steps``; writes ``logits`` and its next state.

    Where ``is_init``, it teaches the row's route (the kept frames of :func:`~spf_rl.modules.memory.memory_indices`
    at the export's sparsity, or ``sparsity``) and starts the pointer and hidden state at zero, as the eager
    policy does; then it steps every row through the step graph at once.

    Args:
        directory: an export directory (``recipes/export.py``).
        demo_length: the routes' (padded) length the env emits (default: the model's).
        sparsity: the sparsity a route is taught at (default: the export's).
        threads: ONNX Runtime's intra-op threads.
        memory_dtype: how a taught route's features are kept (``"float32"``, ``"float16"``, ``"int8"``:
            :class:`spf_rl_runtime.RouteMemory`), then read back, as a robot keeping them so would.

    Examples:
        >>> policy = ExportedPolicy("exports/spf-s0.8")  # doctest: +SKIP
        >>> summary, _ = evaluate_policy(policy, EvalConfig(...))  # doctest: +SKIP
    """

    def __init__(self, directory: str | os.PathLike, demo_length: int | None = None, sparsity: float | None = None,
                 threads: int = 1, memory_dtype: str = "float32") -> None:
        super().__init__()
        from spf_rl_runtime import MEMORY_DTYPES, Export

        if memory_dtype not in MEMORY_DTYPES:
            raise ValueError(f"memory_dtype must be one of {MEMORY_DTYPES}, got {memory_dtype!r}")
        if sparsity is not None and not 0.0 < float(sparsity) <= 1.0:
            raise ValueError(f"sparsity must be in (0, 1], got {sparsity!r}")
        self.export = Export(directory, threads)
        self.directory, self.threads, self.memory_dtype = str(directory), threads, memory_dtype
        self.demo_length = int(demo_length or self.export.demo_length)
        self.sparsity = float(sparsity if sparsity is not None else (self.export.sparsity or 1.0))
        self.slots = memory_length(self.demo_length, self.sparsity) if self.export.uses_memory else 1
        #: Read where ``is_init`` only (:func:`~spf_rl.evaluation.frames_lookup`): the memory is taught then.
        self.memory_key, self.is_init_key = MEMORY_KEY, "is_init"
        #: The step's further state (``start_match``, with a start check) and its value at a route's start.
        self.extra_state = {key: value for key, value in self.export.initial_state.items() if key not in ("eta", "hidden")}
        if set(self.extra_state) - {"start_match"}:
            raise ValueError(f"{directory}: a step state this module does not know: {sorted(self.extra_state)}")
        extra = [START_KEY] if self.extra_state else []
        self.in_keys = ["pixels", "demo_frames", "demo_actions", "is_init", MEMORY_KEY, SLOTS_KEY, ETA_KEY, HIDDEN_KEY,
                        *extra, "demo_steps"]  # demo_steps optional, as the eager policy's: padded routes' own lengths
        self.out_keys = ["logits", ("next", MEMORY_KEY), ("next", SLOTS_KEY), ("next", ETA_KEY), ("next", HIDDEN_KEY)] + [
            ("next", key) for key in extra]

    def __getstate__(self) -> dict:  # ONNX Runtime's sessions do not pickle: a copy loads the directory again
        return {"directory": self.directory, "demo_length": self.demo_length, "sparsity": self.sparsity, "threads": self.threads,
                "memory_dtype": self.memory_dtype}

    def __setstate__(self, state: dict) -> None:
        self.__init__(**state)

    @property
    def model_type(self) -> str:
        """The exported checkpoint's model type (``"spf"``, ``"spf_random"``, ...)."""
        return self.export.manifest["model_type"]

    @property
    def config(self):
        """The exported model's :class:`~spf_rl.modules.SPFConfig`, at the routes' length this module plays."""
        from spf_rl.modules.config import SPFConfig

        config = dict(self.export.manifest["model_config"])
        config["image_size"] = tuple(config["image_size"])
        if config.get("sparsity_range") is not None:
            config["sparsity_range"] = tuple(config["sparsity_range"])
        return SPFConfig(**{**config, "demo_length": self.demo_length})

    def at_length(self, demo_length: int) -> ExportedPolicy:
        """The same export for routes of ``demo_length`` steps (:func:`~spf_rl.modules.views.policy_for_length`)."""
        return ExportedPolicy(self.directory, demo_length, self.sparsity, self.threads, self.memory_dtype)

    def set_sparsity(self, sparsity: float) -> ExportedPolicy:
        """Teach routes at ``sparsity`` from now on (a random-sparsity model's; any export reads any sparsity)."""
        if not 0.0 < float(sparsity) <= 1.0:
            raise ValueError(f"sparsity must be in (0, 1], got {sparsity!r}")
        self.sparsity = float(sparsity)
        self.slots = memory_length(self.demo_length, self.sparsity) if self.export.uses_memory else 1
        return self

    def cache_identity(self) -> dict:
        """What decides this module's actions, for :func:`~spf_rl.records_cache.policy_sha256`: the export's
        step graph (its SHA-256, which the manifest ties to the teach graph's), the sparsity and the memory's precision."""
        return {"export": self.export.manifest["files"], "sparsity": self.sparsity, "memory_dtype": self.memory_dtype,
                "demo_length": self.demo_length}

    def make_tensordict_primer(self) -> TensorDictPrimer:
        """Primer for the recurrent state (zeroed at every (partial) reset)."""
        specs = {
            MEMORY_KEY: Unbounded(shape=(self.slots, self.export.memory_width)),
            SLOTS_KEY: Unbounded(shape=(self.slots,), dtype=torch.long),
            ETA_KEY: Unbounded(shape=(1,)),
            HIDDEN_KEY: Unbounded(shape=(self.export.hidden_size,)),
            **({START_KEY: Unbounded(shape=(1,))} if self.extra_state else {}),
        }
        return TensorDictPrimer(specs, expand_specs=True)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        batch = tensordict.batch_size
        flat = tensordict.reshape(-1)
        rows = flat.batch_size[0]
        actions = flat.get("demo_actions").reshape(rows, -1).long()
        lengths = (flat.get("demo_steps").reshape(rows).long() if "demo_steps" in flat.keys()
                   else torch.full((rows,), actions.shape[-1], dtype=torch.long))
        is_init = flat.get("is_init").reshape(rows).bool()
        memory = flat.get(MEMORY_KEY, None)
        slots = flat.get(SLOTS_KEY, None)
        eta = flat.get(ETA_KEY, None)
        hidden = flat.get(HIDDEN_KEY, None)
        start = flat.get(START_KEY, None) if self.extra_state else None
        if memory is None:  # no primer (a bare env): every row starts now
            memory = torch.zeros(rows, self.slots, self.export.memory_width)
            slots = torch.zeros(rows, self.slots, dtype=torch.long)
            eta, hidden = torch.zeros(rows, 1), torch.zeros(rows, self.export.hidden_size)
            is_init = torch.ones(rows, dtype=torch.bool)
        if self.extra_state and start is None:  # set where is_init, below
            start = torch.zeros(rows, 1)
        memory, slots, eta, hidden = memory.clone(), slots.clone(), eta.clone(), hidden.clone()
        start = None if start is None else start.clone()
        starting = is_init.nonzero().flatten().tolist()
        if starting:
            frames = flat.get("demo_frames") if self.export.uses_memory else None
            for row in starting:  # teach each new route once
                eta[row], hidden[row] = self.export.initial_state["eta"], self.export.initial_state["hidden"]
                if start is not None:
                    start[row] = self.extra_state["start_match"]
                slots[row] = -1
                if frames is None:
                    continue
                kept = memory_indices(int(lengths[row]), self.sparsity)
                features = self.export.teach_features(frames[row, kept].cpu().numpy(), actions[row, kept].numpy())
                if self.memory_dtype != "float32":  # kept as a robot keeps it, read back
                    from spf_rl_runtime import RouteMemory

                    features = RouteMemory.of(features, kept.numpy(), actions[row].numpy(), self.export.export_id,
                                              self.memory_dtype).dequantized()
                memory[row] = 0.0
                memory[row, : kept.numel()] = torch.from_numpy(features)
                slots[row, : kept.numel()] = kept
        logits, eta_next, hidden_next, *carried = self.export.step(
            flat.get("pixels").reshape(rows, *self.export.image_size, 3).cpu().numpy(),
            memory.numpy().astype(np.float32), slots.numpy(), actions.numpy(), lengths.numpy(),
            eta.reshape(rows).numpy().astype(np.float32), hidden.numpy().astype(np.float32),
            **({} if start is None else {"start_match": start.reshape(rows).numpy().astype(np.float32)}),
        )
        out = {
            "logits": torch.from_numpy(logits),
            ("next", MEMORY_KEY): memory,
            ("next", SLOTS_KEY): slots,
            ("next", ETA_KEY): torch.from_numpy(eta_next).reshape(rows, 1),
            ("next", HIDDEN_KEY): torch.from_numpy(hidden_next),
            **({("next", START_KEY): torch.from_numpy(carried[0]).reshape(rows, 1)} if start is not None else {}),
        }
        for key, value in out.items():
            tensordict.set(key, value.reshape(*batch, *value.shape[1:]))
        return tensordict
