"""Tests that the data loaders lose nothing and trust nothing damaged (issue 26).

A damaged cache file is decoded again; atomic writes reach the disk before
their rename; a local archive with the wrong MD5 is named as such and skipped
for a good copy; temporaries left by a killed run are removed later. All on
small files generated here; the network is replaced by a fake opener.
"""

import gzip
import os
import tarfile
import time
import urllib.error
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from test_data import leftovers, make_official_tarball, write_mnist, write_tree

from ebjepa_tutorial.data import (
    CorruptDataError,
    DataNotFoundError,
    cifar10,
    load_cifar10,
    load_mnist,
    mnist,
    paths,
)
from ebjepa_tutorial.data.moving_mnist import load_moving_mnist_file

HOUR = 3600.0


@pytest.fixture(autouse=True)
def tmp_cache(tmp_path, monkeypatch):
    """Every test gets its own cache; none touches the project's data/cache."""
    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("EBJEPA_DATA", raising=False)
    return tmp_path / "cache"


@pytest.fixture
def offline(monkeypatch):
    """No network: every URL fails to open, as on a machine without internet."""

    def opener(url, timeout=60.0):
        raise urllib.error.URLError("no network")

    monkeypatch.setattr(paths, "_open_url", opener)


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
    write_tree(tmp_path / "data" / "cifar10")
    first, first_labels = load_cifar10("test", root=tmp_path / "data", download=False)
    (cached,) = tmp_cache.glob(f"*-{which}.npy")
    cached.write_bytes(damage(cached.read_bytes()))
    again, again_labels = load_cifar10("test", root=tmp_path / "data", download=False)
    assert torch.equal(first, again) and torch.equal(first_labels, again_labels)
    assert len(np.load(cached)) == len(first)  # rewritten whole
    assert leftovers(tmp_cache) == []


def test_read_cache_of_zero_byte_file_is_none(tmp_cache):
    paths.write_cache("x", np.zeros((2, 3), np.uint8), np.zeros(2, np.int64))
    (tmp_cache / "x-labels.npy").write_bytes(b"")
    assert paths.read_cache("x") is None


@pytest.mark.parametrize("keep", [0, 50, 500], ids=["zero-byte", "cut-header", "cut-data"])
def test_damaged_moving_mnist_file_is_a_clear_error(tmp_path, keep):
    path = tmp_path / "mnist_test_seq.npy"
    np.save(path, np.zeros((2, 3, 64, 64), np.uint8))
    path.write_bytes(path.read_bytes()[:keep])
    with pytest.raises(CorruptDataError, match="damaged or incomplete; delete it"):
        load_moving_mnist_file(path)


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
    paths.write_cache("x", np.zeros((2, 3), np.uint8), np.zeros(2, np.int64))
    served = tmp_path / "served.bin"
    served.write_bytes(b"some bytes")
    paths.download([served.as_uri()], tmp_path / "got.bin", paths.md5sum(served))
    assert events == [
        "fsync", "replace x-images.npy", "fsync", "replace x-labels.npy",
        "fsync", "replace got.bin",
    ]  # fmt: skip


# --- (c) a local archive with the wrong MD5 ---------------------------------------------------


def cifar_with_bad_official(tmp_path, monkeypatch, packed: bool):
    """data/ with an official archive whose MD5 is not the expected one, and maybe a good
    packed tree beside it; returns (data folder, bad archive, images of the packed tree)."""
    good = tmp_path / "good" / cifar10.TARBALL
    good.parent.mkdir()
    make_official_tarball(good, n=3)
    monkeypatch.setattr(cifar10, "CIFAR10_MD5", paths.md5sum(good))
    data = tmp_path / "data"
    data.mkdir()
    make_official_tarball(data / cifar10.TARBALL, n=2)  # readable, but not the official bytes
    expected = None
    if packed:
        expected = write_tree(tmp_path / "src")
        with tarfile.open(data / "cifar10-jpeg.tar.gz", "w:gz") as archive:
            archive.add(tmp_path / "src" / "test", arcname="test")
    return data, data / cifar10.TARBALL, expected


def test_cifar_wrong_md5_offline_falls_back_to_a_good_copy(tmp_path, monkeypatch, offline):
    data, bad, expected = cifar_with_bad_official(tmp_path, monkeypatch, packed=True)
    with pytest.warns(UserWarning, match="wrong MD5") as record:
        images, _ = load_cifar10("test", root=data, download=False)
    message = str(record[0].message)
    assert str(bad) in message and "Delete it" in message and "cifar10-jpeg.tar.gz" in message
    assert np.array_equal(images.numpy(), expected)
    assert bad.is_file()  # download=False: the data folder is left as it is

    with pytest.warns(UserWarning, match="renamed to"):  # download allowed, but offline
        images, _ = load_cifar10("test", root=data)
    assert np.array_equal(images.numpy(), expected)
    assert not bad.exists() and bad.with_name(bad.name + ".bad").is_file()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the next run reads the good copy silently
        assert torch.equal(load_cifar10("test", root=data)[0], images)


def test_cifar_wrong_md5_offline_without_other_copy_says_so(tmp_path, monkeypatch, offline):
    data, bad, _ = cifar_with_bad_official(tmp_path, monkeypatch, packed=False)
    with pytest.raises(CorruptDataError) as info:
        load_cifar10("test", root=data, download=False)
    message = str(info.value)
    assert f"{bad} has the wrong MD5" in message and "Delete it" in message
    assert bad.is_file()

    with pytest.raises(CorruptDataError) as info:  # not "not found": the file is there
        load_cifar10("test", root=data)
    message = str(info.value)
    assert f"{bad} has the wrong MD5" in message and "no network" in message
    assert f"renamed to {bad}.bad" in message and "delete that file" in message
    with pytest.raises(DataNotFoundError, match=r"\.tar\.gz\.bad is a damaged copy"):
        load_cifar10("test", root=data, download=False)


def test_cifar_wrong_md5_is_replaced_by_a_download_when_online(tmp_path, monkeypatch):
    data, bad, _ = cifar_with_bad_official(tmp_path, monkeypatch, packed=True)
    monkeypatch.setattr(cifar10, "CIFAR10_URL", (tmp_path / "good" / cifar10.TARBALL).as_uri())
    images, _ = load_cifar10("test", root=data)
    assert images.shape == (3, 3, 32, 32)  # the official archive, not the packed tree
    assert paths.md5sum(bad) == cifar10.CIFAR10_MD5 and leftovers(data) == []


def mnist_with_bad_images(tmp_path, monkeypatch, good_copy: str):
    """mnist/ whose test images .gz has the wrong MD5, and a good copy elsewhere:
    uncompressed beside it (``"raw"``) or in MNIST/raw/ (``"torchvision"``)."""
    data = tmp_path / "data"
    folder = data / "mnist"
    images, _ = write_mnist(folder)
    monkeypatch.setattr(mnist, "MNIST_MD5", {p.name: paths.md5sum(p) for p in folder.iterdir()})
    bad = folder / f"{mnist.MNIST_FILES['test'][0]}.gz"
    bad.write_bytes(gzip.compress(b"\x00\x00\x08\x01\x00\x00\x00\x00", mtime=0))
    if good_copy == "raw":  # the same seed: the same digits
        write_mnist(folder, compress=False)
    elif good_copy == "torchvision":
        write_mnist(data / "MNIST" / "raw")
    return data, bad, images


@pytest.mark.parametrize("good_copy", ["raw", "torchvision"])
def test_mnist_wrong_md5_falls_back_to_a_good_copy(tmp_path, monkeypatch, offline, good_copy):
    data, bad, expected = mnist_with_bad_images(tmp_path, monkeypatch, good_copy)
    with pytest.warns(UserWarning, match="wrong MD5") as record:
        images, _ = load_mnist("test", root=data, download=False)
    assert str(bad) in str(record[0].message) and "Delete it" in str(record[0].message)
    assert np.array_equal(images[:, 0].numpy(), expected) and bad.is_file()

    with pytest.warns(UserWarning, match="renamed to"):  # download allowed, but offline
        images, _ = load_mnist("test", root=data)
    assert np.array_equal(images[:, 0].numpy(), expected)
    assert bad.with_name(bad.name + ".bad").is_file() and not bad.exists()


def test_mnist_wrong_md5_offline_without_other_copy_says_so(tmp_path, monkeypatch, offline):
    data, bad, _ = mnist_with_bad_images(tmp_path, monkeypatch, good_copy="none")
    with pytest.raises(CorruptDataError) as info:
        load_mnist("test", root=data)
    message = str(info.value)
    assert f"{bad} has the wrong MD5" in message and f"renamed to {bad}.bad" in message
    with pytest.raises(DataNotFoundError, match=r"idx3-ubyte\.gz\.bad"):
        load_mnist("test", root=data, download=False)


# --- (d) temporaries left by a killed run -----------------------------------------------------


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


def test_loads_and_downloads_clean_their_stale_temporaries(tmp_path, tmp_cache):
    write_tree(tmp_path / "data" / "cifar10")
    tmp_cache.mkdir()
    stale = old_file(tmp_cache / ".cifar10-test-tree-0123-images.npy.k2j4.part")
    fresh = old_file(tmp_cache / ".cifar10-test-tree-0123-labels.npy.m9x1.part", seconds=0)
    load_cifar10("test", root=tmp_path / "data", download=False)
    assert not stale.exists() and fresh.exists()

    served = tmp_path / "served.bin"
    served.write_bytes(b"data")
    (tmp_path / "out").mkdir()
    old_download = old_file(tmp_path / "out" / ".got.bin.zz81.part")
    paths.download([served.as_uri()], tmp_path / "out" / "got.bin", paths.md5sum(served))
    assert sorted(p.name for p in old_download.parent.iterdir()) == ["got.bin"]
