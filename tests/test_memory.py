"""Tests for spf_rl.modules.memory."""
from __future__ import annotations

import pytest
import torch

from spf_rl.modules import (
    ImageEncoder,
    MemoryEncoder,
    memory_bytes,
    memory_indices,
    memory_length,
    memory_mask,
    validate_sparsity_range,
)

EXPECTED_N30 = {
    0.2: [0, 6, 12, 17, 23, 29],
    0.4: [0, 3, 5, 8, 11, 13, 16, 18, 21, 24, 26, 29],
    0.6: [0, 2, 3, 5, 7, 9, 10, 12, 14, 15, 17, 19, 20, 22, 24, 26, 27, 29],
    0.8: [0, 1, 3, 4, 5, 6, 8, 9, 10, 11, 13, 14, 15, 16, 18, 19, 20, 21, 23, 24, 25, 26, 28, 29],
    1.0: list(range(30)),
}


@pytest.mark.parametrize("sparsity", sorted(EXPECTED_N30))
def test_memory_indices_n30(sparsity):
    idx = memory_indices(30, sparsity)
    assert idx.dtype == torch.long
    assert idx.tolist() == EXPECTED_N30[sparsity]
    assert memory_length(30, sparsity) == len(EXPECTED_N30[sparsity])


@pytest.mark.parametrize("n", [1, 2, 5, 7, 30, 31])
@pytest.mark.parametrize("sparsity", [0.01, 0.1, 0.33, 0.5, 0.9, 1.0])
def test_memory_indices_properties(n, sparsity):
    idx = memory_indices(n, sparsity).tolist()
    l = max(1, round(sparsity * n))
    assert len(idx) == l == len(set(idx))
    assert idx == sorted(idx)
    assert idx[0] == 0
    if l > 1:
        assert idx[-1] == n - 1
    assert all(0 <= i < n for i in idx)


def test_memory_bytes():
    # 12 frames of 3*64*64 uint8 + 30 one-byte actions
    assert memory_bytes(30, 0.4) == 12 * 3 * 64 * 64 + 30
    assert memory_bytes(30, 1.0, frame_shape=(16, 16, 3), bytes_per_pixel=4, bytes_per_action=8) == (
        30 * 3 * 16 * 16 * 4 + 30 * 8
    )
    assert memory_bytes(30, 0.01) == 3 * 64 * 64 + 30  # at least one frame


@pytest.mark.parametrize("sparsity", [0, 0.0, 1.5, -0.1, float("nan"), "0.5", None, True])
def test_bad_sparsity_raises(sparsity):
    with pytest.raises(ValueError, match=r"sparsity must be a number in the range \(0, 1\]"):
        memory_indices(30, sparsity)


@pytest.mark.parametrize("n", [0, -3, 2.5])
def test_bad_n_raises(n):
    with pytest.raises(ValueError, match="n .*positive int"):
        memory_indices(n, 0.5)


def test_memory_encoder_gathers_and_encodes():
    torch.manual_seed(0)
    enc = ImageEncoder(feature_dim=8, image_size=(16, 16))
    idx = memory_indices(10, 0.3)  # [0, 4, 9] (4.5 rounds half to even)
    assert idx.tolist() == [0, 4, 9]
    mem = MemoryEncoder(enc, idx)
    demo = torch.randint(0, 256, (2, 10, 16, 16, 3), dtype=torch.uint8)
    out = mem(demo)
    assert out.shape == (2, 3, 8)
    torch.testing.assert_close(out, enc(demo[:, [0, 4, 9]]))
    # row selection on an expanded [B, T, n, ...] view encodes only the chosen rows
    expanded = demo.unsqueeze(1).expand(2, 5, *demo.shape[1:])
    rows = (torch.tensor([1, 0]), torch.tensor([3, 2]))
    sel = mem(expanded, rows)
    torch.testing.assert_close(sel, enc(demo[[1, 0]][:, [0, 4, 9]]))


def test_memory_longer_than_demo_raises():
    enc = ImageEncoder(feature_dim=8, image_size=(16, 16))
    mem = MemoryEncoder(enc, memory_indices(30, 0.4))
    with pytest.raises(ValueError, match="memory longer than the demo"):
        mem(torch.zeros(1, 20, 16, 16, 3, dtype=torch.uint8))


if __name__ == "__main__":
    pytest.main([__file__, "--capture", "no", "--exitfirst"])


@pytest.mark.parametrize("sparsity", sorted(EXPECTED_N30))
def test_memory_mask_is_true_at_memory_indices(sparsity):
    mask = memory_mask(30, sparsity)
    assert mask.dtype == torch.bool and mask.shape == (30,)
    assert mask.nonzero().squeeze(-1).tolist() == EXPECTED_N30[sparsity]


def test_sparsity_range_validation():
    assert validate_sparsity_range([0.2, 1]) == (0.2, 1.0)
    assert validate_sparsity_range((0.5, 0.5)) == (0.5, 0.5)
    for bad in [(0.0, 1.0), (0.6, 0.4), (0.2, 1.1), (0.5,), (0.2, 0.5, 1.0), "0.2-1", (0.2, float("nan")), (True, 1.0), None]:
        with pytest.raises(ValueError, match=r"sparsity_range must be a pair \(low, high\)"):
            validate_sparsity_range(bad)
