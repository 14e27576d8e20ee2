"""Batched image augmentations on tensors, for two-view self-supervised learning.

A joint-embedding model learns what two *views* of one image have in common,
so the views must differ in everything we want it to ignore: framing, colour,
orientation. Each view here is drawn with its own random parameters per image
(crop box, jitter factors, flips...), on whatever device the images live on,
so a batch of 256 CIFAR-10 images is augmented in one call (about 0.1-0.2 s
on 2 CPU cores) without a data-loader worker.

Recipe (the usual SimCLR / VICReg CIFAR recipe, used by the EB-JEPA paper):
random resized crop to 32 px with scale (0.2, 1.0), horizontal flip p 0.5,
colour jitter (brightness 0.4, contrast 0.4, saturation 0.2, hue 0.1) p 0.8,
grayscale p 0.2, solarize p 0.1, then normalisation with CIFAR-10 statistics
(``CIFAR10_MEAN``, ``CIFAR10_STD``).

Determinism: kornia draws its random parameters from torch's *global* RNG.
:func:`augment` therefore draws one integer seed from the caller's
``torch.Generator``, and runs the pipeline inside ``torch.random.fork_rng``
after ``torch.manual_seed(seed)``: the same generator state gives the same
views, and the global RNG is left exactly as it was.

Images: ``(B, 3, H, W)``, float in ``[0, 1]`` or uint8 in ``[0, 255]``.
"""

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
    """The knobs of the two-view recipe; the defaults are the paper's CIFAR-10 settings."""

    size: int = 32  # output side, pixels
    crop_scale: tuple[float, float] = (0.2, 1.0)  # fraction of the image area kept by the crop
    jitter: tuple[float, float, float, float] = (0.4, 0.4, 0.2, 0.1)  # bright, contrast, sat, hue
    jitter_p: float = 0.8
    grayscale_p: float = 0.2
    solarize_p: float = 0.1
    flip_p: float = 0.5


def build_augmentation(config: AugmentConfig = AugmentConfig()) -> K.AugmentationSequential:
    """The augmentation pipeline as a kornia module: ``(B, 3, H, W) -> (B, 3, size, size)``,
    standardised as :func:`normalize` does.

    Every random parameter is drawn per image (``same_on_batch=False``), except
    that kornia's ``ColorJitter`` applies its four steps in one random order
    shared by the batch. ``ColorJitter`` (not ``ColorJiggle``) uses torchvision's
    formulas, the ones the SSL literature tuned these strengths for. Solarize
    inverts pixels above 0.5 (a fixed threshold, as in BYOL).
    """
    brightness, contrast, saturation, hue = config.jitter
    return K.AugmentationSequential(
        K.RandomResizedCrop((config.size, config.size), scale=config.crop_scale),
        K.RandomHorizontalFlip(p=config.flip_p),
        K.ColorJitter(brightness, contrast, saturation, hue, p=config.jitter_p),
        K.RandomGrayscale(p=config.grayscale_p),
        K.RandomSolarize(thresholds=0.0, additions=0.0, p=config.solarize_p),
        K.Normalize(mean=torch.tensor(CIFAR10_MEAN), std=torch.tensor(CIFAR10_STD)),
    )


def to_float_images(images: torch.Tensor) -> torch.Tensor:
    """Check ``(B, 3, H, W)`` images and return them as float32 in ``[0, 1]``.

    uint8 images are divided by 255; float images must already lie in ``[0, 1]``.
    """
    if not isinstance(images, torch.Tensor) or images.ndim != 4:
        shape = tuple(images.shape) if isinstance(images, torch.Tensor) else type(images).__name__
        raise ValueError(
            f"images must be a (batch, 3, height, width) tensor, got {shape}; "
            "add a batch dimension with images.unsqueeze(0) for a single image"
        )
    if images.shape[1] != 3:
        raise ValueError(
            f"images must have 3 colour channels in dimension 1, got shape {tuple(images.shape)}; "
            "channels-last arrays need images.permute(0, 3, 1, 2)"
        )
    if images.dtype == torch.uint8:
        return images.float().div_(255)
    if not images.is_floating_point():
        raise TypeError(f"images must be uint8 or float, got {images.dtype}")
    low, high = images.min().item(), images.max().item()
    if low < -1e-6 or high > 1 + 1e-6:
        raise ValueError(
            f"float images must lie in [0, 1], got values in [{low:.3g}, {high:.3g}]; "
            "augment raw images (uint8, or float / 255), not normalised ones"
        )
    return images.float()


def _global_rng_devices(device: torch.device) -> tuple[list[int], str]:
    """Which accelerator RNG states ``fork_rng`` must save and restore for ``device``."""
    if device.type == "cuda":
        index = device.index if device.index is not None else torch.cuda.current_device()
        return [index], "cuda"
    if device.type == "mps":
        return [0], "mps"
    return [], "cuda"


def augment(images: torch.Tensor, pipeline: nn.Module, generator: torch.Generator) -> torch.Tensor:
    """One random view of each image: ``(B, 3, H, W)`` -> ``(B, 3, size, size)`` float32.

    ``pipeline``: :func:`build_augmentation`'s (build it once, pass it at every step). The
    views depend only on the ``generator``'s state (see the module docstring). The output
    is on the images' device.
    """
    images = to_float_images(images)
    seed = int(torch.randint(0, 2**62, (1,), generator=generator, device=generator.device))
    devices, device_type = _global_rng_devices(images.device)
    with torch.random.fork_rng(devices=devices, device_type=device_type):
        torch.manual_seed(seed)
        return pipeline(images)


def two_views(images: torch.Tensor, pipeline: nn.Module,
              generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Two independent views of each image, each ``(B, 3, size, size)``."""
    return augment(images, pipeline, generator), augment(images, pipeline, generator)


def normalize(images: torch.Tensor) -> torch.Tensor:
    """Standardise ``(B, 3, H, W)`` images in ``[0, 1]`` (or uint8) with the CIFAR-10 statistics.

    The un-augmented images seen at evaluation time must go through this too,
    so that they match what the encoder saw in training.
    """
    images = to_float_images(images)
    mean = torch.tensor(CIFAR10_MEAN, device=images.device).view(1, 3, 1, 1)
    std = torch.tensor(CIFAR10_STD, device=images.device).view(1, 3, 1, 1)
    return (images - mean) / std


def denormalize(images: torch.Tensor) -> torch.Tensor:
    """Undo :func:`normalize` for display: ``(B, 3, H, W)`` -> values clipped to ``[0, 1]``."""
    mean = torch.tensor(CIFAR10_MEAN, device=images.device).view(1, 3, 1, 1)
    std = torch.tensor(CIFAR10_STD, device=images.device).view(1, 3, 1, 1)
    return (images * std + mean).clamp(0, 1)
