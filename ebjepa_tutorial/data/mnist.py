"""MNIST digits (LeCun et al., 1998) as uint8 tensors, read from their IDX files; one split's
two files are enough (``torchvision.datasets.MNIST``, which downloads them, wants all four)."""

from __future__ import annotations

import gzip
import os
import zlib
from pathlib import Path

import numpy as np
import torch

from .paths import CorruptDataError, DataNotFoundError, data_dir

MNIST_FILES = {  # split -> (images, labels), without the .gz
    "train": ("train-images-idx3-ubyte", "train-labels-idx1-ubyte"),
    "test": ("t10k-images-idx3-ubyte", "t10k-labels-idx1-ubyte"),
}


def find_mnist(directory: Path, split: str) -> tuple[Path, Path] | None:
    """Paths of the (images, labels) IDX files of ``split``, ``.gz`` or not, in
    ``directory/MNIST/raw``, ``directory/mnist`` or ``directory``; None if absent."""
    for folder in (directory / "MNIST" / "raw", directory / "mnist", directory):
        pair = [next((p for p in (folder / f"{stem}.gz", folder / stem) if p.is_file()), None)
                for stem in MNIST_FILES[split]]  # fmt: skip
        if all(pair):
            return pair[0], pair[1]
    return None


def _missing_message(directory: Path, split: str) -> str:
    from torchvision import datasets  # here: importing torchvision takes over a second

    images, labels = (f"{stem}.gz" for stem in MNIST_FILES[split])
    return (
        f"MNIST ({split} split) was not found. Looked for {images} and {labels}\n"
        f"(or the same files uncompressed) in {directory}/MNIST/raw, {directory}/mnist "
        f"and {directory}.\n"
        "To get them: call load_mnist(download=True) on a machine with internet (torchvision\n"
        f"downloads them from {datasets.MNIST.mirrors[0]} and checks their MD5), or set\n"
        "EBJEPA_DATA (or pass root=...) to a folder that holds them."
    )


def _read_idx(path: Path, ndim: int) -> torch.Tensor:
    """An IDX file of unsigned bytes with ``ndim`` axes (``.gz`` or not) as a uint8 tensor: a
    header ``0 0 8 ndim``, ``ndim`` big-endian sizes, then the values."""
    try:
        data = gzip.decompress(path.read_bytes()) if path.suffix == ".gz" else path.read_bytes()
        if data[:4] != bytes([0, 0, 8, ndim]):
            raise ValueError(f"its header is {data[:4].hex(' ')}, not 00 00 08 {ndim:02x}")
        shape = np.frombuffer(data, ">u4", count=ndim, offset=4)
        values = np.frombuffer(data, np.uint8, offset=4 + 4 * ndim)
        if values.size != shape.prod():
            raise ValueError(f"{values.size} values where its header announces {shape.tolist()}")
    except (OSError, EOFError, zlib.error, ValueError) as err:
        raise CorruptDataError(
            f"cannot read {path}: {type(err).__name__}: {err}. The file is truncated, damaged "
            "or not an IDX file of unsigned bytes; replace it (see data/README.md)."
        ) from err
    return torch.from_numpy(values.reshape(shape.tolist()).copy())


def load_mnist(split: str = "train", root: str | os.PathLike | None = None,
               download: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """One MNIST split: images (N, 1, 28, 28) uint8, labels (N,) int64; N = 60,000 or 10,000.
    ``root``: the data directory; ``download=False``: DataNotFoundError instead of fetching."""
    if split not in ("train", "test"):
        raise ValueError(f"split must be one of 'train', 'test'; got {split!r}")
    directory = data_dir(root)
    files = find_mnist(directory, split)
    if files is None and not download:
        raise DataNotFoundError(_missing_message(directory, split))
    if files is None:  # torchvision downloads all four files to MNIST/raw, checking their MD5
        from torchvision import datasets  # here: importing torchvision takes over a second

        try:
            datasets.MNIST(str(directory), train=split == "train", download=True)
        except (OSError, RuntimeError, ValueError) as err:  # no network, HTTP error, wrong MD5
            message = _missing_message(directory, split)
            raise DataNotFoundError(f"{message}\n\nThe download failed: {err}") from err
        files = find_mnist(directory, split)
    images, labels = _read_idx(files[0], 3), _read_idx(files[1], 1)
    return images[:, None].contiguous(), labels.long()
