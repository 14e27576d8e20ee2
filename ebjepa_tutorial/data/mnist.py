"""MNIST digits (LeCun et al., 1998) as uint8 tensors, read with ``torchvision.datasets``; one
split's two IDX files are enough (``datasets.MNIST``, which downloads them, wants all four)."""

from __future__ import annotations

import gzip
import os
import tempfile
import zlib
from pathlib import Path

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


def _read_idx(path: Path, read) -> torch.Tensor:
    """torchvision's IDX ``read`` on ``path``, decompressed first when it is a ``.gz``."""
    try:
        if path.suffix != ".gz":
            return read(str(path))
        with tempfile.TemporaryDirectory() as folder:  # torchvision reads plain files only
            plain = Path(folder) / path.stem
            plain.write_bytes(gzip.decompress(path.read_bytes()))
            return read(str(plain))
    except (OSError, EOFError, zlib.error, AssertionError, RuntimeError, ValueError) as err:
        raise CorruptDataError(
            f"cannot read {path}: {type(err).__name__}: {err}. The file is truncated, damaged "
            "or not an IDX file of unsigned bytes; replace it (see data/README.md)."
        ) from err


def load_mnist(split: str = "train", root: str | os.PathLike | None = None,
               download: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """One MNIST split: images (N, 1, 28, 28) uint8, labels (N,) int64; N = 60,000 or 10,000.
    ``root``: the data directory; ``download=False``: DataNotFoundError instead of fetching."""
    if split not in ("train", "test"):
        raise ValueError(f"split must be one of 'train', 'test'; got {split!r}")
    from torchvision import datasets
    from torchvision.datasets.mnist import read_image_file, read_label_file

    directory = data_dir(root)
    files = find_mnist(directory, split)
    if files is not None:
        images, labels = _read_idx(files[0], read_image_file), _read_idx(files[1], read_label_file)
    elif not download:
        raise DataNotFoundError(_missing_message(directory, split))
    else:
        try:
            dataset = datasets.MNIST(str(directory), train=split == "train", download=True)
        except (OSError, RuntimeError, ValueError) as err:  # no network, HTTP error, wrong MD5
            message = _missing_message(directory, split)
            raise DataNotFoundError(f"{message}\n\nThe download failed: {err}") from err
        images, labels = dataset.data, dataset.targets
    return images[:, None].contiguous(), labels.long()
