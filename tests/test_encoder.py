"""Tests for spf_rl.modules.encoder."""
from __future__ import annotations

import pytest
import torch

from spf_rl.modules import ImageEncoder, SPFConfig
from spf_rl.modules.encoder import FRAME_REFERENCE_MEAN, normalize_frames
from spf_rl.modules.registry import build_policy
from spf_rl.train.dagger import start_policy


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


def test_a_normalising_encoder_does_not_see_a_change_of_exposure_or_light_colour():
    torch.manual_seed(0)
    raw, normalising = ImageEncoder(feature_dim=8, image_size=(16, 16)), ImageEncoder(feature_dim=8, image_size=(16, 16), normalize=True)
    normalising.load_state_dict(raw.state_dict())  # no weights of its own
    frames = torch.rand(4, 16, 16, 3) * 0.8 + 0.1
    changed = frames * torch.tensor([0.3, 0.25, 0.21]) + 0.02  # 30% of the light, warm, a little ambient
    scale = normalising(frames).abs().max()
    assert (normalising(frames) - normalising(changed)).abs().max() < 0.02 * scale
    assert (raw(frames) - raw(changed)).abs().max() > 0.1 * raw(frames).abs().max()  # the raw encoder sees it


def test_a_uniform_frame_is_the_reference_mean_and_every_output_is_finite():
    frames = torch.zeros(2, 3, 8, 8)
    frames[1] = 1.0
    normalised = normalize_frames(frames)
    torch.testing.assert_close(normalised[:, :, 0, 0], torch.tensor([FRAME_REFERENCE_MEAN] * 2))
    encoder = ImageEncoder(feature_dim=8, image_size=(8, 8), normalize=True)
    assert torch.isfinite(encoder(torch.zeros(2, 8, 8, 3, dtype=torch.uint8))).all()


def test_normalize_must_be_a_bool():
    with pytest.raises(ValueError, match="normalize must be True or False"):
        ImageEncoder(normalize=1)
    with pytest.raises(ValueError, match="normalize_frames must be True or False"):
        SPFConfig(normalize_frames="yes")


def test_a_policy_with_normalised_frames_keeps_its_choice_under_a_dimmer_light():
    """The current frame and the memory's are both normalised: a darker, warmer repeat of the same frames
    gives the same logits (close), where the raw network's change."""
    from tensordict import TensorDict

    config = SPFConfig(demo_length=6, feature_dim=8, hidden_size=8, image_size=(16, 16))
    torch.manual_seed(1)
    raw = build_policy("spf", config).eval()
    normalised = start_policy("spf", config, raw.state_dict(), None, 0, normalize_frames=True)[1].eval()
    generator = torch.Generator().manual_seed(2)
    demo = torch.randint(20, 236, (1, 6, 16, 16, 3), dtype=torch.uint8, generator=generator)
    td = TensorDict({"pixels": demo[:, 2], "demo_frames": demo, "demo_actions": torch.zeros(1, 6, dtype=torch.long),
                     "is_init": torch.ones(1, 1, dtype=torch.bool)}, [1])
    dim = td.clone()
    dim["pixels"] = (td["pixels"].float() * torch.tensor([0.5, 0.45, 0.4])).round().to(torch.uint8)  # the repeat alone darker
    with torch.no_grad():
        same = (normalised(td.clone())["logits"] - normalised(dim.clone())["logits"]).abs().max()
        moved = (raw(td.clone())["logits"] - raw(dim.clone())["logits"]).abs().max()
    assert same < 0.1 * moved
    assert normalised.config.to_dict()["normalize_frames"] is True and "normalize_frames" not in raw.config.to_dict()
