"""Image encoders for notebooks 01-02: a CIFAR ResNet-18 and a small Vision Transformer.

Both map normalised images ``(B, C, H, W)`` to one embedding per image
``(B, out_dim)``; ``encoder.out_dim`` says how wide it is.

- :class:`ResNet18`: the CIFAR variant used by the EB-JEPA paper (3x3 stride-1
  stem, no max-pool, so 32x32 inputs keep 32x32 maps in the first stage). The
  stem uses padding 1; the paper's reference code uses padding 2, which turns
  32x32 inputs into 34x34 maps (an extra ring of zeros convolved into every
  layer). Widths shrink for CPU runs: ``widths=(16, 32, 64, 128)`` costs about
  1/16 of the full ``(64, 128, 256, 512)``.
- :class:`ViT`: pre-norm transformer on non-overlapping patches with a class
  token. Defaults are ViT-S (dim 384, depth 12, 6 heads, MLP 4x); the paper's
  reference runs its CIFAR ViT-S with patch size 2 (256 tokens per image), the
  default here too. Patch 4 (64 tokens) is about 5x cheaper.

:func:`build_encoder` picks one by name.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def check_images(x: torch.Tensor, in_channels: int) -> None:
    """Raise a clear error unless ``x`` is a float ``(B, in_channels, H, W)`` tensor."""
    if not isinstance(x, torch.Tensor) or x.ndim != 4:
        shape = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
        raise ValueError(
            f"the encoder expects images of shape (batch, {in_channels}, height, width), got "
            f"{shape}; use x.unsqueeze(0) for one image, or flatten time into the batch for videos"
        )
    if x.shape[1] != in_channels:
        raise ValueError(
            f"the encoder was built for {in_channels} input channels, got {x.shape[1]} "
            f"(shape {tuple(x.shape)}); channels go in dimension 1 (use x.permute(0, 3, 1, 2) "
            "for channels-last arrays) or build the encoder with in_channels=..."
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
    """CIFAR ResNet-18: ``(B, C, H, W) -> (B, widths[-1])``.

    Stem: 3x3 convolution, stride 1, padding 1, BatchNorm, ReLU (no max-pool).
    Then 4 stages of ``blocks_per_stage`` BasicBlocks; stages 2-4 halve the
    resolution (32 -> 16 -> 8 -> 4 for CIFAR). Global average pooling gives the
    ``widths[-1]``-d embedding (512 at full width).
    """

    def __init__(
        self,
        widths: tuple[int, int, int, int] = (64, 128, 256, 512),
        in_channels: int = 3,
        blocks_per_stage: int = 2,
    ):
        super().__init__()
        if len(widths) != 4 or any(int(w) < 1 for w in widths):
            raise ValueError(f"widths must be 4 positive channel counts, got {widths}")
        self.in_channels = in_channels
        self.out_dim = widths[-1]
        self.stem = nn.Sequential(
            nn.Conv2d(in_channels, widths[0], 3, stride=1, padding=1, bias=False),
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

    def feature_maps(self, x: torch.Tensor) -> torch.Tensor:
        """The last stage's maps before pooling: ``(B, C, H, W) -> (B, widths[-1], H/8, W/8)``."""
        check_images(x, self.in_channels)
        return self.stages(self.stem(x))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.feature_maps(x).mean(dim=(2, 3))


class TransformerBlock(nn.Module):
    """Pre-norm self-attention + MLP, each with a residual: ``(B, N, dim) -> (B, N, dim)``."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float = 4.0):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.attn = nn.MultiheadAttention(dim, heads, batch_first=True)
        self.norm2 = nn.LayerNorm(dim)
        hidden = int(dim * mlp_ratio)
        self.mlp = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h = self.norm1(x)
        x = x + self.attn(h, h, h, need_weights=False)[0]
        return x + self.mlp(self.norm2(x))


class ViT(nn.Module):
    """Vision Transformer: ``(B, C, image_size, image_size) -> (B, dim)`` (the class token).

    The image is cut into ``(image_size / patch_size)^2`` patches, each linearly
    embedded (a strided convolution), a learned class token and learned position
    embeddings are added, ``depth`` transformer blocks mix the tokens, and the
    final LayerNorm'd class token is the embedding. Defaults: ViT-S for CIFAR.
    """

    def __init__(
        self,
        image_size: int = 32,
        patch_size: int = 2,
        dim: int = 384,
        depth: int = 12,
        heads: int = 6,
        mlp_ratio: float = 4.0,
        in_channels: int = 3,
    ):
        super().__init__()
        if image_size % patch_size != 0:
            raise ValueError(
                f"image_size {image_size} is not a multiple of patch_size {patch_size}"
            )
        if dim % heads != 0:
            raise ValueError(f"dim {dim} must be divisible by heads {heads}")
        self.image_size, self.in_channels, self.out_dim = image_size, in_channels, dim
        num_patches = (image_size // patch_size) ** 2
        self.patch_embed = nn.Conv2d(in_channels, dim, patch_size, stride=patch_size)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, dim))
        self.pos_embed = nn.Parameter(torch.randn(1, num_patches + 1, dim) * 0.02)
        self.blocks = nn.Sequential(
            *[TransformerBlock(dim, heads, mlp_ratio) for _ in range(depth)]
        )
        self.norm = nn.LayerNorm(dim)
        for module in self.modules():
            if isinstance(module, nn.Linear):  # small weights, as in the original ViT
                nn.init.trunc_normal_(module.weight, std=0.02)
                nn.init.zeros_(module.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        check_images(x, self.in_channels)
        if x.shape[-2:] != (self.image_size, self.image_size):
            raise ValueError(
                f"this ViT was built for {self.image_size}x{self.image_size} images, got "
                f"{x.shape[-2]}x{x.shape[-1]}; resize the images or build it with image_size=..."
            )
        tokens = self.patch_embed(x).flatten(2).transpose(1, 2)  # (B, num_patches, dim)
        cls = self.cls_token.expand(x.shape[0], -1, -1)
        tokens = torch.cat([cls, tokens], dim=1) + self.pos_embed
        return self.norm(self.blocks(tokens))[:, 0]


ENCODERS = {"resnet18": ResNet18, "vit_s": ViT, "vit_small": ViT}


def build_encoder(name: str, **kwargs) -> nn.Module:
    """Build an encoder by name: ``"resnet18"`` or ``"vit_s"`` (alias ``"vit_small"``).

    Keyword arguments go to the class, e.g.
    ``build_encoder("resnet18", widths=(16, 32, 64, 128))`` (a 128-d output) or
    ``build_encoder("vit_s", patch_size=4)``.
    """
    key = name.strip().lower().replace("-", "_")
    if key not in ENCODERS:
        raise ValueError(f"unknown encoder {name!r}; choose one of {', '.join(sorted(ENCODERS))}")
    return ENCODERS[key](**kwargs)
