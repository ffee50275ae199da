"""Image encoder phi of the SPF policy (paper Sec. 3.1, eq. 3).

A small CNN sized for CPU training on first-person RGB frames (64x64 pixels by
default). The same encoder embeds the current observation ``o_t`` and the
demonstration frames kept in the sparse memory.
"""
from __future__ import annotations

import logging
from collections.abc import Sequence

import torch
from torch import nn

logger = logging.getLogger(__name__)

__all__ = ["FRAME_REFERENCE_MEAN", "FRAME_REFERENCE_STD", "ImageEncoder", "NUM_RGB_CHANNELS", "PIXEL_MAX", "normalize_frames"]

#: Number of colour channels of an RGB frame.
NUM_RGB_CHANNELS = 3
#: Largest value of a uint8 pixel; uint8 frames are divided by it.
PIXEL_MAX = 255.0
#: Default frame size (height, width) in pixels.
DEFAULT_IMAGE_SIZE = (64, 64)
#: Default output size of the encoder.
DEFAULT_FEATURE_DIM = 128
#: Default conv channels: the patchifying layer, then stride-2 3x3 layers.
DEFAULT_CHANNELS = (32, 64, 64)
#: Side of the non-overlapping patches the first convolution reads, pixels. A
#: patchifying first layer keeps activations small, which is what costs time on a CPU
#: (about 2.4x faster than four stride-2 3x3 layers at 64x64, for similar size).
DEFAULT_PATCH_SIZE = 4
#: A normalised frame's per-channel mean and spread (RGB, in [0, 1] units): the mean over frames of a
#: frame's channel mean and of its channel standard deviation, measured on 3,840 demonstration frames of
#: the training houses (64 px). A normalised frame of the teaching world so stays near the range
#: an encoder trained on raw frames reads, which lets it be fine-tuned instead of trained anew.
FRAME_REFERENCE_MEAN = (0.322, 0.276, 0.240)
FRAME_REFERENCE_STD = (0.188, 0.151, 0.151)
#: Added to a frame's channel standard deviation before dividing by it (two grey levels): a uniform
#: frame (a wall seen close up) maps to the reference mean, and every output stays finite.
FRAME_STD_FLOOR = 2.0 / PIXEL_MAX
_KERNEL_SIZE = 3
_STRIDE = 2
_PADDING = 1


def _conv_out(size: int, kernel: int = _KERNEL_SIZE, stride: int = _STRIDE, padding: int = _PADDING) -> int:
    return (size + 2 * padding - kernel) // stride + 1


def normalize_frames(x: torch.Tensor) -> torch.Tensor:
    """Per-frame, per-channel standardisation of NCHW float frames in ``[0, 1]``, mapped to the
    reference mean and spread (:data:`FRAME_REFERENCE_MEAN`, :data:`FRAME_REFERENCE_STD`).

    A change of exposure or of the light's colour that scales (or shifts) a channel of the
    whole frame leaves the result unchanged: the photometric invariance that
    ``SPFConfig.normalize_frames`` gives the encoder. The frame's brightness is lost with it.

    Examples:
        >>> import torch
        >>> frame = torch.rand(1, 3, 8, 8)
        >>> dimmed = frame * torch.tensor([0.3, 0.25, 0.2]).view(1, 3, 1, 1)  # darker and warmer
        >>> bool((normalize_frames(frame) - normalize_frames(dimmed)).abs().max() < 0.05)
        True
        >>> normalize_frames(torch.full((1, 3, 4, 4), 0.7))[0, :, 0, 0]  # a uniform frame: the reference mean
        tensor([0.3220, 0.2760, 0.2400])
    """
    mean = x.mean((-2, -1), keepdim=True)
    std = x.std((-2, -1), keepdim=True)
    reference_mean = x.new_tensor(FRAME_REFERENCE_MEAN).view(-1, 1, 1)
    reference_std = x.new_tensor(FRAME_REFERENCE_STD).view(-1, 1, 1)
    return (x - mean) / (std + FRAME_STD_FLOOR) * reference_std + reference_mean


class ImageEncoder(nn.Module):
    """Small CNN mapping RGB frames ``[*, H, W, 3]`` to features ``[*, feature_dim]``.

    Frames are HWC, as TorchRL's pixel envs emit them (``pixels``, ``demo_frames``
    of :class:`~envs.nav_env.PathFollowEnv`); the encoder permutes them to the
    ``[N, 3, H, W]`` view its convolutions read (channels_last in memory, no copy).

    A patchifying convolution (kernel = stride = ``patch_size``), then stride-2 3x3
    convolutions (ReLU after each), then a linear layer (ReLU).
    uint8 inputs are scaled to ``[0, 1]`` by dividing by 255; floating inputs are
    used as they are (expected in ``[0, 1]``). With ``normalize=True`` each frame is
    then standardised per channel (:func:`normalize_frames`), so that a global change
    of exposure or light colour does not reach the features. Any number of leading
    batch dimensions is accepted.

    Args:
        feature_dim (int, optional): size of the output features. Defaults to 128.
        image_size (tuple of int, optional): expected ``(height, width)`` of the
            frames, in pixels. Defaults to ``(64, 64)``.
        channels (sequence of int, optional): output channels of the conv layers.
            Defaults to ``(32, 64, 64)``.
        patch_size (int, optional): kernel and stride of the first convolution,
            pixels. Defaults to 4.
        normalize (bool, optional): standardise each frame per channel before the
            convolutions (:func:`normalize_frames`). Defaults to ``False`` (the paper's).

    Examples:
        >>> import torch
        >>> from spf_rl.modules import ImageEncoder
        >>> enc = ImageEncoder(feature_dim=32, image_size=(16, 16))
        >>> frames = torch.randint(0, 256, (2, 5, 16, 16, 3), dtype=torch.uint8)
        >>> enc(frames).shape
        torch.Size([2, 5, 32])
        >>> robust = ImageEncoder(feature_dim=32, image_size=(16, 16), normalize=True)
        >>> dim = (frames.float() * 0.4).round().to(torch.uint8)  # the same frames at 40% of the light
        >>> bool((robust(frames) - robust(dim)).abs().max() < 0.05 * robust(frames).abs().max())
        True
    """

    def __init__(
        self,
        feature_dim: int = DEFAULT_FEATURE_DIM,
        image_size: tuple[int, int] = DEFAULT_IMAGE_SIZE,
        channels: Sequence[int] = DEFAULT_CHANNELS,
        patch_size: int = DEFAULT_PATCH_SIZE,
        normalize: bool = False,
    ) -> None:
        super().__init__()
        if not isinstance(feature_dim, int) or feature_dim < 1:
            raise ValueError(f"feature_dim must be a positive int, got {feature_dim!r}.")
        image_size = tuple(image_size)
        if len(image_size) != 2 or any(
            not isinstance(s, int) or s < 1 for s in image_size
        ):
            raise ValueError(
                f"image_size must be a pair of positive ints (height, width) in pixels, got {image_size!r}."
            )
        if len(channels) < 1 or any(c < 1 for c in channels):
            raise ValueError(
                f"channels must be a non-empty sequence of positive ints, got {channels!r}."
            )
        if not isinstance(normalize, bool):
            raise ValueError(f"normalize must be True or False, got {normalize!r}.")
        self.normalize = normalize
        self.feature_dim = feature_dim
        self.image_size: tuple[int, int] = image_size  # type: ignore[assignment]
        layers: list[nn.Module] = []
        in_ch = NUM_RGB_CHANNELS
        h, w = image_size
        if not isinstance(patch_size, int) or patch_size < 1 or patch_size > min(image_size):
            raise ValueError(f"patch_size must be an int in [1, {min(image_size)}] pixels, got {patch_size!r}.")
        for index, out_ch in enumerate(channels):
            if index == 0:
                layers += [nn.Conv2d(in_ch, out_ch, patch_size, stride=patch_size), nn.ReLU()]
                h, w = _conv_out(h, patch_size, patch_size, 0), _conv_out(w, patch_size, patch_size, 0)
            else:
                layers += [nn.Conv2d(in_ch, out_ch, _KERNEL_SIZE, stride=_STRIDE, padding=_PADDING), nn.ReLU()]
                h, w = _conv_out(h), _conv_out(w)
            in_ch = out_ch
        self.conv = nn.Sequential(*layers)
        self.head = nn.Sequential(nn.Linear(in_ch * h * w, feature_dim), nn.ReLU())

    @property
    def frame_shape(self) -> tuple[int, int, int]:
        """The expected frame shape ``(H, W, 3)`` (HWC)."""
        return (*self.image_size, NUM_RGB_CHANNELS)

    def check_frames(self, frames: torch.Tensor, name: str = "frames") -> None:
        """Raise a ``ValueError`` if ``frames`` is not ``[*, H, W, 3]`` with the configured H, W."""
        if frames.ndim < 3 or tuple(frames.shape[-3:]) != self.frame_shape:
            hint = (
                " The frames look CHW: frames are HWC (TorchRL's pixel convention)."
                if tuple(frames.shape[-3:]) == (NUM_RGB_CHANNELS, *self.image_size)
                else " Set image_size to the env's frame size."
            )
            raise ValueError(
                f"{name} must have shape [*, {', '.join(map(str, self.frame_shape))}] "
                f"(height, width, channels), got {tuple(frames.shape)}.{hint}"
            )

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        """Encode HWC ``frames`` of shape ``[*, H, W, 3]`` into ``[*, feature_dim]``."""
        self.check_frames(frames)
        batch_shape = frames.shape[:-3]
        x = frames.reshape(-1, *self.frame_shape).permute(0, 3, 1, 2)
        if x.dtype == torch.uint8:
            # in place: a second frame-sized float tensor costs more than the division
            # (a BC step 1.04x, bit-identical; docs/performance.md)
            x = x.float().div_(PIXEL_MAX)
        elif not x.is_floating_point():
            raise ValueError(f"frames must be uint8 or floating point, got dtype {x.dtype}.")
        if self.normalize:
            x = normalize_frames(x)
        if x.shape[0] == 0:
            out = x.new_zeros(0, self.feature_dim)
        else:
            out = self.head(self.conv(x).flatten(1))
        return out.reshape(*batch_shape, self.feature_dim)
