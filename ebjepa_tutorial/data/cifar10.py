"""CIFAR-10 (Krizhevsky, 2009) as uint8 tensors: the official release (torchvision, MD5-checked),
else class folders packed as ``cifar10*.tar.gz`` (decoded once, then cached)."""

from __future__ import annotations

import gzip
import os
import tarfile
import tempfile
import zlib
from pathlib import Path, PurePosixPath

import numpy as np
import torch
from tqdm.auto import tqdm

from .paths import CorruptDataError, DataNotFoundError, cached_arrays, data_dir

CIFAR10_CLASSES = (
    "airplane", "automobile", "bird", "cat", "deer", "dog", "frog", "horse", "ship", "truck",
)  # fmt: skip
OFFICIAL_FOLDER = "cifar-10-batches-py"  # torchvision's CIFAR10.base_folder


def find_cifar10(directory: Path) -> Path | None:
    """The official release's folder in ``directory``, else its first ``cifar10*.tar.gz`` (a
    file: the packed copy), else None."""
    if (directory / OFFICIAL_FOLDER).is_dir():
        return directory / OFFICIAL_FOLDER
    packed = sorted(directory.glob("cifar10*.tar.gz"))
    return packed[0] if packed else None


def _missing_message(directory: Path, split: str) -> str:
    from torchvision import datasets

    return (
        f"CIFAR-10 ({split} split) was not found. Looked in {directory} for, in this order:\n"
        f"  {directory / OFFICIAL_FOLDER}/      the official release, extracted\n"
        f"  {directory / 'cifar10*.tar.gz'}      folders {split}/<class>/ of images, packed\n"
        "To get it: call load_cifar10(download=True) on a machine with internet (torchvision\n"
        f"downloads {datasets.CIFAR10.url} and checks its MD5), or set EBJEPA_DATA\n"
        "(or pass root=...) to a folder that holds one of the above."
    )


def _read_official(directory: Path, split: str, download: bool) -> tuple[np.ndarray, np.ndarray]:
    from torchvision import datasets  # here: importing torchvision takes over a second

    try:
        dataset = datasets.CIFAR10(str(directory), train=split == "train", download=download)
    except RuntimeError as err:  # torchvision's words for a wrong MD5 or a missing batch file
        raise CorruptDataError(
            f"cannot read CIFAR-10 from {directory / OFFICIAL_FOLDER}: a file there is "
            "damaged or incomplete (its checksum fails); delete the folder and load again "
            "(data/README.md)."
        ) from err
    except (OSError, ValueError) as err:  # no network, an HTTP error, a bad download
        message = _missing_message(directory, split)
        raise DataNotFoundError(f"{message}\n\nThe download failed: {err}") from err
    images = np.ascontiguousarray(dataset.data.transpose(0, 3, 1, 2))  # NHWC -> NCHW
    return images, np.asarray(dataset.targets, dtype=np.int64)


def _read_tree(split_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    """``<split>/<class>/*`` -> images (N, 3, 32, 32) uint8, labels (N,) int64, in sorted
    order (CIFAR-10's class names sort into its own order)."""
    from torchvision import datasets
    from torchvision.transforms import v2

    # an image of another size: its largest centred square, resized to 32x32
    fit = v2.Compose([v2.PILToTensor(), v2.Resize(32), v2.CenterCrop(32)])
    folder = datasets.ImageFolder(str(split_dir), transform=fit, allow_empty=True)
    present = {folder.classes[label] for label in folder.targets}
    if tuple(folder.classes) != CIFAR10_CLASSES or len(present) < len(CIFAR10_CLASSES):
        raise DataNotFoundError(f"{split_dir} must hold images in a folder per class, "
                                f"{', '.join(CIFAR10_CLASSES)}; has some for {sorted(present)}")
    images = np.empty((len(folder), 3, 32, 32), dtype=np.uint8)
    for i in tqdm(range(len(folder)), desc="decoding", leave=False):
        try:
            images[i] = folder[i][0].numpy()
        except (OSError, ValueError) as err:
            raise CorruptDataError(f"cannot read image {folder.samples[i][0]}: {err}") from err
    return images, np.asarray(folder.targets, dtype=np.int64)


def _split_members(archive: tarfile.TarFile, split: str) -> list[tarfile.TarInfo]:
    """The files and folders under ``[<top>/]<split>/``, none that could unpack outside the
    folder it is given: no link, no absolute path, no ``..``."""
    members = []
    for member in archive:
        parts = PurePosixPath(member.name).parts
        if (member.isfile() or member.isdir()) and split in parts[:2] and parts[0] != "/" \
                and ".." not in parts:
            members.append(member)
    return members


def _read_packed(path: Path, split: str) -> tuple[np.ndarray, np.ndarray]:
    """A tree stored as ``[<top>/]<split>/<class>/<file>`` in a tar.gz, split unpacked in /tmp."""
    with tempfile.TemporaryDirectory() as unpacked:
        try:
            with tarfile.open(path) as archive:  # and Python's own filter, where it has one
                safe = {"filter": "data"} if hasattr(tarfile, "data_filter") else {}
                archive.extractall(unpacked, _split_members(archive, split), **safe)
        except (EOFError, tarfile.TarError, zlib.error, gzip.BadGzipFile) as err:
            raise CorruptDataError(
                f"cannot read CIFAR-10 from {path}: {type(err).__name__}: {err}. The archive is "
                "damaged or incomplete; replace it (see data/README.md)."
            ) from err
        for split_dir in (Path(unpacked) / split, *sorted(Path(unpacked).glob(f"*/{split}"))):
            if any((split_dir / c).is_dir() for c in CIFAR10_CLASSES):
                return _read_tree(split_dir)
    raise DataNotFoundError(f"{path} holds no {split}/<class>/ folders of CIFAR-10 images")


def load_cifar10(split: str = "train", root: str | os.PathLike | None = None,
                 download: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """One CIFAR-10 split: images (N, 3, 32, 32) uint8, labels (N,) int64; N = 50,000 or 10,000.
    ``root``: the data directory; ``download=False``: DataNotFoundError instead of fetching."""
    if split not in ("train", "test"):
        raise ValueError(f"split must be one of 'train', 'test'; got {split!r}")
    directory = data_dir(root)
    source = find_cifar10(directory)
    if source is None and not download:
        raise DataNotFoundError(_missing_message(directory, split))
    if source is None or source.is_dir():  # the official release, or its download
        images, labels = _read_official(directory, split, download=source is None)
    else:  # a packed archive: decoding its images takes seconds, so their arrays are cached
        images, labels = cached_arrays(source, f"cifar10-{split}-packed",
                                       lambda: _read_packed(source, split))
    return torch.from_numpy(images), torch.from_numpy(labels)
