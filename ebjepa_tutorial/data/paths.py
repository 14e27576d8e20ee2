"""Where data lives (``root``, else ``$EBJEPA_DATA``, else ``<project>/data``), the cache of
decoded arrays (``$EBJEPA_CACHE``, else ``<project>/data/cache``), and atomic file writes."""

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


def remove_stale_temporaries(folder: Path, patterns: list[str]) -> list[Path]:
    """Delete and return the regular files in ``folder`` matching ``patterns`` and unmodified
    for an hour (left by a killed write, not a live one). Never raises."""
    cutoff, removed = time.time() - 3600.0, []
    for pattern in patterns:
        with contextlib.suppress(OSError):
            for path in sorted(Path(folder).glob(pattern)):
                with contextlib.suppress(OSError):
                    info = path.lstat()  # a link is not ours: never follow it
                    if stat.S_ISREG(info.st_mode) and info.st_mtime < cutoff:
                        path.unlink()
                        removed.append(path)
    return removed


@contextlib.contextmanager
def atomic_file(path: Path):
    """A binary file that appears at ``path`` whole, or not at all: a hidden temp file beside
    it, synced and renamed over ``path`` on leaving the block, deleted on an exception (or, if
    a kill left it, by a later write to ``path``)."""
    remove_stale_temporaries(path.parent, [f".{glob.escape(path.name)}.*.part"])
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
    """``decode()``'s ``(images, labels)`` arrays, cached as two ``.npy`` files keyed by
    ``source``'s path, size and time (a replaced source is decoded again)."""
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
