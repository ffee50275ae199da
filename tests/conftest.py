"""Shared test set-up: headless rendering, a fixed matplotlib back-end, small envs."""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import envs  # noqa: E402,F401  (selects the GL back-end before mujoco opens a context)
