"""Tests for spf_rl.modules.attention (eq. 2 of the paper on hand-made inputs)."""
from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from spf_rl.modules import PointerAttention, action_window, attention_weights, soft_action_memory


def _onehot(a, c=3):
    v = [0.0] * c
    if a is not None:
        v[a] = 1.0
    return v


def test_weights_match_formula_fractional_eta():
    idx = torch.tensor([0, 3, 6, 9])
    eta = torch.tensor([[0.0], [4.25], [10.5]])
    w = attention_weights(eta, idx)
    expected = [
        [math.exp(-abs(e - m)) for m in (0, 3, 6, 9)] for e in (0.0, 4.25, 10.5)
    ]
    torch.testing.assert_close(w, torch.tensor(expected))
    # un-normalised: the weights do not sum to one
    assert not torch.allclose(w.sum(-1), torch.ones(3))


def test_window_padding_both_ends_and_floor():
    acts = torch.tensor([[2, 0, 1, 1, 0, 2]]).expand(4, 6)  # n = 6
    eta = torch.tensor([[0.0], [1.7], [5.9], [-3.2]])
    win = action_window(acts, eta, k=2, num_classes=3)
    assert win.shape == (4, 5, 3)
    seq = [2, 0, 1, 1, 0, 2]

    def expected(centre):
        return [_onehot(seq[p] if 0 <= p < 6 else None) for p in range(centre - 2, centre + 3)]

    # eta 0 -> positions -2..2 (two padded), 1.7 -> floor 1 -> -1..3 (one padded),
    # 5.9 -> 5 -> 3..7 (two padded), -3.2 -> floor clamped to 0
    torch.testing.assert_close(win[0], torch.tensor(expected(0)))
    torch.testing.assert_close(win[1], torch.tensor(expected(1)))
    torch.testing.assert_close(win[2], torch.tensor(expected(5)))
    torch.testing.assert_close(win[3], torch.tensor(expected(0)))
    assert win[0, :2].sum() == 0 and win[2, 3:].sum() == 0


def test_window_beyond_end_clamped():
    acts = torch.tensor([[0, 1, 2]])
    win = action_window(acts, torch.tensor([[7.5]]), k=1, num_classes=4)
    torch.testing.assert_close(win[0], torch.tensor([_onehot(1, 4), _onehot(2, 4), _onehot(None, 4)]))


def test_forward_is_psi_of_concat():
    torch.manual_seed(0)
    att = PointerAttention(feature_dim=4, out_dim=5, k=1, num_action_classes=3)
    mem = torch.randn(2, 3, 4)
    idx = torch.tensor([0, 2, 4])
    acts = torch.tensor([[0, 1, 2, 0, 1], [2, 2, 1, 0, 0]])
    eta = torch.tensor([[1.5], [3.0]])
    w, win = att.weights_and_window(idx, acts, eta)
    attended = torch.stack(
        [sum(math.exp(-abs(eta[b, 0].item() - m)) * mem[b, j] for j, m in enumerate((0, 2, 4))) for b in range(2)]
    )
    torch.testing.assert_close((w.unsqueeze(-1) * mem).sum(1), attended)
    expected = att.psi(torch.cat([attended, win.flatten(-2)], -1))
    mu, win2 = att(mem, idx, acts, eta, return_window=True)
    torch.testing.assert_close(mu, expected)
    torch.testing.assert_close(win2, win)
    # window for eta=1.5 (floor 1, k=1): actions at 0, 1, 2
    torch.testing.assert_close(win[0], torch.tensor([_onehot(0), _onehot(1), _onehot(2)]))


def test_action_only():
    att = PointerAttention(feature_dim=4, out_dim=5, k=2, action_only=True)
    assert att.psi.in_features == 5 * 3
    acts = torch.randint(0, 3, (2, 6))
    eta = torch.zeros(2, 1)
    w, win = att.weights_and_window(None, acts, eta)
    assert w is None
    torch.testing.assert_close(att(None, None, acts, eta), att.psi(win.flatten(-2)))


def test_soft_action_memory_formula():
    acts = torch.tensor([[2, 0, 1, 1, 0, 2], [0, 0, 0, 0, 0, 0]])  # n = 6
    eta = torch.tensor([[1.5], [-2.0]])
    out = soft_action_memory(acts, eta, 3)
    assert out.shape == (2, 3)
    expected = torch.zeros(2, 3)
    for b in range(2):
        for j in range(6):
            expected[b, acts[b, j]] += math.exp(-abs(eta[b, 0].item() - j))
    torch.testing.assert_close(out, expected)
    # hand values, eta = 1.5: class 0 at j = 1, 4; class 1 at j = 2, 3; class 2 at j = 0, 5
    e = math.exp
    torch.testing.assert_close(
        out[0], torch.tensor([e(-0.5) + e(-2.5), e(-0.5) + e(-1.5), e(-1.5) + e(-3.5)])
    )
    # un-normalised (same weights as eq. 2 with indices 0..n-1); 4 classes pads a zero column
    torch.testing.assert_close(out, (attention_weights(eta, torch.arange(6)).unsqueeze(-1) * F.one_hot(acts, 3)).sum(1))
    assert soft_action_memory(acts, eta, 4)[:, 3].abs().sum() == 0


@pytest.mark.parametrize("action_only", [True, False])
def test_psi_takes_soft_action_memory(action_only):
    torch.manual_seed(0)
    att = PointerAttention(feature_dim=4, out_dim=5, k=1, action_only=action_only, soft_action_memory=True)
    assert att.psi.in_features == (0 if action_only else 4) + 3 * 3 + 3
    mem = None if action_only else torch.randn(2, 3, 4)
    idx = None if action_only else torch.tensor([0, 2, 4])
    acts = torch.tensor([[0, 1, 2, 0, 1], [2, 2, 1, 0, 0]])
    eta = torch.tensor([[1.5], [3.0]], requires_grad=True)
    w, win = att.weights_and_window(idx, acts, eta)
    parts = [] if action_only else [(w.unsqueeze(-1) * mem).sum(1)]
    parts += [win.flatten(-2), soft_action_memory(acts, eta, 3)]
    mu = att(mem, idx, acts, eta)
    torch.testing.assert_close(mu, att.psi(torch.cat(parts, -1)))
    # eta gets a gradient even without visual memory
    mu.sum().backward()
    assert eta.grad is not None and (eta.grad.abs() > 0).all()


def test_gradient_wrt_eta_through_soft_weights():
    att = PointerAttention(feature_dim=4, out_dim=3)
    eta = torch.tensor([[1.3]], requires_grad=True)
    att(torch.randn(1, 2, 4), torch.tensor([0, 5]), torch.zeros(1, 6, dtype=torch.long), eta).sum().backward()
    assert eta.grad is not None and eta.grad.abs().item() > 0


def test_bad_args():
    with pytest.raises(ValueError, match="k"):
        PointerAttention(4, 4, k=-1)
    with pytest.raises(ValueError, match="num_action_classes"):
        PointerAttention(4, 4, num_action_classes=0)
    att = PointerAttention(4, 4)
    with pytest.raises(ValueError, match="memory_features"):
        att(None, torch.tensor([0]), torch.zeros(1, 3, dtype=torch.long), torch.zeros(1, 1))


if __name__ == "__main__":
    pytest.main([__file__, "--capture", "no", "--exitfirst"])


def test_mask_zeroes_weights_and_hides_masked_features():
    idx = torch.arange(5)
    eta = torch.tensor([[1.3], [3.0]])
    mask = torch.tensor([[True, False, True, False, True], [False, True, True, True, False]])
    w = attention_weights(eta, idx, mask)
    assert (w[~mask] == 0).all()
    torch.testing.assert_close(w[mask], attention_weights(eta, idx)[mask], rtol=0, atol=0)
    att = PointerAttention(feature_dim=4, out_dim=6)
    acts = torch.randint(0, 3, (2, 5))
    mem = torch.randn(2, 5, 4)
    noisy = torch.where(mask.unsqueeze(-1), mem, 1e3 * torch.randn(2, 5, 4))
    assert torch.equal(att(mem, idx, acts, eta, mask=mask), att(noisy, idx, acts, eta, mask=mask))
    assert not torch.allclose(att(mem, idx, acts, eta), att(noisy, idx, acts, eta))
    # a mask shared by the batch ([l]) broadcasts
    torch.testing.assert_close(att(mem, idx, acts, eta, mask=mask[0]), att(mem[:, ::2], idx[::2], acts, eta))
