"""Shared test set-up: headless rendering, a fixed matplotlib back-end, small envs."""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import envs  # noqa: E402,F401  (selects the GL back-end before mujoco opens a context)
from torch import nn  # noqa: E402

from spf_rl.modules.encoder import ImageEncoder  # noqa: E402


class CountingEncoder(nn.Module):
    """Wraps an encoder and counts the frames it encodes (tests of encode-once memory)."""

    def __init__(self, encoder: ImageEncoder):
        super().__init__()
        self.inner = encoder
        self.feature_dim = encoder.feature_dim
        self.frames = 0

    def check_frames(self, frames, name="frames"):
        self.inner.check_frames(frames, name)

    def forward(self, x):
        self.frames += x.reshape(-1, *x.shape[-3:]).shape[0]
        return self.inner(x)
