"""CIFAR-10 as uint8 tensors, from the official archive or from folders of images.

CIFAR-10 (Krizhevsky, 2009): 60,000 colour images of 32x32 pixels in 10
classes, 50,000 for training and 10,000 for testing. :func:`load_cifar10`
looks inside the data directory (see ``paths.data_dir``), in this order, for:

1. ``cifar-10-batches-py/``: the official python archive, extracted;
2. ``cifar-10-python.tar.gz``: the official archive itself (MD5-checked);
3. a tree of class folders, ``cifar10/<split>/<class>/*.jpg`` (also ``cifar-10/``,
   ``cifar10-jpeg/``, or ``<split>/<class>/`` directly in the data directory);
4. such a tree packed as ``cifar10*.tar.gz`` (for example ``cifar10-jpeg.tar.gz``);

and downloads the official archive only when none is found. An official
archive with the wrong MD5 is replaced by a fresh download when allowed, else
skipped, with a warning, for the next copy found. The decoded arrays are
cached, so only the first load of each split is slow.
"""

from __future__ import annotations

import codecs
import gzip
import io
import os
import pickle
import tarfile
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np
import torch
from PIL import Image, ImageOps
from tqdm.auto import tqdm

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

CIFAR10_CLASSES = (
    "airplane", "automobile", "bird", "cat", "deer", "dog", "frog", "horse", "ship", "truck",
)  # fmt: skip
SPLITS = ("train", "test")
CIFAR10_URL = "https://www.cs.toronto.edu/~kriz/cifar-10-python.tar.gz"
CIFAR10_MD5 = "c58f30108f718f92721af3b95e74349a"
TARBALL = "cifar-10-python.tar.gz"
BATCHES_DIR = "cifar-10-batches-py"
TREE_DIRS = ("cifar10", "cifar-10", "cifar10-jpeg", ".")
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".bmp", ".gif", ".webp"}
SIZE = 32


@dataclass(frozen=True)
class Source:
    """Where one split was found: ``kind`` is batches, official, tree or packed."""

    kind: str
    path: Path


def _batch_names(split: str) -> list[str]:
    return [f"data_batch_{i}" for i in range(1, 6)] if split == "train" else ["test_batch"]


def cifar10_sources(directory: Path, split: str) -> list[Source]:
    """Every CIFAR-10 source for ``split`` in ``directory``, best first (search order above)."""
    sources = [Source("batches", folder) for folder in (directory / BATCHES_DIR, directory)
               if all((folder / name).is_file() for name in _batch_names(split))]  # fmt: skip
    if (directory / TARBALL).is_file():
        sources.append(Source("official", directory / TARBALL))
    for name in TREE_DIRS:
        split_dir = directory / name / split
        if any((split_dir / c).is_dir() for c in CIFAR10_CLASSES):
            sources.append(Source("tree", split_dir))
    packed = sorted([*directory.glob("cifar10*.tar.gz"), *directory.glob("cifar10*.tgz")])
    return sources + [Source("packed", path) for path in packed]


def find_cifar10(directory: Path, split: str) -> Source | None:
    """The first CIFAR-10 source for ``split`` in ``directory`` (search order above), or None."""
    sources = cifar10_sources(directory, split)
    return sources[0] if sources else None


def _missing_message(directory: Path, split: str) -> str:
    return (
        f"CIFAR-10 ({split} split) was not found. Looked in {directory} for, in this order:\n"
        f"  {directory / BATCHES_DIR}/      the official python archive, extracted\n"
        f"  {directory / TARBALL}      the official archive\n"
        f"  {directory / 'cifar10' / split}/<class>/*.jpg   your own images, a folder per class\n"
        f"  {directory / 'cifar10*.tar.gz'}      such a tree of folders, packed\n"
        "To get it: call load_cifar10(download=True) on a machine with internet, or download\n"
        f"  {CIFAR10_URL} (MD5 {CIFAR10_MD5})\n"
        f"and put it at {directory / TARBALL}; or set EBJEPA_DATA (or pass root=...) "
        "to a folder that holds one of the above." + _set_aside_note(directory / TARBALL)
    )


def _set_aside_note(path: Path) -> str:
    """A line about ``<path>.bad``, a damaged copy that an earlier run renamed, if it is there."""
    bad = path.with_name(path.name + ".bad")
    if not bad.is_file():
        return ""
    return f"\n({bad} is a damaged copy set aside by an earlier run: delete it.)"


def _download_official(directory: Path, split: str) -> Path:
    try:
        return download([CIFAR10_URL], directory / TARBALL, CIFAR10_MD5)
    except DownloadError as err:
        message = _missing_message(directory, split)
        raise DataNotFoundError(f"{message}\n\nThe download failed: {err}") from err


_SAFE_GLOBALS = {  # all a CIFAR-10 batch pickle refers to; anything else could run code
    ("numpy.core.multiarray", "_reconstruct"): np.empty(0).__reduce__()[0],
    ("numpy._core.multiarray", "_reconstruct"): np.empty(0).__reduce__()[0],
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
    ("_codecs", "encode"): codecs.encode,
}


class _BatchUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str):
        if (module, name) not in _SAFE_GLOBALS:
            raise pickle.UnpicklingError(f"unexpected object {module}.{name} in a CIFAR-10 batch")
        return _SAFE_GLOBALS[(module, name)]


def _read_batch(raw: bytes) -> tuple[np.ndarray, np.ndarray]:
    """One pickled batch -> images (n, 3, 32, 32) uint8 and labels (n,) int64.

    Each row of ``data`` holds the red, then green, then blue 32x32 plane, row by row.
    """
    batch = _BatchUnpickler(io.BytesIO(raw), encoding="bytes").load()
    data = np.asarray(batch[b"data"], dtype=np.uint8)
    return data.reshape(-1, 3, SIZE, SIZE), np.asarray(batch[b"labels"], dtype=np.int64)


def _check_complete(path: Path) -> None:
    """Decompress ``path`` once to its end: a truncated .tar.gz raises EOFError here.

    Reading a tar stream alone is not enough: a cut inside the archive can end
    the member listing early without an error, and whole classes go missing.
    """
    with gzip.open(path, "rb") as stream:
        while stream.read(1 << 20):
            pass


def _read_official(source: Source, split: str) -> tuple[np.ndarray, np.ndarray]:
    names = _batch_names(split)
    if source.kind == "batches":
        raws = {name: (source.path / name).read_bytes() for name in names}
    else:
        raws = {}
        _check_complete(source.path)
        with tarfile.open(source.path, "r|gz") as archive:
            for member in archive:
                name = PurePosixPath(member.name).name
                if member.isfile() and name in names:
                    raws[name] = archive.extractfile(member).read()
        if missing := [n for n in names if n not in raws]:
            raise CorruptDataError(f"{source.path} lacks {', '.join(missing)}")
    batches = [_read_batch(raws[name]) for name in names]
    return np.concatenate([b[0] for b in batches]), np.concatenate([b[1] for b in batches])


def _decode_image(raw: bytes) -> np.ndarray:
    """Image file bytes -> (32, 32, 3) uint8; other sizes are centre-cropped and resized."""
    with Image.open(io.BytesIO(raw)) as image:
        if image.mode != "RGB":
            image = image.convert("RGB")
        if image.size != (SIZE, SIZE):
            image = ImageOps.fit(image, (SIZE, SIZE), Image.Resampling.BICUBIC)
        return np.asarray(image)


def _decode_all(items: list[tuple[int, str, bytes]]) -> tuple[np.ndarray, np.ndarray]:
    """(label, name, file bytes) items -> images (N, 3, 32, 32) uint8, labels (N,) int64.

    Sorted by label, then name, so the order never depends on the file system.
    One thread: these images are so small that threads only add overhead.
    """
    items.sort(key=lambda item: item[:2])
    images = np.empty((len(items), SIZE, SIZE, 3), dtype=np.uint8)
    for i, (_, name, raw) in enumerate(tqdm(items, desc="decoding", leave=False)):
        try:
            images[i] = _decode_image(raw)
        except (OSError, ValueError) as err:
            raise CorruptDataError(f"cannot read image {name}: {err}") from err
    labels = np.array([label for label, _, _ in items], dtype=np.int64)
    return np.ascontiguousarray(images.transpose(0, 3, 1, 2)), labels


def _check_classes(items: list[tuple[int, str, bytes]], where: str) -> None:
    present = {label for label, _, _ in items}
    if missing := [c for i, c in enumerate(CIFAR10_CLASSES) if i not in present]:
        raise DataNotFoundError(f"no images for class(es) {', '.join(missing)} in {where}")


def _read_tree(split_dir: Path) -> tuple[np.ndarray, np.ndarray]:
    items = []
    for label, name in enumerate(CIFAR10_CLASSES):
        folder = split_dir / name
        files = sorted(folder.iterdir()) if folder.is_dir() else []
        items += [(label, str(f), f.read_bytes()) for f in files
                  if f.suffix.lower() in IMAGE_SUFFIXES]  # fmt: skip
    _check_classes(items, f"{split_dir}/<class>/")
    return _decode_all(items)


def _read_packed(path: Path, split: str) -> tuple[np.ndarray, np.ndarray]:
    """Images stored as ``[<top>/]<split>/<class>/<file>`` inside a tar.gz."""
    index = {name: label for label, name in enumerate(CIFAR10_CLASSES)}
    items = []
    _check_complete(path)
    with tarfile.open(path, "r|gz") as archive:
        for member in archive:
            parts = PurePosixPath(member.name).parts
            if (member.isfile() and len(parts) >= 3 and parts[-3] == split
                    and parts[-2] in index and PurePosixPath(parts[-1]).suffix.lower()
                    in IMAGE_SUFFIXES):  # fmt: skip
                items.append((index[parts[-2]], member.name, archive.extractfile(member).read()))
    _check_classes(items, f"{path} (under {split}/<class>/)")
    return _decode_all(items)


def _read_source(source: Source, split: str) -> tuple[np.ndarray, np.ndarray]:
    """Decode one split; any failure of the underlying format becomes CorruptDataError."""
    try:
        if source.kind == "tree":
            return _read_tree(source.path)
        if source.kind == "packed":
            return _read_packed(source.path, split)
        return _read_official(source, split)
    except (DataNotFoundError, CorruptDataError):
        raise
    except (OSError, EOFError, tarfile.TarError, zlib.error, pickle.UnpicklingError,
            KeyError, ValueError, TypeError) as err:  # fmt: skip
        raise CorruptDataError(
            f"cannot read CIFAR-10 from {source.path}: {type(err).__name__}: {err}. The file is "
            "damaged, incomplete or not in the expected layout; replace it (see data/README.md)."
        ) from err


def _key_paths(source: Source, split: str) -> list[Path]:
    if source.kind == "batches":
        return [source.path / name for name in _batch_names(split)]
    if source.kind == "tree":
        folders = [source.path / name for name in CIFAR10_CLASSES]
        return [source.path, *(folder for folder in folders if folder.is_dir())]
    return [source.path]


def _cache_name(source: Source, split: str) -> str:
    return f"cifar10-{split}-{source.kind}-{source_key(*_key_paths(source, split))}"


def _load_source(source: Source, split: str, download: bool) -> tuple[np.ndarray, ...] | str:
    """The decoded arrays of ``source``, cached; or, for an official archive with the
    wrong MD5 that could not be replaced, the message saying so."""
    arrays = read_cache(_cache_name(source, split))
    if arrays is not None:
        return arrays
    if source.kind == "official":
        problem = verify_md5(source.path, CIFAR10_MD5, [CIFAR10_URL], download)
        if problem is not None:
            return problem
    arrays = _read_source(source, split)
    write_cache(_cache_name(source, split), *arrays)  # after a re-download the key is new
    return arrays


def load_cifar10(
    split: str = "train", root: str | os.PathLike | None = None, download: bool = True
) -> tuple[torch.Tensor, torch.Tensor]:
    """Load one CIFAR-10 split: images (N, 3, 32, 32) uint8 and labels (N,) int64.

    ``root`` overrides the data directory; ``download=False`` raises
    DataNotFoundError instead of fetching the official archive. N is 50,000
    for ``"train"`` and 10,000 for ``"test"``. The first load decodes (seconds)
    and caches the arrays; later loads read the cache (a fraction of a second).
    """
    check_split(split, SPLITS)
    directory = data_dir(root)
    sources = cifar10_sources(directory, split)
    if not sources:
        if not download:
            raise DataNotFoundError(_missing_message(directory, split))
        sources = [Source("official", _download_official(directory, split))]
    problems = []
    for source in sources:
        arrays = _load_source(source, split, download)
        if isinstance(arrays, str):
            problems.append(arrays)
            continue
        if problems:
            warnings.warn(f"{' '.join(problems)} Reading {source.path} instead.", stacklevel=2)
        images, labels = arrays
        return torch.from_numpy(images), torch.from_numpy(labels)
    raise CorruptDataError(
        "\n".join(problems) + f"\nNo other copy of CIFAR-10 ({split} split) is in {directory}; "
        "put a good one there (see data/README.md)."
    )
