"""Where data lives, the cache of decoded arrays, and files written atomically.

The data directory is an explicit ``root``, else ``$EBJEPA_DATA``, else ``<project>/data``.
The cache is ``$EBJEPA_CACHE``, else ``<project>/data/cache`` (git-ignored), never under
``EBJEPA_DATA``, which may be a read-only shared folder.
"""

from __future__ import annotations

import contextlib
import glob
import hashlib
import os
import stat
import tempfile
import time
import warnings
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import BinaryIO

import numpy as np

SPLITS = ("train", "test")


class DataNotFoundError(FileNotFoundError):
    """The data is not on disk and could not be downloaded; the message says where to put it."""


class CorruptDataError(RuntimeError):
    """A data file is damaged: truncated archive, wrong checksum, or a format we cannot read."""


def project_root() -> Path:
    """The repository root when the package runs from a checkout, else the working directory."""
    root = Path(__file__).resolve().parents[2]
    return root if (root / "pyproject.toml").is_file() else Path.cwd()


def data_dir(root: str | os.PathLike | None = None) -> Path:
    """The data directory: ``root`` if given, else ``$EBJEPA_DATA``, else ``<project>/data``."""
    if root is not None:
        return Path(root).expanduser()
    if os.environ.get("EBJEPA_DATA"):
        return Path(os.environ["EBJEPA_DATA"]).expanduser()
    return project_root() / "data"


def cache_dir() -> Path:
    """Where decoded arrays are cached: ``$EBJEPA_CACHE``, else ``<project>/data/cache``."""
    if os.environ.get("EBJEPA_CACHE"):
        return Path(os.environ["EBJEPA_CACHE"]).expanduser()
    return project_root() / "data" / "cache"


def check_split(split: str) -> None:
    """Raise ValueError naming the choices when ``split`` is not ``"train"`` or ``"test"``."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {', '.join(map(repr, SPLITS))}; got {split!r}")


def remove_stale_temporaries(folder: Path, patterns: Sequence[str],
                             older_than_s: float = 3600.0) -> list[Path]:
    """Delete the regular files in ``folder`` matching ``patterns`` and unmodified for
    ``older_than_s`` (temporaries of writes cut short by a kill); return them. Never raises."""
    cutoff, removed = time.time() - older_than_s, []
    for pattern in patterns:
        try:
            matches = sorted(Path(folder).glob(pattern))
        except OSError:
            continue
        for path in matches:
            try:
                info = path.lstat()  # a link is not ours: never follow it
                if stat.S_ISREG(info.st_mode) and info.st_mtime < cutoff:
                    path.unlink()
                    removed.append(path)
            except OSError:
                continue
    return removed


def temporaries_of(path: Path) -> str:
    """The glob of the temp files that :func:`atomic_file` makes beside ``path``."""
    return f".{glob.escape(path.name)}.*.part"


@contextlib.contextmanager
def atomic_file(path: Path) -> Iterator[BinaryIO]:
    """A binary file that appears at ``path`` whole, or not at all.

    The block writes a hidden temp file beside ``path``, synced and renamed over ``path``
    on leaving; an exception in the block deletes it and leaves ``path`` as it was.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".part")
    try:
        with os.fdopen(fd, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())  # on disk before the rename: a power loss leaves no empty file
        os.chmod(tmp, 0o644)  # mkstemp makes it private; these are ordinary shared files
        os.replace(tmp, path)
    finally:
        Path(tmp).unlink(missing_ok=True)


def source_key(*paths: Path) -> str:
    """A short hash of these files or folders (path, size, modification time), for cache names:
    editing a source, or adding or removing a file in a folder, invalidates its cache."""
    digest = hashlib.sha1()
    for path in paths:
        info = path.stat()
        digest.update(f"{path.resolve()}|{info.st_size}|{info.st_mtime_ns};".encode())
    return digest.hexdigest()[:12]


def _cache_paths(name: str) -> tuple[Path, Path]:
    folder = cache_dir()
    return folder / f"{name}-images.npy", folder / f"{name}-labels.npy"


def read_cache(name: str) -> tuple[np.ndarray, np.ndarray] | None:
    """The ``(images, labels)`` arrays cached under ``name``; None if absent or damaged."""
    images_path, labels_path = _cache_paths(name)
    remove_stale_temporaries(images_path.parent, [".*.npy.*.part"])
    if not (images_path.is_file() and labels_path.is_file()):
        return None
    try:
        images, labels = np.load(images_path), np.load(labels_path)
    except (OSError, ValueError, EOFError):  # EOFError: a zero-byte file
        return None
    return (images, labels) if len(images) == len(labels) else None


def write_cache(name: str, images: np.ndarray, labels: np.ndarray) -> None:
    """Save ``images`` and ``labels`` under ``name``, each file atomically; only warn on failure."""
    images_path, labels_path = _cache_paths(name)
    try:
        for path, array in ((images_path, images), (labels_path, labels)):
            with atomic_file(path) as f:
                np.save(f, array)
    except OSError as err:  # a read-only or full disk costs speed next time, not this result
        warnings.warn(f"could not cache {name} in {images_path.parent}: {err}", stacklevel=3)
