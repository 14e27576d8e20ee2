"""The video JEPA of notebook 03 (a frame encoder to a spatial latent ``(C, S, S)``, a ResUNet
predictor, a per-location projector) and two evaluation heads for frozen latents."""

import math
from dataclasses import dataclass

import torch
from torch import nn

from ..data.moving_mnist import FRAME_SIZE
from .encoders import ResidualBlock, build_projector, conv_bn_relu


@dataclass(frozen=True)
class VideoModelConfig:
    """Sizes of a :class:`VideoJEPA`. The default is the class-scale model."""

    encoder_width: int = 16  # h: channels of the stem and first block (the paper: 32)
    stem_stride: int = 2  # of the stem conv: 2 halves the frame before any block (the paper: 1)
    latent_channels: int = 32  # C (the paper: 16)
    strides: tuple[int, int, int] = (1, 2, 2)  # of the blocks: S = 64 / (2*1*2*2) = 8
    predictor_width: int = 32  # ResUNet width h, levels h, 2h, 4h, ... (the paper: 32)
    predictor_levels: int = 2  # times the ResUNet halves the map (S must divide by 2**levels)
    context: int = 2  # latent frames the predictor sees
    projector_dim: int = 64  # hidden and output width of the projector (the paper: 4 C)
    residual: bool = True  # predict a change to the last latent (the paper: False)

    @property
    def latent_side(self) -> int:  # S
        return FRAME_SIZE // (self.stem_stride * math.prod(self.strides))


VIDEO_MODEL_CONFIGS = {
    "ci": VideoModelConfig(encoder_width=8, stem_stride=1, latent_channels=8, strides=(2, 2, 2),
                           predictor_width=8, projector_dim=32),
    "class": VideoModelConfig(),
    "full": VideoModelConfig(encoder_width=32, stem_stride=1, latent_channels=16,
                             strides=(1, 1, 1), predictor_levels=3, residual=False),
}


class FrameEncoder(nn.Module):
    """ResNet-5-style: stem conv, blocks of widths h, 2h, C: ``(N, 1, 64, 64) -> (N, C, S, S)``."""

    def __init__(self, config: VideoModelConfig):
        super().__init__()
        h, c, (s1, s2, s3) = config.encoder_width, config.latent_channels, config.strides
        self.stem = conv_bn_relu(1, h, config.stem_stride)
        self.blocks = nn.Sequential(ResidualBlock(h, h, s1), ResidualBlock(h, 2 * h, s2),
                                    ResidualBlock(2 * h, c, s3, relu_out=False))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.blocks(self.stem(x))


class ResUNetPredictor(nn.Module):
    """Next latent from a window, ``(N, context, C, S, S) -> (N, C, S, S)``: a UNet of residual
    blocks (widths h, 2h, 4h, ...) on the window stacked along channels."""

    def __init__(self, config: VideoModelConfig):
        super().__init__()
        h, c, levels = config.predictor_width, config.latent_channels, config.predictor_levels
        widths = [h * 2**i for i in range(levels + 1)]  # h, 2h, 4h, ... down to the bottleneck
        self.context = config.context
        self.stem = conv_bn_relu(config.context * c, h)
        self.down = nn.ModuleList([ResidualBlock(h, h)] + [
            ResidualBlock(widths[i - 1], widths[i], stride=2) for i in range(1, levels + 1)])
        self.up = nn.ModuleList([nn.ConvTranspose2d(widths[i], widths[i - 1], 2, stride=2)
                                 for i in range(levels, 0, -1)])
        self.fuse = nn.ModuleList([ResidualBlock(2 * widths[i - 1], widths[i - 1])
                                   for i in range(levels, 0, -1)])
        self.head = nn.Conv2d(h, c, 1)
        self.residual = config.residual
        if self.residual:  # start as "nothing moves": the prediction is the last latent
            nn.init.zeros_(self.head.weight)
            nn.init.zeros_(self.head.bias)

    def forward(self, window: torch.Tensor) -> torch.Tensor:
        if window.ndim != 5 or window.shape[1] != self.context:
            raise ValueError(f"the predictor takes (N, {self.context}, C, S, S) windows, "
                             f"got {tuple(window.shape)}")
        x = self.stem(window.flatten(1, 2))  # (N, context * C, S, S) -> (N, h, S, S)
        skips = []
        for block in self.down:
            x = block(x)
            skips.append(x)
        skips.pop()  # the bottleneck itself is not a skip
        for up, fuse in zip(self.up, self.fuse):
            x = fuse(torch.cat([up(x), skips.pop()], dim=1))
        return window[:, -1] + self.head(x) if self.residual else self.head(x)


class VideoJEPA(nn.Module):
    """Encoder, predictor and projector; the encoder and predictor are what we keep."""

    def __init__(self, config: VideoModelConfig = VideoModelConfig()):
        super().__init__()
        self.config = config
        self.encoder = FrameEncoder(config)
        self.predictor = ResUNetPredictor(config)
        self.projector = build_projector(config.latent_channels, config.projector_dim,
                                         config.projector_dim, depth=2)

    def encode(self, frames: torch.Tensor) -> torch.Tensor:
        """Frames ``(B, T, 1, 64, 64)`` (uint8, or float in 0..1) -> ``(B, T, C, S, S)``."""
        low, high = (torch.aminmax(frames.detach()) if frames.dtype != torch.uint8  # one scan
                     and frames.numel() else (0, 1))
        outside = not 0 <= low <= high <= 1  # 0..255 floats, or standardised frames
        if frames.ndim != 5 or frames.shape[2:] != (1, FRAME_SIZE, FRAME_SIZE) or outside:
            raise ValueError(f"frames must be (B, T, 1, 64, 64) clips, uint8 or float in 0..1 "
                             f"(uint8 / 255); got {tuple(frames.shape)} {frames.dtype}")
        x = frames.float() / 255 if frames.dtype == torch.uint8 else frames
        return self.encoder(x.flatten(0, 1)).unflatten(0, frames.shape[:2])

    def project(self, z: torch.Tensor) -> torch.Tensor:
        """Latents ``(..., C, S, S)`` -> projections ``(M, D)``, one row per location."""
        return self.projector(z.movedim(-3, -1).reshape(-1, z.shape[-3]))  # rows (M, C)


def detection_head(channels: int, grid: int = 8) -> nn.Sequential:
    """Digit-centre logits on a ``grid x grid`` map: ``(N, C, S, S) -> (N, grid, grid)``: the
    latent average-pooled to the grid, then conv3x3-ReLU-conv3x3."""
    return nn.Sequential(nn.AdaptiveAvgPool2d(grid), nn.Conv2d(channels, 32, 3, padding=1),
                         nn.ReLU(inplace=True), nn.Conv2d(32, 1, 3, padding=1),
                         nn.Flatten(1, 2))  # (N, 1, grid, grid) -> (N, grid, grid)


def frame_decoder(channels: int, latent_side: int) -> nn.Sequential:
    """Pictures from latents, for looking only: ``(N, C, S, S) -> logits (N, 1, 64, 64)``: a
    conv, one transposed conv per doubling from ``S`` to 64, a conv to one channel."""
    layers = [nn.Conv2d(channels, 16, 3, padding=1), nn.ReLU(inplace=True)]
    for _ in range(int(math.log2(FRAME_SIZE // latent_side))):
        layers += [nn.ConvTranspose2d(16, 16, 4, stride=2, padding=1), nn.ReLU(inplace=True)]
    return nn.Sequential(*layers, nn.Conv2d(16, 1, 3, padding=1))
