"""Tests for spf_rl.modules.encoder."""
from __future__ import annotations

import pytest
import torch

from spf_rl.modules import ImageEncoder


@pytest.mark.parametrize("size", [(16, 16), (64, 64), (24, 32)])
@pytest.mark.parametrize("batch", [(), (2,), (2, 3)])
def test_shapes(size, batch):
    enc = ImageEncoder(feature_dim=12, image_size=size)
    x = torch.randint(0, 256, (*batch, *size, 3), dtype=torch.uint8)
    assert enc(x).shape == (*batch, 12)


def test_uint8_equals_float_scaled():
    torch.manual_seed(0)
    enc = ImageEncoder(feature_dim=8, image_size=(16, 16))
    x = torch.randint(0, 256, (4, 16, 16, 3), dtype=torch.uint8)
    torch.testing.assert_close(enc(x), enc(x.float() / 255.0))


def test_empty_batch():
    enc = ImageEncoder(feature_dim=8, image_size=(16, 16))
    assert enc(torch.zeros(0, 16, 16, 3, dtype=torch.uint8)).shape == (0, 8)


@pytest.mark.parametrize("shape", [(2, 16, 16, 1), (2, 16, 8, 3), (2, 32, 32, 3), (16, 16)])
def test_wrong_shape_raises(shape):
    enc = ImageEncoder(feature_dim=8, image_size=(16, 16))
    with pytest.raises(ValueError, match=r"\[\*, 16, 16, 3\]"):
        enc(torch.zeros(shape, dtype=torch.uint8))


def test_bad_config_raises():
    with pytest.raises(ValueError, match="feature_dim"):
        ImageEncoder(feature_dim=0)
    with pytest.raises(ValueError, match="image_size"):
        ImageEncoder(image_size=(16,))


def test_gradients_reach_all_parameters():
    enc = ImageEncoder(feature_dim=8, image_size=(16, 16))
    enc(torch.rand(3, 16, 16, 3)).sum().backward()
    for name, p in enc.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


if __name__ == "__main__":
    pytest.main([__file__, "--capture", "no", "--exitfirst"])
