"""Batched two-view image augmentations on tensors, drawn per image, on the images' device.
Images: ``(B, 3, H, W)``, float in ``[0, 1]`` or uint8 in ``[0, 255]``."""

from __future__ import annotations

from dataclasses import dataclass

import kornia.augmentation as K
import torch
from torch import nn

# Per-channel mean and standard deviation of the CIFAR-10 training images, in [0, 1] units.
CIFAR10_MEAN = (0.4914, 0.4822, 0.4465)
CIFAR10_STD = (0.2470, 0.2435, 0.2616)


@dataclass(frozen=True)
class AugmentConfig:
    """The two-view recipe; the defaults are the usual SimCLR / VICReg CIFAR-10 settings."""

    size: int = 32  # output side, pixels
    crop_scale: tuple[float, float] = (0.2, 1.0)  # fraction of the image area kept by the crop
    jitter_p: float = 0.8
    grayscale_p: float = 0.2
    solarize_p: float = 0.1
    flip_p: float = 0.5


def build_augmentation(config: AugmentConfig = AugmentConfig()) -> K.AugmentationSequential:
    """The pipeline as a kornia module: ``(B, 3, H, W) -> (B, 3, size, size)``, normalised."""
    return K.AugmentationSequential(
        K.RandomResizedCrop((config.size, config.size), scale=config.crop_scale),
        K.RandomHorizontalFlip(p=config.flip_p),
        K.ColorJitter(0.4, 0.4, 0.2, 0.1, p=config.jitter_p),  # brightness, contrast, sat, hue
        K.RandomGrayscale(p=config.grayscale_p),
        K.RandomSolarize(thresholds=0.0, additions=0.0, p=config.solarize_p),  # as in BYOL
        K.Normalize(mean=torch.tensor(CIFAR10_MEAN), std=torch.tensor(CIFAR10_STD)),
    )


def to_float_images(images: torch.Tensor) -> torch.Tensor:
    """Check ``(B, 3, H, W)`` images (uint8, or float in ``[0, 1]``); return float32 in [0, 1]."""
    if images.ndim != 4 or images.shape[1] != 3:
        raise ValueError(f"images must be (batch, 3 colour channels, height, width), got "
                         f"{tuple(images.shape)}: try .unsqueeze(0) or .permute(0, 3, 1, 2)")
    if images.dtype == torch.uint8:
        return images.float().div_(255)
    low, high = images.min().item(), images.max().item()
    if not images.is_floating_point() or not -1e-6 <= low <= high <= 1 + 1e-6:  # NaN fails
        fix = ("normalised images? augment raw ones" if low < 0 else "0..255 values: make them "
               "uint8 with .to(torch.uint8)" if 2 < high <= 255 else "clamp them to [0, 1]")
        raise ValueError(f"images must be uint8, or float in [0, 1], got {images.dtype} in "
                         f"[{low:.3g}, {high:.3g}]; {fix}")
    return images.float()


def augment(images: torch.Tensor, pipeline: nn.Module, generator: torch.Generator) -> torch.Tensor:
    """One random view of each image by ``pipeline``: ``(B, 3, H, W) -> (B, 3, size, size)``
    float32, drawn from ``generator`` alone (kornia's global RNG is seeded from it, forked)."""
    images = to_float_images(images)
    seed = int(torch.randint(0, 2**62, (1,), generator=generator, device=generator.device))
    device = images.device
    with torch.random.fork_rng(devices=[] if device.type == "cpu" else [device],
                               device_type=device.type):
        torch.manual_seed(seed)
        return pipeline(images)


def two_views(images: torch.Tensor, pipeline: nn.Module,
              generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Two independent views of each image, each ``(B, 3, size, size)``."""
    return augment(images, pipeline, generator), augment(images, pipeline, generator)


def normalize(images: torch.Tensor) -> torch.Tensor:
    """Standardise ``(B, 3, H, W)`` images in ``[0, 1]`` (or uint8) as the pipeline does."""
    images = to_float_images(images)
    mean = torch.tensor(CIFAR10_MEAN, device=images.device).view(1, 3, 1, 1)
    std = torch.tensor(CIFAR10_STD, device=images.device).view(1, 3, 1, 1)
    return (images - mean) / std


def denormalize(images: torch.Tensor) -> torch.Tensor:
    """Undo :func:`normalize` for display: ``(B, 3, H, W)`` -> values clipped to ``[0, 1]``."""
    mean = torch.tensor(CIFAR10_MEAN, device=images.device).view(1, 3, 1, 1)
    std = torch.tensor(CIFAR10_STD, device=images.device).view(1, 3, 1, 1)
    return (images * std + mean).clamp(0, 1)
