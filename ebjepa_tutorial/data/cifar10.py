"""CIFAR-10 (Krizhevsky, 2009) as uint8 tensors, read through ``torchvision.datasets``.

:func:`load_cifar10` looks in the data directory for the official release extracted, then a
tree of class folders, then such a tree packed as ``cifar10*.tar.gz``, and downloads the
official archive (MD5-checked) only when none is there; ``data/README.md`` gives the paths.
Decoded image folders are cached as arrays, so only their first load is slow.
"""

from __future__ import annotations

import gzip
import os
import shutil
import tarfile
import tempfile
import zlib
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torchvision import datasets
from torchvision.datasets.utils import extract_archive
from torchvision.transforms import v2
from tqdm.auto import tqdm

from .paths import (
    CorruptDataError,
    DataNotFoundError,
    cache_dir,
    check_split,
    data_dir,
    read_cache,
    source_key,
    write_cache,
)

CIFAR10_CLASSES = (
    "airplane", "automobile", "bird", "cat", "deer", "dog", "frog", "horse", "ship", "truck",
)  # fmt: skip
TREE_DIRS = ("cifar10", "cifar-10", "cifar10-jpeg", ".")
SIZE = 32
# Your own images of another size: the largest centred square, resized to 32x32.
FIT = v2.Compose([v2.PILToTensor(), v2.Resize(SIZE), v2.CenterCrop(SIZE)])


class Source(NamedTuple):
    """Where one split was found: ``kind`` is official, tree or packed."""

    kind: str
    path: Path


def find_cifar10(directory: Path, split: str) -> Source | None:
    """The first CIFAR-10 source for ``split`` in ``directory`` (search order above), or None."""
    if (directory / datasets.CIFAR10.base_folder).is_dir():
        return Source("official", directory)
    for name in TREE_DIRS:
        split_dir = directory / name / split
        if any((split_dir / c).is_dir() for c in CIFAR10_CLASSES):
            return Source("tree", split_dir)
    packed = sorted([*directory.glob("cifar10*.tar.gz"), *directory.glob("cifar10*.tgz")])
    return Source("packed", packed[0]) if packed else None


def _missing_message(directory: Path, split: str) -> str:
    return (
        f"CIFAR-10 ({split} split) was not found. Looked in {directory} for, in this order:\n"
        f"  {directory / datasets.CIFAR10.base_folder}/      the official release, extracted\n"
        f"  {directory / 'cifar10' / split}/<class>/*.jpg   your own images, a folder per class\n"
        f"  {directory / 'cifar10*.tar.gz'}      such a tree of folders, packed\n"
        "To get it: call load_cifar10(download=True) on a machine with internet (torchvision\n"
        f"downloads {datasets.CIFAR10.url} and checks its MD5), or set EBJEPA_DATA\n"
        "(or pass root=...) to a folder that holds one of the above."
    )


def _read_official(directory: Path, split: str, download: bool) -> tuple[np.ndarray, np.ndarray]:
    try:
        dataset = datasets.CIFAR10(str(directory), train=split == "train", download=download)
    except RuntimeError as err:  # torchvision's words for a wrong MD5 or a missing batch file
        raise CorruptDataError(
            f"cannot read CIFAR-10 from {directory / datasets.CIFAR10.base_folder}: {err}. A file "
            "there is damaged or incomplete; delete the folder and load again (data/README.md)."
        ) from err
    images = np.ascontiguousarray(dataset.data.transpose(0, 3, 1, 2))  # NHWC -> NCHW
    return images, np.asarray(dataset.targets, dtype=np.int64)


def _download(directory: Path, split: str) -> tuple[np.ndarray, np.ndarray]:
    try:
        return _read_official(directory, split, download=True)
    except (OSError, ValueError) as err:  # no network, an HTTP error, a bad download
        message = _missing_message(directory, split)
        raise DataNotFoundError(f"{message}\n\nThe download failed: {err}") from err


def _read_tree(split_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """``<split>/<class>/*`` -> images (N, 3, 32, 32) uint8, labels (N,) int64, in sorted
    order (CIFAR-10's class names sort into its own order)."""
    try:
        folder = datasets.ImageFolder(str(split_dir), transform=FIT, allow_empty=True)
    except OSError as err:
        raise DataNotFoundError(f"no class folders in {split_dir}: {err}") from err
    present = {folder.classes[label] for label in folder.targets}
    if missing := [c for c in CIFAR10_CLASSES if c not in present]:
        raise DataNotFoundError(f"no images for class(es) {', '.join(missing)} in {split_dir}/")
    if extra := sorted(set(folder.classes) - set(CIFAR10_CLASSES)):
        raise CorruptDataError(f"{split_dir} holds folders that are not CIFAR-10 classes: {extra}")
    images = np.empty((len(folder), 3, SIZE, SIZE), dtype=np.uint8)
    for i in tqdm(range(len(folder)), desc="decoding", leave=False):
        try:
            images[i] = folder[i][0].numpy()
        except (OSError, ValueError) as err:
            raise CorruptDataError(f"cannot read image {folder.samples[i][0]}: {err}") from err
    return images, np.asarray(folder.targets, dtype=np.int64)


def _unpack(path: Path) -> Path:
    """Extract ``path`` once into the cache, via a temp folder renamed when complete (processes
    of one torchrun may race here; the first rename wins)."""
    target = cache_dir() / f"{path.name.split('.')[0]}-{source_key(path)}"
    if target.is_dir():
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    partial = Path(tempfile.mkdtemp(dir=target.parent, prefix=f".{target.name}.", suffix=".part"))
    try:
        extract_archive(str(path), str(partial))
        partial.rename(target)
    except (EOFError, tarfile.TarError, zlib.error, gzip.BadGzipFile) as err:
        raise CorruptDataError(
            f"cannot read CIFAR-10 from {path}: {type(err).__name__}: {err}. The archive is "
            "damaged or incomplete; replace it (see data/README.md)."
        ) from err
    except OSError:
        if not target.is_dir():  # not another process's finished copy: a real failure
            raise
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    return target


def _read_packed(path: Path, split: str) -> tuple[np.ndarray, np.ndarray]:
    """A tree stored as ``[<top>/]<split>/<class>/<file>`` inside a tar.gz."""
    unpacked = _unpack(path)
    for split_dir in (unpacked / split, *sorted(unpacked.glob(f"*/{split}"))):
        if any((split_dir / c).is_dir() for c in CIFAR10_CLASSES):
            return _read_tree(split_dir)
    raise DataNotFoundError(f"{path} holds no {split}/<class>/ folders of CIFAR-10 images")


def _load(source: Source, split: str) -> tuple[np.ndarray, np.ndarray]:
    """The arrays of a source; decoded image folders come from (and go to) the cache."""
    if source.kind == "official":
        return _read_official(source.path, split, download=False)
    folders = [source.path / c for c in CIFAR10_CLASSES if (source.path / c).is_dir()]
    keyed = [source.path, *folders] if source.kind == "tree" else [source.path]
    name = f"cifar10-{split}-{source.kind}-{source_key(*keyed)}"
    if (arrays := read_cache(name)) is not None:
        return arrays
    read = _read_tree(source.path) if source.kind == "tree" else _read_packed(source.path, split)
    write_cache(name, *read)
    return read


def load_cifar10(split: str = "train", root: str | os.PathLike | None = None,
                 download: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """One CIFAR-10 split: images (N, 3, 32, 32) uint8, labels (N,) int64; N = 50,000 or 10,000.

    ``root`` overrides the data directory; ``download=False`` raises DataNotFoundError
    instead of fetching the official archive.
    """
    check_split(split)
    directory = data_dir(root)
    source = find_cifar10(directory, split)
    if source is None and not download:
        raise DataNotFoundError(_missing_message(directory, split))
    images, labels = _download(directory, split) if source is None else _load(source, split)
    return torch.from_numpy(images), torch.from_numpy(labels)
