"""Photometric augmentation of training images: the same lane under other light and optics.

A state network trained on one look learns that look: under new light its error grew
tenfold. Each training image is redrawn, per image, with a brightness offset, a contrast
factor about its mean, a gamma, a gain per channel, pixel noise and (on some images) a 3x3
blur: the changes of ``saferace.envs.randomization``'s looks that leave the geometry alone
(textures and camera pose are not photometric, and stay unseen). The draws come from the
caller's generator, so an ensemble's members, each with its own, see different ones.
"""

from __future__ import annotations

import torch
from torch.nn import functional

#: Ranges of the per-image draws (uniform): brightness offset (of 1), contrast factor,
#: log gamma, channel gain, noise standard deviation (of 1); and the share of blurred images.
BRIGHTNESS = (-0.25, 0.25)
CONTRAST = (0.6, 1.4)
LOG_GAMMA = (-0.4, 0.4)
CHANNEL_GAIN = (0.85, 1.15)
NOISE_STD = (0.0, 0.04)
BLUR_SHARE = 0.3


def photometric(images: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Augmented copies of uint8 images ``(N, H, W, C)``, uint8 again."""
    count, channels = images.shape[0], images.shape[-1]

    def draw(bounds: tuple[float, float], *shape: int) -> torch.Tensor:
        low, high = bounds
        return low + (high - low) * torch.rand((count, *shape), generator=generator)

    x = images.float() / 255.0
    mean = x.mean(dim=(1, 2, 3), keepdim=True)
    x = (x - mean) * draw(CONTRAST, 1, 1, 1) + mean + draw(BRIGHTNESS, 1, 1, 1)
    x = x.clamp(0.0, 1.0) ** torch.exp(draw(LOG_GAMMA, 1, 1, 1))
    x = x * draw(CHANNEL_GAIN, 1, 1, channels)
    x = x + draw(NOISE_STD, 1, 1, 1) * torch.randn(x.shape, generator=generator)
    blurred = torch.rand(count, generator=generator) < BLUR_SHARE
    if blurred.any():
        nchw = x[blurred].permute(0, 3, 1, 2)
        smooth = functional.avg_pool2d(nchw, 3, stride=1, padding=1, count_include_pad=False)
        x[blurred] = smooth.permute(0, 2, 3, 1)
    return (x.clamp(0.0, 1.0) * 255.0).round().to(torch.uint8)
