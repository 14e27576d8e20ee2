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


def _decode_counting(calls: list, value: int = 0, n: int = 3):
    """A ``decode`` for cached_arrays that notes each call: images (n, 2) filled with value."""
    def decode():
        calls.append(value)
        return np.full((n, 2), value, np.uint8), np.arange(n)
    return decode


def test_cached_images_and_labels_of_different_lengths_are_decoded_again(tmp_path, tmp_cache):
    """Two readable cache files that disagree in length (one left by another decode) are no
    dataset: the arrays are decoded again and rewritten, not returned mismatched."""
    source, calls = tmp_path / "source", []
    source.write_bytes(b"x")
    paths.cached_arrays(source, "x", _decode_counting(calls))
    (labels_file,) = tmp_cache.glob("*-labels.npy")
    np.save(labels_file, np.arange(2))
    images, labels = paths.cached_arrays(source, "x", _decode_counting(calls))
    assert calls == [0, 0] and len(images) == len(labels) == 3
    assert len(np.load(labels_file)) == 3


def test_two_sources_of_one_size_and_time_keep_their_own_cache(tmp_path, tmp_cache):
    """The cache key holds the source's path, not only its size and time: two copies of an
    archive in two folders, same size and same timestamp, each get their own arrays."""
    stamp = 1_700_000_000 * 10**9
    got = []
    for value, folder in enumerate(("one", "two"), start=1):
        source = tmp_path / folder / "cifar10-x.tar.gz"
        source.parent.mkdir()
        source.write_bytes(folder.encode())  # three bytes each
        os.utime(source, ns=(stamp, stamp))
        got.append(paths.cached_arrays(source, "x", _decode_counting([], value))[0])
    assert got[0].max() == 1 and got[1].max() == 2


def test_a_cache_that_cannot_be_written_costs_a_warning_not_the_result(tmp_path, monkeypatch):
    """A cache folder that cannot be made (a file stands where its parent should be; root
    could write to a read-only folder) warns and still returns the decoded arrays."""
    (tmp_path / "a_file").write_bytes(b"")
    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path / "a_file" / "cache"))
    source = tmp_path / "source"
    source.write_bytes(b"x")
    with pytest.warns(UserWarning, match="could not cache x"):
        images, labels = paths.cached_arrays(source, "x", _decode_counting([], 7))
    assert images.shape == (3, 2) and (images == 7).all() and labels.tolist() == [0, 1, 2]

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


def test_remove_stale_temporaries_leaves_a_link_alone(tmp_path):
    """A link whose name matches is no temporary this code wrote (lstat, never stat): it is
    kept, and so is the hour-old file it points to."""
    target = old_file(tmp_path / "precious.npy")
    link = tmp_path / ".run.pt.abc123.part"
    link.symlink_to(target)
    assert paths.remove_stale_temporaries(tmp_path, [".*.part"]) == []
    assert link.is_symlink() and target.exists()


def test_loads_clean_their_stale_temporaries(tmp_path, tmp_cache):
    write_packed(tmp_path / "data")
    tmp_cache.mkdir()
    stale = old_file(tmp_cache / ".cifar10-test-packed-0123-images.npy.k2j4.part")
    fresh = old_file(tmp_cache / ".cifar10-test-packed-0123-labels.npy.m9x1.part", seconds=0)
    load_cifar10("test", root=tmp_path / "data", download=False)
    assert not stale.exists() and fresh.exists()
