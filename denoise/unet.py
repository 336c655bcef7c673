"""The N2V UNet: a 4-level encoder-decoder on RGB images (torch, float32).

Layout (``depth`` = 4 downsamplings): per level a conv block (two 3x3
convolutions with LeakyReLU), a 2x downsampling, a bottleneck block, then
``depth`` bilinear 2x upsamplings each followed by concatenation with the
encoder features of that level (the skip connection) and a conv block, and a
1x1 output convolution. Widths are ``width * 2**level`` capped at
``width * max_width_mult``.

N2V2 fixes against checkerboard artefacts (Höck et al. 2022), both optional:

- ``blurpool``: max-blur-pool downsampling (a stride-1 2x2 max pool followed by
  a [1 2 1] x [1 2 1] binomial blur with stride 2, Zhang 2019; edges replicated) instead of a
  stride-2 max pool;
- ``top_skip=False``: no skip connection at the full-resolution level.

Any input size works: the input is padded (half-sample symmetric) to a
multiple of ``2**depth`` and the output is cropped back.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from denoise.filters import pad_symmetric
from mvgeo.common.errors import check_shape

#: Run the CPU convolutions on channels-last (NHWC) activations: oneDNN's fast path, R2R training 1.2x and
#: inference 1.3-1.6x faster than on NCHW ones on real photos (docs/bench/denoise_speed.md); the weights keep their
#: layout and callers get NCHW back. Other devices keep the layout they are given. (False only for the tests'
#: NCHW reference.)
_CHANNELS_LAST_ON_CPU = True


@dataclass(frozen=True)
class UNetConfig:
    """Architecture of the UNet.

    Attributes:
        in_channels: input channels (3 for RGB).
        out_channels: output channels (3 for RGB).
        width: channels of the first level (CPU-friendly default 16).
        depth: number of 2x downsamplings (the issue's 4 levels).
        max_width_mult: channel cap as a multiple of `width` (8 -> 16, 32, 64, 128, 128).
        blurpool: N2V2 max-blur-pool downsampling.
        top_skip: keep the full-resolution skip connection (N2V2 removes it).
        input_skip: the 1x1 output convolution also sees the network input (a linear
            path). N2V's residual output ``x + alpha * UNet(x)`` must learn to cancel the
            centre pixel (a masked pixel's value is a random replacement); through this
            path that is one weight, and training converges in far fewer steps on CPU
            (measured: see docs/bench/denoise.md).
    """

    in_channels: int = 3
    out_channels: int = 3
    width: int = 16
    depth: int = 4
    max_width_mult: int = 8
    blurpool: bool = False
    top_skip: bool = True
    input_skip: bool = True

    def __post_init__(self) -> None:
        for name in ("in_channels", "out_channels", "width", "depth", "max_width_mult"):
            if getattr(self, name) < 1:
                raise ValueError(f"UNetConfig.{name} must be >= 1, got {getattr(self, name)}")


def _block(c_in: int, c_out: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, 3, padding=1, padding_mode="replicate"),
        nn.LeakyReLU(0.1, inplace=True),
        nn.Conv2d(c_out, c_out, 3, padding=1, padding_mode="replicate"),
        nn.LeakyReLU(0.1, inplace=True),
    )


class MaxBlurPool2d(nn.Module):
    """Max-blur-pool: stride-1 2x2 max, then a stride-2 binomial [1 2 1]^2 / 16 blur (per channel)."""

    def __init__(self) -> None:
        super().__init__()
        k = torch.tensor([1.0, 2.0, 1.0])
        self.register_buffer("kernel", (k[:, None] * k[None, :] / 16.0)[None, None], persistent=False)

    def forward(self, x: Tensor) -> Tensor:
        x = F.max_pool2d(F.pad(x, (0, 1, 0, 1), mode="replicate"), 2, stride=1)
        c = x.shape[1]
        x = F.pad(x, (1, 1, 1, 1), mode="replicate")
        return F.conv2d(x, self.kernel.to(x.dtype).expand(c, 1, 3, 3), stride=2, groups=c)


class UNet(nn.Module):
    """UNet mapping ``[B, in_channels, H, W]`` to ``[B, out_channels, H, W]`` (any H, W >= 1)."""

    def __init__(self, config: UNetConfig | None = None) -> None:
        super().__init__()
        self.config = cfg = config or UNetConfig()
        widths = [cfg.width * min(2**i, cfg.max_width_mult) for i in range(cfg.depth + 1)]
        self.encoders = nn.ModuleList()
        c_prev = cfg.in_channels
        for i in range(cfg.depth):
            self.encoders.append(_block(c_prev, widths[i]))
            c_prev = widths[i]
        self.down = MaxBlurPool2d() if cfg.blurpool else nn.MaxPool2d(2)
        self.bottleneck = _block(c_prev, widths[cfg.depth])
        self.decoders = nn.ModuleList()
        c_prev = widths[cfg.depth]
        for i in reversed(range(cfg.depth)):
            skip = widths[i] if (i > 0 or cfg.top_skip) else 0
            self.decoders.append(_block(c_prev + skip, widths[i]))
            c_prev = widths[i]
        self.head = nn.Conv2d(c_prev + (cfg.in_channels if cfg.input_skip else 0), cfg.out_channels, 1)

    def forward(self, x: Tensor) -> Tensor:
        """Args: x ``[B, C_in, H, W]``. Returns ``[B, C_out, H, W]``."""
        check_shape(x, ["B", self.config.in_channels, "H", "W"], "x")
        h, w = x.shape[-2:]
        m = 2**self.config.depth
        ph, pw = (-h) % m, (-w) % m
        top, left = ph // 2, pw // 2
        if ph or pw:
            r = max(ph, pw)
            x = pad_symmetric(x, r)[..., r - top : r + h + ph - top, r - left : r + w + pw - left]
        if x.is_cpu and _CHANNELS_LAST_ON_CPU:
            x = x.contiguous(memory_format=torch.channels_last)
        inp = x
        skips = []
        for enc in self.encoders:
            x = enc(x)
            skips.append(x)
            x = self.down(x)
        x = self.bottleneck(x)
        for level, dec in zip(reversed(range(self.config.depth)), self.decoders, strict=True):
            x = F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False)
            if level > 0 or self.config.top_skip:
                x = torch.cat([x, skips[level]], dim=1)
            x = dec(x)
        out = self.head(torch.cat([x, inp], dim=1) if self.config.input_skip else x)
        return out[..., top : top + h, left : left + w].contiguous()
