"""MNIST digits as uint8 tensors, read from the official IDX files.

MNIST (LeCun et al., 1998): 28x28 grey handwritten digits, 60,000 for training
and 10,000 for testing, distributed as four IDX files (gzip-compressed). An
IDX file is a 4-byte magic number (two zero bytes, a type code, 0x08 for
unsigned bytes, and the number of dimensions), one big-endian 32-bit size per
dimension, then the values row by row.

:func:`load_mnist` looks for the two files of a split, ``.gz`` or uncompressed,
in ``<data>/mnist/``, ``<data>/MNIST/raw/`` (torchvision's layout), then
``<data>/`` itself, and downloads them into ``<data>/mnist/`` when absent. An
official ``.gz`` with the wrong MD5 is replaced by a fresh download when
allowed, else skipped, with a warning, for the next copy found.
"""

from __future__ import annotations

import gzip
import itertools
import os
import struct
import warnings
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
    read_cache,
    source_key,
    verify_md5,
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


def mnist_sources(directory: Path, split: str) -> list[tuple[Path, Path]]:
    """Every (images, labels) pair of IDX files of ``split`` under ``directory``, best first.

    Both files of a pair come from the same folder (Fashion-MNIST uses the same
    names, so mixing folders could mix datasets); ``.gz`` comes before uncompressed.
    """
    pairs = []
    for folder in _folders(directory):
        forms = [[p for p in (folder / f"{stem}.gz", folder / stem) if p.is_file()]
                 for stem in MNIST_FILES[split]]  # fmt: skip
        pairs += itertools.product(*forms)
    return pairs


def find_mnist(directory: Path, split: str) -> tuple[Path, Path] | None:
    """Paths of the (images, labels) IDX files of ``split`` under ``directory``, or None."""
    pairs = mnist_sources(directory, split)
    return pairs[0] if pairs else None


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
    bad = [p for folder in _folders(directory) for p in sorted(folder.glob("*-ubyte*.bad"))]
    if bad:
        names = ", ".join(map(str, bad))
        message += f"\n(Damaged copies set aside by an earlier run, to delete: {names}.)"
    other = "test" if split == "train" else "train"
    if (found := find_mnist(directory, other)) is not None:
        message += f"\n(Only the {other} split is there: {found[0].parent}.)"
    return message


def _urls(name: str) -> list[str]:
    return [mirror + name for mirror in MNIST_MIRRORS]


def _download(directory: Path, split: str) -> tuple[Path, Path]:
    """Fetch both files of ``split`` into ``<data>/mnist``, MD5-checked."""
    paths = []
    for stem in MNIST_FILES[split]:
        name = f"{stem}.gz"
        try:
            paths.append(download(_urls(name), directory / "mnist" / name, MNIST_MD5[name]))
        except DownloadError as err:
            message = _missing_message(directory, split)
            raise DataNotFoundError(f"{message}\n\nThe download failed: {err}") from err
    return paths[0], paths[1]


def _damaged(files: tuple[Path, Path], download: bool) -> dict[Path, str]:
    """The official ``.gz`` files among ``files`` with the wrong MD5 that could not be
    replaced (see ``paths.verify_md5``), each with the message saying so."""
    problems = {}
    for path in files:
        if path.name in MNIST_MD5:
            problem = verify_md5(path, MNIST_MD5[path.name], _urls(path.name), download)
            if problem is not None:
                problems[path] = problem
    return problems


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
    pairs = mnist_sources(directory, split)
    if not pairs:
        if not download:
            raise DataNotFoundError(_missing_message(directory, split))
        pairs = [_download(directory, split)]
    problems: dict[Path, str] = {}
    for files in pairs:
        if problems.keys() & set(files):  # a damaged file (perhaps renamed since) in this pair
            continue
        arrays = read_cache(f"mnist-{split}-{source_key(*files)}")
        if arrays is None:
            if damaged := _damaged(files, download):
                problems |= damaged
                continue
            arrays = _read_split(*files)
            write_cache(f"mnist-{split}-{source_key(*files)}", *arrays)  # after any re-download
        if problems:
            others = ", ".join(map(str, files))
            warnings.warn(f"{' '.join(problems.values())} Reading {others} instead.", stacklevel=2)
        images, labels = arrays
        return torch.from_numpy(images), torch.from_numpy(labels)
    raise CorruptDataError(
        "\n".join(problems.values()) + f"\nNo other copy of the MNIST {split} files is under "
        f"{directory}; put good ones in {directory / 'mnist'} (see data/README.md)."
    )
