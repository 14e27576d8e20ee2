"""The image encoder of notebooks 01-02: the CIFAR ResNet-18 of the EB-JEPA paper.

It maps normalised images ``(B, 3, H, W)`` to one embedding per image ``(B, out_dim)``.
A 3x3 stride-1 stem and no max-pool, so 32x32 inputs keep 32x32 maps in the first stage.
The stem uses padding 1; the paper's reference code uses padding 2, which turns 32x32
inputs into 34x34 maps (an extra ring of zeros convolved into every layer). Widths shrink
for CPU runs: ``widths=(16, 32, 64, 128)`` costs about 1/16 of the full ``(64, 128, 256, 512)``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def check_images(x: torch.Tensor) -> None:
    """Raise a clear error unless ``x`` is a float ``(B, 3, H, W)`` tensor."""
    if not isinstance(x, torch.Tensor) or x.ndim != 4:
        shape = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
        raise ValueError(
            f"the encoder expects images of shape (batch, 3, height, width), got "
            f"{shape}; use x.unsqueeze(0) for one image, or flatten time into the batch for videos"
        )
    if x.shape[1] != 3:
        raise ValueError(
            f"the encoder was built for 3 input channels, got {x.shape[1]} "
            f"(shape {tuple(x.shape)}); channels go in dimension 1 (use x.permute(0, 3, 1, 2) "
            "for channels-last arrays)"
        )
    if not x.is_floating_point():
        raise TypeError(
            f"the encoder expects float images, got {x.dtype}; convert uint8 images with "
            "ebjepa_tutorial.augment.normalize(images)"
        )


class BasicBlock(nn.Module):
    """Two 3x3 convolutions plus a shortcut: ``(B, C_in, H, W) -> (B, C_out, H/s, W/s)``."""

    def __init__(self, in_channels: int, out_channels: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(in_channels, out_channels, 3, stride, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(out_channels)
        self.conv2 = nn.Conv2d(out_channels, out_channels, 3, 1, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(out_channels)
        self.shortcut = nn.Identity()
        if stride != 1 or in_channels != out_channels:
            # A 1x1 convolution matches the shape when the block changes it.
            self.shortcut = nn.Sequential(
                nn.Conv2d(in_channels, out_channels, 1, stride, bias=False),
                nn.BatchNorm2d(out_channels),
            )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = F.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return F.relu(out + self.shortcut(x))


class ResNet18(nn.Module):
    """CIFAR ResNet-18: ``(B, 3, H, W) -> (B, widths[-1])``.

    Stem: 3x3 convolution, stride 1, padding 1, BatchNorm, ReLU (no max-pool).
    Then 4 stages of ``blocks_per_stage`` BasicBlocks; stages 2-4 halve the
    resolution (32 -> 16 -> 8 -> 4 for CIFAR). Global average pooling gives the
    ``widths[-1]``-d embedding (512 at full width).
    """

    def __init__(self, widths: tuple[int, int, int, int] = (64, 128, 256, 512),
                 blocks_per_stage: int = 2):
        super().__init__()
        if len(widths) != 4 or any(int(w) < 1 for w in widths):
            raise ValueError(f"widths must be 4 positive channel counts, got {widths}")
        self.out_dim = widths[-1]
        self.stem = nn.Sequential(
            nn.Conv2d(3, widths[0], 3, stride=1, padding=1, bias=False),
            nn.BatchNorm2d(widths[0]),
            nn.ReLU(inplace=True),
        )
        stages, channels = [], widths[0]
        for index, width in enumerate(widths):
            stride = 1 if index == 0 else 2
            blocks = [BasicBlock(channels, width, stride)]
            blocks += [BasicBlock(width, width) for _ in range(blocks_per_stage - 1)]
            stages.append(nn.Sequential(*blocks))
            channels = width
        self.stages = nn.Sequential(*stages)
        for module in self.modules():
            if isinstance(module, nn.Conv2d):  # He initialisation, as in the original ResNet
                nn.init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        check_images(x)
        return self.stages(self.stem(x)).mean(dim=(2, 3))  # (B, widths[-1], H/8, W/8) pooled
