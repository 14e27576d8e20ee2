"""Where data lives (``root``, else ``$EBJEPA_DATA``, else ``<project>/data``), the cache of
decoded arrays (``$EBJEPA_CACHE``, else ``<project>/data/cache``, never under a read-only
``EBJEPA_DATA``), and files written atomically."""

from __future__ import annotations

import contextlib
import glob
import hashlib
import os
import stat
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np


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
    return Path(root or os.environ.get("EBJEPA_DATA") or project_root() / "data").expanduser()


def cache_dir() -> Path:
    """Where decoded arrays are cached: ``$EBJEPA_CACHE``, else ``<project>/data/cache``."""
    return Path(os.environ.get("EBJEPA_CACHE") or project_root() / "data" / "cache").expanduser()


def check_split(split: str) -> None:
    if split not in ("train", "test"):
        raise ValueError(f"split must be one of 'train', 'test'; got {split!r}")


def remove_stale_temporaries(folder: Path, patterns: list[str],
                             older_than_s: float = 3600.0) -> list[Path]:
    """Delete the regular files in ``folder`` matching ``patterns`` and unmodified for
    ``older_than_s`` (an hour: temporaries of writes cut short by a kill, not of live ones);
    return them. Never raises."""
    cutoff, removed = time.time() - older_than_s, []
    for pattern in patterns:
        with contextlib.suppress(OSError):
            for path in sorted(Path(folder).glob(pattern)):
                with contextlib.suppress(OSError):
                    info = path.lstat()  # a link is not ours: never follow it
                    if stat.S_ISREG(info.st_mode) and info.st_mtime < cutoff:
                        path.unlink()
                        removed.append(path)
    return removed


def temporaries_of(path: Path) -> str:
    """The glob of the temp files that :func:`atomic_file` makes beside ``path``."""
    return f".{glob.escape(path.name)}.*.part"


@contextlib.contextmanager
def atomic_file(path: Path):
    """A binary file that appears at ``path`` whole, or not at all: a hidden temp file beside
    it, synced and renamed over ``path`` on leaving the block, deleted on an exception."""
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


def cached_arrays(source: Path, name: str, decode) -> tuple[np.ndarray, np.ndarray]:
    """``decode()``'s ``(images, labels)`` arrays, cached as two ``.npy`` files named after
    ``name`` and ``source``'s path, size and time, so that a replaced source or a damaged
    cache file is decoded again; a failure to save only warns."""
    info, folder = source.stat(), cache_dir()
    key = hashlib.sha1(f"{source.resolve()}|{info.st_size}|{info.st_mtime_ns};".encode())
    files = [folder / f"{name}-{key.hexdigest()[:12]}-{part}.npy" for part in ("images", "labels")]
    remove_stale_temporaries(folder, [".*.npy.*.part"])  # any cache's, older keys' too
    try:
        images, labels = (np.load(path) for path in files)
        if len(images) == len(labels):
            return images, labels
    except (OSError, ValueError, EOFError):  # absent, or damaged (EOFError: a zero-byte file)
        pass
    images, labels = decode()
    try:
        for path, array in zip(files, (images, labels)):
            with atomic_file(path) as f:
                np.save(f, array)
    except OSError as err:  # a read-only or full disk costs speed next time, not this result
        warnings.warn(f"could not cache {name} in {folder}: {err}", stacklevel=2)
    return images, labels
