"""The CIFAR ResNet-18 of notebooks 01-02, the residual block it shares with the video encoder,
and the projector ("expander")."""

import torch
import torch.nn.functional as F
from torch import nn


def conv_bn_relu(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    """conv3x3 (no bias), BN, ReLU: ``(N, c_in, s, s) -> (N, c_out, s', s')``, s' = ⌈s/stride⌉."""
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride, padding=1, bias=False),
                         nn.BatchNorm2d(c_out), nn.ReLU(inplace=True))


class ResidualBlock(nn.Module):
    """conv3x3-BN-ReLU-conv3x3-BN plus a shortcut: ``(N, c_in, s, s) -> (N, c_out, s', s')``;
    ``relu_out=False`` leaves the sum un-rectified (the video encoder's last block)."""

    def __init__(self, c_in: int, c_out: int, stride: int = 1, relu_out: bool = True):
        super().__init__()
        self.conv1 = nn.Conv2d(c_in, c_out, 3, stride, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(c_out)
        self.conv2 = nn.Conv2d(c_out, c_out, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(c_out)
        self.shortcut = nn.Identity()
        if stride != 1 or c_in != c_out:  # a 1x1 convolution matches the shape
            self.shortcut = nn.Sequential(nn.Conv2d(c_in, c_out, 1, stride, bias=False),
                                          nn.BatchNorm2d(c_out))
        self.relu_out = relu_out

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        out = self.bn2(self.conv2(F.relu(self.bn1(self.conv1(x))))) + self.shortcut(x)
        return F.relu(out) if self.relu_out else out


class ResNet18(nn.Module):
    """CIFAR ResNet-18: ``(B, 3, H, W) -> (B, widths[-1])``: a stem (conv3x3, BN, ReLU), 4 stages
    of ``blocks_per_stage`` residual blocks (stages 2-4 halve the resolution), average pooling."""

    def __init__(self, widths: tuple[int, int, int, int] = (64, 128, 256, 512),
                 blocks_per_stage: int = 2):
        super().__init__()
        self.out_dim = widths[-1]
        self.stem = conv_bn_relu(3, widths[0])
        stages, channels = [], widths[0]
        for index, width in enumerate(widths):
            blocks = [ResidualBlock(channels, width, 1 if index == 0 else 2)]
            blocks += [ResidualBlock(width, width) for _ in range(blocks_per_stage - 1)]
            stages.append(nn.Sequential(*blocks))
            channels = width
        self.stages = nn.Sequential(*stages)
        for module in self.modules():
            if isinstance(module, nn.Conv2d):  # He initialisation, as in the original ResNet
                nn.init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.ndim != 4 or x.shape[1] != 3 or not x.is_floating_point():
            raise ValueError(f"the encoder expects float images (batch, 3, height, width), got "
                             f"{tuple(x.shape)} {x.dtype}: uint8 images through augment.normalize")
        return self.stages(self.stem(x)).mean(dim=(2, 3))  # (B, widths[-1], H/8, W/8) pooled


def build_projector(in_dim: int, hidden_dim: int, out_dim: int, depth: int) -> nn.Module:
    """``(B, in_dim) -> (B, out_dim)``: ``depth - 1`` Linear-BN-ReLU layers (Linears without bias:
    the BN removes it), then a Linear. ``depth=3`` is the VICReg / EB-JEPA projector; ``depth=0``
    the identity (``out_dim = in_dim``)."""
    layers, width = [], in_dim
    for _ in range(depth - 1):
        layers += [nn.Linear(width, hidden_dim, bias=False), nn.BatchNorm1d(hidden_dim),
                   nn.ReLU(inplace=True)]
        width = hidden_dim
    projector = nn.Sequential(*layers, nn.Linear(width, out_dim)) if depth else nn.Identity()
    projector.in_dim, projector.out_dim = in_dim, (out_dim if depth else in_dim)
    return projector
