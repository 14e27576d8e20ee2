"""CIFAR-10 and MNIST as uint8 ``(N, C, H, W)`` images and int64 ``(N,)`` labels
(``data/README.md``: where the files are looked for), and Moving MNIST made from them."""

import torch

from .cifar10 import CIFAR10_CLASSES, load_cifar10
from .mnist import load_mnist
from .paths import CorruptDataError, DataNotFoundError, cache_dir, data_dir


def random_subset(images: torch.Tensor, labels: torch.Tensor, n: int,
                  seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` of the ``(N, ...)`` images and their labels, drawn with ``seed`` (all if ``n >= N``),
    not the first ``n``, which in a copy stored class by class would be one class."""
    if n >= len(images):
        return images, labels
    keep = torch.randperm(len(images), generator=torch.Generator().manual_seed(seed))[:n]
    keep = keep.sort().values
    return images[keep], labels[keep]


__all__ = [
    "CIFAR10_CLASSES", "CorruptDataError", "DataNotFoundError", "cache_dir", "data_dir",
    "load_cifar10", "load_mnist", "random_subset",
]  # fmt: skip
