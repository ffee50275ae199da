"""What a robot keeps of a taught route: the kept frames' memory features (float32, float16 or int8 with
one scale per slot), the kept frames' route steps and the route's actions, and the identity of the export
that made it. Nothing of the frames themselves is kept.

The byte layout (:meth:`RouteMemory.to_bytes`, little-endian): a 52-byte header (``b"SPFM"``, the format
version, the features' dtype code, the route length ``n``, the number of slots ``l``, the feature size ``D``,
the export's 32-byte identity), then the features ``[l, D]``, the per-slot scales ``[l]`` (float32, int8
only), the slots' route steps ``[l]`` (uint16) and the actions ``[n]`` (uint8).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

#: Version of the byte layout.
MEMORY_FORMAT_VERSION = 1
#: Precisions a memory's features may be kept in.
MEMORY_DTYPES = ("float32", "float16", "int8")
_MAGIC = b"SPFM"
_HEADER = struct.Struct("<4sHBxIII32s")
_INT8_MAX = 127.0


def memory_length(n: int, sparsity: float) -> int:
    """The number of frames a route of ``n`` steps keeps at ``sparsity``: ``max(1, round(sparsity * n))``
    (Python's rounding, half to even), as spf-rl's ``spf_rl.modules.memory.memory_length``.

    Examples:
        >>> memory_length(30, 0.4), memory_length(5, 0.1)
        (12, 1)
    """
    return max(1, min(n, round(sparsity * n)))


def memory_indices(n: int, sparsity: float) -> np.ndarray:
    """The route steps ``M*`` of the kept frames: ``round(i * (n - 1) / (l - 1))`` for ``i < l =
    memory_length(n, sparsity)``, exact in integers, half to even, as spf-rl's
    ``spf_rl.modules.memory.memory_indices``.

    Examples:
        >>> memory_indices(30, 0.2).tolist()
        [0, 6, 12, 17, 23, 29]
    """
    length = memory_length(n, sparsity)
    if length == 1:
        return np.zeros(1, dtype=np.int64)
    numerator = np.arange(length, dtype=np.int64) * (n - 1)
    quotient, remainder = np.divmod(numerator, length - 1)
    up = (2 * remainder > length - 1) | ((2 * remainder == length - 1) & (quotient % 2 == 1))
    return quotient + up.astype(np.int64)


@dataclass(frozen=True)
class RouteMemory:
    """A taught route as a robot keeps it (made by :meth:`spf_rl_runtime.Follower.teach`).

    Examples:
        >>> features = np.array([[0.5, -1.0], [2.0, 0.25]], dtype=np.float32)
        >>> memory = RouteMemory.of(features, np.array([0, 3]), np.array([0, 1, 2, 0]), "ab" * 32, "int8")
        >>> memory.nbytes, RouteMemory.from_bytes(memory.to_bytes()) == memory
        (72, True)
        >>> bool(np.abs(memory.dequantized() - features).max() < 0.01)
        True
    """

    features: np.ndarray
    scales: np.ndarray | None
    slot_indices: np.ndarray
    actions: np.ndarray
    export_id: str
    dtype: str

    @classmethod
    def of(cls, features: np.ndarray, slot_indices: np.ndarray, actions: np.ndarray, export_id: str,
           dtype: str = "float32") -> RouteMemory:
        """Keep float32 ``features`` ``[l, D]`` in ``dtype`` (int8: symmetric, one scale per slot)."""
        if dtype not in MEMORY_DTYPES:
            raise ValueError(f"memory_dtype must be one of {MEMORY_DTYPES}, got {dtype!r}")
        if len(export_id) != 64 or any(c not in "0123456789abcdef" for c in export_id):
            raise ValueError(f"export_id must be a SHA-256 in 64 lowercase hex digits, got {export_id!r}")
        features = np.asarray(features, dtype=np.float32)
        if not np.isfinite(features).all():
            raise ValueError("the route's memory features are not finite")
        if dtype == "float16" and features.size and np.abs(features).max() > np.finfo(np.float16).max:
            raise ValueError("the route's memory features exceed float16's range: keep them as float32 or int8")
        scales = None
        if dtype == "int8":
            peak = np.abs(features).max(axis=-1) if features.size else np.zeros(features.shape[0], np.float32)
            scales = np.where(peak > 0, peak / _INT8_MAX, 1.0).astype(np.float32)
            kept = np.clip(np.rint(features / scales[:, None]), -_INT8_MAX, _INT8_MAX).astype(np.int8)
        else:
            kept = features.astype(dtype)
        return cls(kept, scales, np.asarray(slot_indices, dtype=np.uint16), np.asarray(actions, dtype=np.uint8),
                   export_id, dtype)

    @property
    def route_length(self) -> int:
        """The route's number of steps ``n``."""
        return int(self.actions.shape[0])

    @property
    def nbytes(self) -> int:
        """Bytes this memory takes (:meth:`to_bytes`' length): what a robot keeps for the route."""
        scales = 0 if self.scales is None else self.scales.nbytes
        return _HEADER.size + self.features.nbytes + scales + self.slot_indices.nbytes + self.actions.nbytes

    def dequantized(self) -> np.ndarray:
        """The features as float32 ``[l, D]``, as the step graph reads them."""
        features = self.features.astype(np.float32)
        return features * self.scales[:, None] if self.scales is not None else features

    def to_bytes(self) -> bytes:
        """The memory in the byte layout of this module."""
        slots, width = self.features.shape
        header = _HEADER.pack(_MAGIC, MEMORY_FORMAT_VERSION, MEMORY_DTYPES.index(self.dtype), self.route_length,
                              slots, width, bytes.fromhex(self.export_id))
        scales = b"" if self.scales is None else self.scales.astype("<f4").tobytes()
        features = self.features.astype(np.dtype(self.dtype).newbyteorder("<"))
        return b"".join([header, features.tobytes(), scales, self.slot_indices.astype("<u2").tobytes(),
                         self.actions.astype(np.uint8).tobytes()])

    @classmethod
    def from_bytes(cls, data: bytes) -> RouteMemory:
        """A memory from :meth:`to_bytes`' layout.

        Raises:
            ValueError: not a route memory, another format version, or a truncated one.
        """
        if len(data) < _HEADER.size or data[:4] != _MAGIC:
            raise ValueError("not a route memory (no SPFM header)")
        _, version, code, n, slots, width, export_id = _HEADER.unpack_from(data)
        if version != MEMORY_FORMAT_VERSION:
            raise ValueError(f"route memory format version {version}; this runtime reads {MEMORY_FORMAT_VERSION}")
        if code >= len(MEMORY_DTYPES):
            raise ValueError(f"route memory of an unknown feature precision (code {code})")
        dtype = MEMORY_DTYPES[code]
        itemsize = np.dtype(dtype).itemsize
        sizes = [slots * width * itemsize, slots * 4 if dtype == "int8" else 0, slots * 2, n]
        if len(data) != _HEADER.size + sum(sizes):
            raise ValueError(f"route memory of {len(data)} bytes, its header says {_HEADER.size + sum(sizes)}")
        offset = _HEADER.size
        parts = []
        for size in sizes:
            parts.append(data[offset:offset + size])
            offset += size
        features = np.frombuffer(parts[0], dtype=np.dtype(dtype).newbyteorder("<")).astype(dtype).reshape(slots, width)
        scales = np.frombuffer(parts[1], dtype="<f4").astype(np.float32) if dtype == "int8" else None
        return cls(features, scales, np.frombuffer(parts[2], dtype="<u2").astype(np.uint16),
                   np.frombuffer(parts[3], dtype=np.uint8).copy(), export_id.hex(), dtype)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, RouteMemory):
            return NotImplemented
        same_scales = (self.scales is None and other.scales is None) or (
            self.scales is not None and other.scales is not None and np.array_equal(self.scales, other.scales))
        return (self.dtype == other.dtype and self.export_id == other.export_id and same_scales
                and np.array_equal(self.features, other.features) and np.array_equal(self.slot_indices, other.slot_indices)
                and np.array_equal(self.actions, other.actions))

    __hash__ = None
