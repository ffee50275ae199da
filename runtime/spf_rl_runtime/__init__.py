"""spf-rl's runtime: follow a route taught once with an exported policy (numpy and ONNX Runtime only).

Examples:
    >>> from spf_rl_runtime import ACTIONS, memory_indices
    >>> ACTIONS, memory_indices(10, 0.5).tolist()
    (('forward', 'left', 'right'), [0, 2, 4, 7, 9])
"""
from spf_rl_runtime.follower import ACTIONS, EXPORT_FORMAT_VERSION, Export, Follower
from spf_rl_runtime.route_memory import MEMORY_DTYPES, MEMORY_FORMAT_VERSION, RouteMemory, memory_indices, memory_length

__all__ = ["ACTIONS", "EXPORT_FORMAT_VERSION", "Export", "Follower", "MEMORY_DTYPES", "MEMORY_FORMAT_VERSION", "RouteMemory",
           "memory_indices", "memory_length"]
