"""spf-rl: sparse-memory path following (SPF) as TorchRL components.

Sub-packages: :mod:`spf_rl.modules` (encoder, sparse memory, pointer attention,
policies) and :mod:`spf_rl.metrics` (success, SPL, confidence intervals).
"""
from __future__ import annotations

__version__ = "0.1.0"
