"""Training glue: policy construction, rollout evaluation and the training loops the recipes call."""
from __future__ import annotations
