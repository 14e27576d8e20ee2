"""Tests that the data loaders lose nothing and trust nothing damaged (issue 26).

A damaged cache file is decoded again; atomic writes reach the disk before
their rename; temporaries left by a killed run are removed later. All on small
files generated here. (Checksums of downloads are torchvision's: test_data.py.)
"""

import os
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from test_data import leftovers, write_packed

from ebjepa_tutorial.data import load_cifar10, paths

HOUR = 3600.0


@pytest.fixture(autouse=True)
def tmp_cache(tmp_path, monkeypatch):
    """Every test gets its own cache; none touches the project's data/cache."""
    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("EBJEPA_DATA", raising=False)
    return tmp_path / "cache"


def old_file(path: Path, seconds: float = 2 * HOUR) -> Path:
    """Write a small file at ``path``, last modified ``seconds`` ago."""
    path.write_bytes(b"x")
    then = time.time() - seconds
    os.utime(path, (then, then))
    return path


# --- (a) a damaged cache file is treated as absent ------------------------------------------


@pytest.mark.parametrize(
    "which, damage",
    [
        ("images", lambda raw: b""),  # zero bytes: numpy raises EOFError
        ("images", lambda raw: raw[:20]),  # cut inside the header
        ("labels", lambda raw: raw[:-3]),  # cut inside the data
    ],
    ids=["zero-byte", "cut-header", "cut-data"],
)
def test_damaged_cache_file_is_decoded_again_and_rewritten(tmp_path, tmp_cache, which, damage):
    write_packed(tmp_path / "data")
    first, first_labels = load_cifar10("test", root=tmp_path / "data", download=False)
    (cached,) = tmp_cache.glob(f"*-{which}.npy")
    cached.write_bytes(damage(cached.read_bytes()))
    again, again_labels = load_cifar10("test", root=tmp_path / "data", download=False)
    assert torch.equal(first, again) and torch.equal(first_labels, again_labels)
    assert len(np.load(cached)) == len(first)  # rewritten whole
    assert leftovers(tmp_cache) == []


# --- (b) atomic writes are flushed to disk before the rename --------------------------------


def test_atomic_writers_fsync_before_rename(tmp_path, monkeypatch):
    events = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        events.append("fsync")
        real_fsync(fd)

    def replace(src, dst):
        events.append(f"replace {Path(dst).name}")
        real_replace(src, dst)

    monkeypatch.setattr(paths.os, "fsync", fsync)
    monkeypatch.setattr(paths.os, "replace", replace)
    (tmp_path / "source").write_bytes(b"x")
    paths.cached_arrays(tmp_path / "source", "x",
                        lambda: (np.zeros((2, 3), np.uint8), np.zeros(2, np.int64)))
    assert [e.split("-")[0] for e in events] == ["fsync", "replace x", "fsync", "replace x"]
    assert events[1].endswith("-images.npy") and events[3].endswith("-labels.npy")


# --- (c) temporaries left by a killed run -----------------------------------------------------


def test_an_atomic_write_cut_short_keeps_the_old_file_and_no_temporary(tmp_path):
    path = tmp_path / "results.json"
    with paths.atomic_file(path) as f:
        f.write(b"old")
    with pytest.raises(KeyboardInterrupt), paths.atomic_file(path) as f:
        f.write(b"new, half written")
        raise KeyboardInterrupt  # a user stopping the kernel mid-write
    assert path.read_bytes() == b"old" and sorted(tmp_path.iterdir()) == [path]
    assert path.stat().st_mode & 0o777 == 0o644  # readable by all, unlike mkstemp's own files

def test_remove_stale_temporaries_keeps_fresh_and_unrelated_files(tmp_path):
    folder = tmp_path / "checkpoints"
    folder.mkdir()
    stale, stale_tmp = old_file(folder / ".run.pt.abc123.part"), old_file(folder / "run.pt.tmp")
    fresh = old_file(folder / ".run.pt.def456.part", seconds=0)  # a live writer's: spared
    unrelated = old_file(folder / "run.pt")
    removed = paths.remove_stale_temporaries(folder, [".*.part", "*.tmp"])
    assert sorted(removed) == sorted([stale, stale_tmp])
    assert fresh.exists() and unrelated.exists() and not stale.exists()
    assert paths.remove_stale_temporaries(tmp_path / "absent", ["*.tmp"]) == []


def test_remove_stale_temporaries_never_raises_on_an_unreadable_folder(tmp_path):
    folder = tmp_path / "locked"
    folder.mkdir()
    old_file(folder / "a.tmp")
    folder.chmod(0o000)
    try:
        removed = paths.remove_stale_temporaries(folder, ["*.tmp"])
    finally:
        folder.chmod(0o755)
    assert removed in ([], [folder / "a.tmp"])  # root may read it anyway; it must not raise


def test_loads_clean_their_stale_temporaries(tmp_path, tmp_cache):
    write_packed(tmp_path / "data")
    tmp_cache.mkdir()
    stale = old_file(tmp_cache / ".cifar10-test-packed-0123-images.npy.k2j4.part")
    fresh = old_file(tmp_cache / ".cifar10-test-packed-0123-labels.npy.m9x1.part", seconds=0)
    load_cifar10("test", root=tmp_path / "data", download=False)
    assert not stale.exists() and fresh.exists()
