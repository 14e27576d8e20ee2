"""Datasets as uint8 tensors: CIFAR-10 and MNIST, through torchvision.datasets, cached.

Images come back as uint8 ``(N, C, H, W)`` tensors with int64 labels ``(N,)``.
Where the files are looked for, and how to bring your own, is described in
``data/README.md``.
"""

import torch

from .cifar10 import CIFAR10_CLASSES, load_cifar10
from .mnist import load_mnist
from .paths import CorruptDataError, DataNotFoundError, cache_dir, data_dir


def random_subset(
    images: torch.Tensor, labels: torch.Tensor, n: int, seed: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` of the ``(N, ...)`` images and their labels, drawn at random with ``seed``.

    All of them, unchanged, when ``n >= N``. Never take the first ``n``: a copy
    stored class by class (like the JPEG folders) would give a single class.
    """
    if n >= len(images):
        return images, labels
    keep = torch.randperm(len(images), generator=torch.Generator().manual_seed(seed))[:n]
    keep = keep.sort().values
    return images[keep], labels[keep]


__all__ = [
    "CIFAR10_CLASSES", "CorruptDataError", "DataNotFoundError", "cache_dir", "data_dir",
    "load_cifar10", "load_mnist", "random_subset",
]  # fmt: skip
