"""spf-rl: sparse-memory path following (SPF) as TorchRL components.

Sub-packages: :mod:`spf_rl.modules` (encoder, sparse memory, pointer attention,
policies), :mod:`spf_rl.metrics` (success, SPL, confidence intervals) and
:mod:`spf_rl.train` (behaviour cloning, DAgger, PPO, evaluation).
:func:`load_policy` returns a trained policy by shipped name or path.
"""
from __future__ import annotations

from spf_rl.hub import list_checkpoints, load_policy

__version__ = "0.1.0"

__all__ = ["__version__", "list_checkpoints", "load_policy"]
