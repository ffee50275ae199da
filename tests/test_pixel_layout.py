"""HWC pixels: shipped checkpoints give the logits they gave on the same frames in CHW.

``tests/data/reference_logits.pt`` holds the logits of every shipped checkpoint on
seeded frames, computed with the CHW code (``tests/data/make_reference_logits.py``
at commit 275dd13). Here the same frames are drawn again, permuted to HWC, and fed
to the current code.
"""
from __future__ import annotations

from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torchrl.modules import set_recurrent_mode

from spf_rl.checkpoint import load_checkpoint
from spf_rl.modules import ImageEncoder
from spf_rl.modules.registry import build_policy

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = torch.load(ROOT / "tests" / "data" / "reference_logits.pt", weights_only=True)
NAMES = sorted(key.split("/", 1)[1] for key in REFERENCE if key.startswith("logits/"))
#: Float tolerance: the HWC view runs the convolutions in channels_last order.
ATOL = 1e-5


def _reference_inputs() -> TensorDict:
    """The frames of make_reference_logits.py, drawn the same way (CHW), returned HWC."""
    generator = torch.Generator().manual_seed(int(REFERENCE["seed"]))
    batch, time, n, size = 2, 4, 30, 64
    pixels = torch.randint(0, 256, (batch, time, 3, size, size), dtype=torch.uint8, generator=generator)
    demo = torch.randint(0, 256, (batch, 1, n, 3, size, size), dtype=torch.uint8, generator=generator)
    demo_actions = torch.randint(0, 3, (batch, 1, n), generator=generator).expand(batch, time, n)
    is_init = torch.zeros(batch, time, 1, dtype=torch.bool)
    is_init[:, 0] = True
    return TensorDict(
        {
            "pixels": pixels.permute(0, 1, 3, 4, 2),
            "demo_frames": demo.expand(batch, time, n, 3, size, size).permute(0, 1, 2, 4, 5, 3),
            "demo_actions": demo_actions,
            "is_init": is_init,
        },
        [batch, time],
    )


def reference_checkpoint(name: str) -> Path:
    """The checkpoint file the reference logits were made from: a checkpoint retrained under
    the current noise keeps its predecessor in ``checkpoints/paper_symmetric/``."""
    kept = ROOT / "checkpoints" / "paper_symmetric" / f"{name}.pt"
    return kept if kept.exists() else ROOT / "checkpoints" / f"{name}.pt"


@pytest.mark.parametrize("name", NAMES)
def test_shipped_checkpoint_logits_unchanged_on_hwc_frames(name: str) -> None:
    checkpoint = load_checkpoint(reference_checkpoint(name))
    policy = build_policy(checkpoint["model_type"], checkpoint["model_config"]).eval()
    policy.load_state_dict(checkpoint["model"])
    td = _reference_inputs()
    for key, spec in policy.make_tensordict_primer().primers.items(True, True):
        td.set(key, spec.zero(td.shape))
    with torch.no_grad(), set_recurrent_mode(True):
        logits = policy(td)["logits"]
    torch.testing.assert_close(logits, REFERENCE[f"logits/{name}"], atol=ATOL, rtol=0)


def test_encoder_refuses_chw_frames_with_a_hint() -> None:
    encoder = ImageEncoder(feature_dim=8, image_size=(16, 16))
    with pytest.raises(ValueError, match="look CHW"):
        encoder(torch.zeros(2, 3, 16, 16, dtype=torch.uint8))
