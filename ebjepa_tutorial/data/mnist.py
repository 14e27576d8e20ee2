"""MNIST digits as uint8 tensors, read from the official IDX files.

MNIST (LeCun et al., 1998): 28x28 grey handwritten digits, 60,000 for training
and 10,000 for testing, distributed as four IDX files (gzip-compressed). An
IDX file is a 4-byte magic number (two zero bytes, a type code, 0x08 for
unsigned bytes, and the number of dimensions), one big-endian 32-bit size per
dimension, then the values row by row.

:func:`load_mnist` looks for the two files of a split, ``.gz`` or uncompressed,
in ``<data>/mnist/``, ``<data>/MNIST/raw/`` (torchvision's layout), then
``<data>/`` itself, and downloads them into ``<data>/mnist/`` when absent.
"""

from __future__ import annotations

import gzip
import os
import struct
import zlib
from pathlib import Path

import numpy as np
import torch

from .paths import (
    CorruptDataError,
    DataNotFoundError,
    DownloadError,
    check_split,
    data_dir,
    download,
    md5sum,
    read_cache,
    source_key,
    write_cache,
)

SPLITS = ("train", "test")
MNIST_MIRRORS = (
    "https://ossci-datasets.s3.amazonaws.com/mnist/",
    "http://yann.lecun.com/exdb/mnist/",
)
MNIST_FILES = {  # split -> (images, labels), without the .gz
    "train": ("train-images-idx3-ubyte", "train-labels-idx1-ubyte"),
    "test": ("t10k-images-idx3-ubyte", "t10k-labels-idx1-ubyte"),
}
MNIST_MD5 = {  # of the official .gz files
    "train-images-idx3-ubyte.gz": "f68b3c2dcbeaaa9fbdd348bbdeb94873",
    "train-labels-idx1-ubyte.gz": "d53e105ee54ea40749a09fcbcd1e9432",
    "t10k-images-idx3-ubyte.gz": "9fb629c4189551a2d022fa330f9573f3",
    "t10k-labels-idx1-ubyte.gz": "ec29112dd5afa0611ce80d1b7f02629c",
}


def _folders(directory: Path) -> list[Path]:
    return [directory / "mnist", directory / "MNIST" / "raw", directory]


def find_mnist(directory: Path, split: str) -> tuple[Path, Path] | None:
    """Paths of the (images, labels) IDX files of ``split`` under ``directory``, or None."""
    for folder in _folders(directory):
        found = []
        for stem in MNIST_FILES[split]:
            candidates = [folder / f"{stem}.gz", folder / stem]
            found += [p for p in candidates if p.is_file()][:1]
        if len(found) == 2:
            return found[0], found[1]
    return None


def read_idx(path: Path) -> np.ndarray:
    """Read an unsigned-byte IDX file (``.gz`` or raw) into an array of its stated shape."""
    opener = gzip.open if path.suffix == ".gz" else open
    try:
        with opener(path, "rb") as f:
            raw = f.read()
    except (OSError, EOFError, zlib.error) as err:  # bad gzip, truncated stream
        raise CorruptDataError(f"cannot read {path}: {type(err).__name__}: {err}") from err
    if len(raw) < 4 or raw[0] != 0 or raw[1] != 0 or raw[2] != 0x08:
        raise CorruptDataError(f"{path} is not an unsigned-byte IDX file (bad magic number)")
    ndim = raw[3]
    if len(raw) < 4 + 4 * ndim:
        raise CorruptDataError(f"{path} is truncated (header cut short)")
    shape = struct.unpack(f">{ndim}I", raw[4 : 4 + 4 * ndim])
    body = raw[4 + 4 * ndim :]
    if len(body) != int(np.prod(shape)):
        raise CorruptDataError(
            f"{path} holds {len(body):,} values, but its header announces {shape} "
            f"= {int(np.prod(shape)):,}: the file is truncated or damaged"
        )
    return np.frombuffer(body, dtype=np.uint8).reshape(shape).copy()


def _missing_message(directory: Path, split: str) -> str:
    names = [f"{stem}.gz" for stem in MNIST_FILES[split]]
    urls = "\n".join(f"  {MNIST_MIRRORS[0]}{name}  (MD5 {MNIST_MD5[name]})" for name in names)
    message = (
        f"MNIST ({split} split) was not found. Looked for {names[0]} and {names[1]}\n"
        f"(or the same files uncompressed) in: {', '.join(map(str, _folders(directory)))}.\n"
        "To get them: call load_mnist(download=True) on a machine with internet, or download\n"
        f"{urls}\ninto {directory / 'mnist'}/, or set EBJEPA_DATA (or pass root=...) "
        "to a folder that holds them."
    )
    other = "test" if split == "train" else "train"
    if (found := find_mnist(directory, other)) is not None:
        message += f"\n(Only the {other} split is there: {found[0].parent}.)"
    return message


def _download(directory: Path, split: str, folder: Path | None = None) -> tuple[Path, Path]:
    """Fetch both files of ``split`` into ``folder`` (default ``<data>/mnist``), MD5-checked."""
    folder = folder if folder is not None else directory / "mnist"
    paths = []
    for stem in MNIST_FILES[split]:
        name = f"{stem}.gz"
        try:
            urls = [mirror + name for mirror in MNIST_MIRRORS]
            paths.append(download(urls, folder / name, MNIST_MD5[name]))
        except DownloadError as err:
            message = _missing_message(directory, split)
            raise DataNotFoundError(f"{message}\n\nThe download failed: {err}") from err
    return paths[0], paths[1]


def _checked(files: tuple[Path, Path], directory: Path, split: str, download: bool):
    """``files`` if every official ``.gz`` among them has its MD5; else re-download or raise."""
    bad = [p for p in files if p.name in MNIST_MD5 and md5sum(p) != MNIST_MD5[p.name]]
    if not bad:
        return files
    if download:
        print(f"{', '.join(map(str, bad))}: wrong MD5, downloading fresh copies.")
        return _download(directory, split, folder=files[0].parent)
    raise CorruptDataError(
        f"{bad[0]} has the wrong MD5 (expected {MNIST_MD5[bad[0].name]}): it is damaged or "
        "incomplete. Delete it and download it again (or call with download=True)."
    )


def _read_split(images_path: Path, labels_path: Path) -> tuple[np.ndarray, np.ndarray]:
    images, labels = read_idx(images_path), read_idx(labels_path)
    if images.ndim != 3 or labels.ndim != 1 or len(images) != len(labels):
        raise CorruptDataError(
            f"{images_path} {images.shape} and {labels_path} {labels.shape} do not match: "
            "expected (N, H, W) images and (N,) labels"
        )
    return images[:, None], labels.astype(np.int64)


def load_mnist(
    split: str = "train", root: str | os.PathLike | None = None, download: bool = True
) -> tuple[torch.Tensor, torch.Tensor]:
    """Load one MNIST split: images (N, 1, 28, 28) uint8 and labels (N,) int64 in 0..9.

    N is 60,000 for ``"train"`` and 10,000 for ``"test"``. ``root`` overrides
    the data directory; ``download=False`` raises DataNotFoundError instead of
    fetching the files. Decoded arrays are cached (see ``paths.cache_dir``).
    """
    check_split(split, SPLITS)
    directory = data_dir(root)
    files = find_mnist(directory, split)
    if files is None:
        if not download:
            raise DataNotFoundError(_missing_message(directory, split))
        files = _download(directory, split)
    arrays = read_cache(f"mnist-{split}-{source_key(*files)}")
    if arrays is None:
        files = _checked(files, directory, split, download)
        arrays = _read_split(*files)
        write_cache(f"mnist-{split}-{source_key(*files)}", *arrays)
    images, labels = arrays
    return torch.from_numpy(images), torch.from_numpy(labels)
