"""Tests of ebjepa_tutorial.data: real loads from the shared copies, and every
download / corruption / missing-data path on small files generated here.

All caches go to tmp folders (EBJEPA_CACHE); downloads are served from
``file://`` URLs or a fake opener, since these machines have no internet.
"""

import email.message
import gzip
import io
import os
import pickle
import tarfile
import time
import urllib.error
import urllib.request
import urllib.response
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from ebjepa_tutorial.data import (
    CIFAR10_CLASSES,
    CorruptDataError,
    DataNotFoundError,
    cache_dir,
    cifar10,
    data_dir,
    load_cifar10,
    load_mnist,
    mnist,
    paths,
    to_float,
)

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = os.environ.get("EBJEPA_DATA")  # read before the fixture below clears it


@pytest.fixture(autouse=True)
def tmp_cache(tmp_path, monkeypatch):
    """Every test gets its own cache; none touches the project's data/cache."""
    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("EBJEPA_DATA", raising=False)
    return tmp_path / "cache"


def leftovers(folder: Path) -> list[str]:
    """Temp files a download or cache write might have left behind."""
    return [p.name for p in folder.rglob("*") if p.name.endswith(".part")]


# --- the real data (../shared/data), when this machine has it -------------------------------


def shared_data() -> Path:
    for candidate in (SHARED_DATA, REPO.parent / "shared" / "data"):
        if candidate and (Path(candidate) / "cifar10-jpeg.tar.gz").is_file():
            return Path(candidate)
    pytest.skip("no shared data (set EBJEPA_DATA or provide ../shared/data)")


@pytest.fixture(scope="module")
def real_loads(tmp_path_factory):
    """Load CIFAR-10 test and MNIST test twice each from the shared copies; time the 2nd load."""
    root = shared_data()
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("EBJEPA_CACHE", str(tmp_path_factory.mktemp("real_cache")))
        results = {}
        for name, load in (("cifar", load_cifar10), ("mnist", load_mnist)):
            first = load("test", root=root, download=False)
            start = time.perf_counter()
            second = load("test", root=root, download=False)
            results[name] = (first, second, time.perf_counter() - start)
    return results


@pytest.mark.slow  # decodes the real files: seconds
def test_real_cifar10_test_split(real_loads):
    (images, labels), (again, again_labels), seconds = real_loads["cifar"]
    assert images.shape == (10_000, 3, 32, 32) and images.dtype == torch.uint8
    assert labels.shape == (10_000,) and labels.dtype == torch.int64
    assert labels.bincount().tolist() == [1_000] * 10
    # Published per-channel means of the CIFAR-10 test set: 0.494, 0.485, 0.450 (x 255).
    means = images.float().mean(dim=(0, 2, 3))
    assert torch.allclose(means, torch.tensor([126.0, 123.7, 114.9]), atol=2.0)
    assert 55 < images.float().std() < 70
    assert torch.equal(images, again) and torch.equal(labels, again_labels)
    assert seconds < 1.0


@pytest.mark.slow
def test_real_mnist_test_split(real_loads):
    (images, labels), (again, _), seconds = real_loads["mnist"]
    assert images.shape == (10_000, 1, 28, 28) and images.dtype == torch.uint8
    # The MNIST test set's digit counts, 0 to 9.
    expected = [980, 1135, 1032, 1010, 982, 892, 958, 1028, 974, 1009]
    assert labels.bincount().tolist() == expected
    assert 30 < images.float().mean() < 37  # mostly black background
    assert torch.equal(images, again) and seconds < 1.0


def test_real_mnist_train_missing_names_what_is_there():
    root = shared_data()
    if (root / "mnist" / "train-images-idx3-ubyte.gz").exists():
        pytest.skip("this copy has the train split")
    with pytest.raises(DataNotFoundError, match="Only the test split is there"):
        load_mnist("train", root=root, download=False)


# --- fake official CIFAR-10 archive ---------------------------------------------------------


def fake_batch(n: int, seed: int) -> dict:
    """A batch in the official layout: bytes keys, data (n, 3072) uint8, labels a list."""
    rng = np.random.default_rng(seed)
    data = rng.integers(0, 256, size=(n, 3072), dtype=np.uint8)
    labels = [int(v) for v in rng.integers(0, 10, size=n)]
    return {b"batch_label": b"fake", b"labels": labels, b"data": data, b"filenames": [b"x"] * n}


def make_official_tarball(path: Path, n: int = 3) -> dict:
    """Write a small cifar-10-python.tar.gz (n images per batch); return the batches."""
    batches = {f"data_batch_{i}": fake_batch(n, i) for i in range(1, 6)}
    batches["test_batch"] = fake_batch(n, 99)
    with tarfile.open(path, "w:gz") as archive:
        for name, batch in batches.items():
            raw = pickle.dumps(batch, protocol=2)
            info = tarfile.TarInfo(f"cifar-10-batches-py/{name}")
            info.size = len(raw)
            archive.addfile(info, io.BytesIO(raw))
    return batches


@pytest.fixture
def server(tmp_path, monkeypatch):
    """A fake official tarball served from a file:// URL with its MD5 set as the official one."""
    served = tmp_path / "server" / cifar10.TARBALL
    served.parent.mkdir()
    batches = make_official_tarball(served)
    monkeypatch.setattr(cifar10, "CIFAR10_URL", served.as_uri())
    monkeypatch.setattr(cifar10, "CIFAR10_MD5", paths.md5sum(served))
    return served, batches


def short_response(data: bytes, announced: int) -> urllib.response.addinfourl:
    """A server reply that announces ``announced`` bytes but sends only ``data``."""
    headers = email.message.Message()
    headers["Content-Length"] = str(announced)
    return urllib.response.addinfourl(io.BytesIO(data), headers, "https://example.org/x")


def count_opens(monkeypatch, serve=None) -> list:
    """Replace the URL opener; ``serve(call_number, url)`` may return another URL or a reply."""
    calls = []

    def opener(url, timeout=60.0):
        calls.append(url)
        target = serve(len(calls), url) if serve else url
        return urllib.request.urlopen(target) if isinstance(target, str) else target

    monkeypatch.setattr(paths, "_open_url", opener)
    return calls


def test_download_official_archive_and_read_pixel_layout(tmp_path, server):
    _, batches = server
    images, labels = load_cifar10("test", root=tmp_path / "data")
    data = batches["test_batch"][b"data"]
    assert images.shape == (3, 3, 32, 32) and images.dtype == torch.uint8
    # Row layout: 1024 red values, then green, then blue, each plane row by row.
    assert images[1, 2, 5, 7] == data[1, 2 * 1024 + 5 * 32 + 7]
    assert labels.tolist() == batches["test_batch"][b"labels"] and labels.dtype == torch.int64
    assert (tmp_path / "data" / cifar10.TARBALL).is_file()
    assert leftovers(tmp_path) == []
    train, _ = load_cifar10("train", root=tmp_path / "data", download=False)
    assert train.shape == (15, 3, 32, 32)


def test_extracted_batches_folder_is_read(tmp_path, server):
    _, batches = server
    folder = tmp_path / "data" / cifar10.BATCHES_DIR
    folder.mkdir(parents=True)
    for name, batch in batches.items():
        (folder / name).write_bytes(pickle.dumps(batch, protocol=2))
    images, labels = load_cifar10("test", root=tmp_path / "data", download=False)
    assert images.flatten(1).numpy().tolist() == batches["test_batch"][b"data"].tolist()


def test_wrong_md5_retries_once_then_fails_and_keeps_nothing(tmp_path, server, monkeypatch):
    monkeypatch.setattr(cifar10, "CIFAR10_MD5", "0" * 32)
    calls = count_opens(monkeypatch)
    with pytest.raises(CorruptDataError, match="MD5"):
        load_cifar10("test", root=tmp_path / "data")
    assert len(calls) == 2
    assert list((tmp_path / "data").iterdir()) == []


def test_truncated_download_is_retried_and_then_succeeds(tmp_path, server, monkeypatch):
    served, _ = server
    truncated = tmp_path / "truncated.tar.gz"
    truncated.write_bytes(served.read_bytes()[:500])
    calls = count_opens(monkeypatch, lambda n, url: truncated.as_uri() if n == 1 else url)
    images, _ = load_cifar10("test", root=tmp_path / "data")
    assert len(calls) == 2 and images.shape == (3, 3, 32, 32)
    assert leftovers(tmp_path) == []


def test_truncated_download_every_time_is_a_clear_error(tmp_path, server, monkeypatch):
    served, _ = server
    full = served.read_bytes()
    count_opens(monkeypatch, lambda n, url: short_response(full[:500], len(full)))
    with pytest.raises(CorruptDataError, match=f"500 of {len(full):,} bytes"):
        load_cifar10("test", root=tmp_path / "data")
    assert list((tmp_path / "data").iterdir()) == []


def test_damaged_archive_on_disk(tmp_path, server, monkeypatch):
    served, _ = server
    local = tmp_path / "data" / cifar10.TARBALL
    local.parent.mkdir()
    local.write_bytes(served.read_bytes()[:500])
    with pytest.raises(CorruptDataError, match="wrong MD5"):
        load_cifar10("test", root=tmp_path / "data", download=False)
    images, _ = load_cifar10("test", root=tmp_path / "data")  # download=True replaces it
    assert images.shape == (3, 3, 32, 32) and paths.md5sum(local) == paths.md5sum(served)


def test_missing_data_without_network(tmp_path, monkeypatch):
    empty = tmp_path / "data"
    with pytest.raises(DataNotFoundError) as info:
        load_cifar10("train", root=empty, download=False)
    message = str(info.value)
    for needle in (str(empty), cifar10.TARBALL, cifar10.CIFAR10_URL, "EBJEPA_DATA"):
        assert needle in message
    assert isinstance(info.value, FileNotFoundError)

    def offline(url, timeout=60.0):
        raise urllib.error.URLError("no network")

    monkeypatch.setattr(paths, "_open_url", offline)
    with pytest.raises(DataNotFoundError, match="download failed"):
        load_cifar10("train", root=empty)
    assert not empty.exists()  # no folder, no temp file


def python2_batch(pixels: bytes, labels: list[int]) -> bytes:
    """A batch pickled the way the official files were (Python 2, protocol 2), opcode by opcode:
    str as BINSTRING, arrays as numpy.core.multiarray._reconstruct of an ndarray and a dtype."""

    def string(b: bytes) -> bytes:
        return b"T" + len(b).to_bytes(4, "little") + b

    dtype = b"cnumpy\ndtype\n" + string(b"u1") + b"K\x00K\x01\x87R"
    dtype += b"(K\x03" + string(b"|") + b"NNNJ\xff\xff\xff\xffJ\xff\xff\xff\xffK\x00tb"
    array = b"cnumpy.core.multiarray\n_reconstruct\ncnumpy\nndarray\nK\x00\x85" + string(b"b")
    shape = b"M" + (len(pixels) // 3072).to_bytes(2, "little") + b"M\x00\x0c\x86"  # (n, 3072)
    array += b"\x87R(K\x01" + shape + dtype + b"\x89" + string(pixels) + b"tb"
    label_list = b"](" + b"".join(b"K" + bytes([v]) for v in labels) + b"e"
    return b"\x80\x02}(" + string(b"data") + array + string(b"labels") + label_list + b"u."


def test_python2_pickled_batch_is_read(tmp_path):
    pixels = np.arange(2 * 3072, dtype=np.uint32).astype(np.uint8)
    folder = tmp_path / "data" / cifar10.BATCHES_DIR
    folder.mkdir(parents=True)
    (folder / "test_batch").write_bytes(python2_batch(pixels.tobytes(), [4, 9]))
    images, labels = load_cifar10("test", root=tmp_path / "data", download=False)
    assert np.array_equal(images.numpy(), pixels.reshape(2, 3, 32, 32))
    assert labels.tolist() == [4, 9]


def test_foreign_pickle_is_refused(tmp_path):
    folder = tmp_path / "data" / cifar10.BATCHES_DIR
    folder.mkdir(parents=True)
    (folder / "test_batch").write_bytes(pickle.dumps({b"data": Path("x")}, protocol=2))
    with pytest.raises(CorruptDataError, match="unexpected object"):
        load_cifar10("test", root=tmp_path / "data", download=False)


# --- class folders: a tree, or a packed tree ------------------------------------------------


def write_tree(root: Path, split: str = "test", per_class: int = 2) -> np.ndarray:
    """PNG images (lossless) in root/split/<class>/; returns the expected (N, 3, 32, 32) array."""
    expected = []
    for label, name in enumerate(CIFAR10_CLASSES):
        (root / split / name).mkdir(parents=True)
        for i in range(per_class):
            pixels = np.full((32, 32, 3), (label * 20, i * 50, 7), dtype=np.uint8)
            pixels[0, 0] = (255, 0, label)
            Image.fromarray(pixels).save(root / split / name / f"{i:04d}.png")
            expected.append(pixels.transpose(2, 0, 1))
    (root / split / "airplane" / "notes.txt").write_text("not an image")
    return np.stack(expected)


def test_class_folder_tree(tmp_path):
    expected = write_tree(tmp_path / "data" / "cifar10")
    images, labels = load_cifar10("test", root=tmp_path / "data", download=False)
    assert np.array_equal(images.numpy(), expected)
    assert labels.tolist() == [c for c in range(10) for _ in range(2)]


def test_packed_tree_with_top_folder(tmp_path):
    expected = write_tree(tmp_path / "src" / "mine")
    (tmp_path / "data").mkdir()
    with tarfile.open(tmp_path / "data" / "cifar10-mine.tar.gz", "w:gz") as archive:
        archive.add(tmp_path / "src" / "mine", arcname="mine")
    images, labels = load_cifar10("test", root=tmp_path / "data", download=False)
    assert np.array_equal(images.numpy(), expected) and labels[-1] == 9
    with pytest.raises(DataNotFoundError, match="airplane"):  # no train/ inside
        load_cifar10("train", root=tmp_path / "data", download=False)


def test_truncated_packed_tree_is_a_clear_error(tmp_path):
    write_tree(tmp_path / "src")
    packed = tmp_path / "data" / "cifar10-jpeg.tar.gz"
    packed.parent.mkdir()
    with tarfile.open(packed, "w:gz") as archive:
        archive.add(tmp_path / "src" / "test", arcname="test")
    packed.write_bytes(packed.read_bytes()[:-300])
    with pytest.raises(CorruptDataError, match="cifar10-jpeg.tar.gz"):
        load_cifar10("test", root=tmp_path / "data", download=False)


def test_tree_other_sizes_missing_class_and_cache_invalidation(tmp_path):
    root = tmp_path / "data" / "cifar10"
    write_tree(root)
    Image.new("L", (64, 48), 200).save(root / "test" / "cat" / "big.png")
    images, labels = load_cifar10("test", root=tmp_path / "data")
    assert images.shape == (21, 3, 32, 32) and (images[labels == 3][-1] == 200).all()
    (root / "test" / "cat" / "big.png").unlink()  # an edited tree is not served from cache
    assert len(load_cifar10("test", root=tmp_path / "data")[0]) == 20
    for f in (root / "test" / "dog").iterdir():
        f.unlink()
    with pytest.raises(DataNotFoundError, match="dog"):
        load_cifar10("test", root=tmp_path / "data", download=False)


# --- MNIST IDX files ------------------------------------------------------------------------


def idx_bytes(array: np.ndarray) -> bytes:
    """The IDX encoding of a uint8 array: magic 0 0 8 ndim, big-endian sizes, values."""
    header = bytes([0, 0, 8, array.ndim]) + b"".join(d.to_bytes(4, "big") for d in array.shape)
    return header + array.astype(np.uint8).tobytes()


def write_mnist(folder: Path, split: str = "test", n: int = 5, compress: bool = True):
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, size=(n, 28, 28), dtype=np.uint8)
    labels = rng.integers(0, 10, size=n, dtype=np.uint8)
    for stem, array in zip(mnist.MNIST_FILES[split], (images, labels), strict=True):
        raw = idx_bytes(array)
        path = folder / (f"{stem}.gz" if compress else stem)
        path.write_bytes(gzip.compress(raw, mtime=0) if compress else raw)
    return images, labels


@pytest.mark.parametrize("compress", [True, False])
def test_mnist_from_folder(tmp_path, monkeypatch, compress):
    monkeypatch.setattr(mnist, "MNIST_MD5", {})  # our own files, not the official ones
    images, labels = write_mnist(tmp_path / "data" / "mnist", compress=compress)
    got, got_labels = load_mnist("test", root=tmp_path / "data", download=False)
    assert got.shape == (5, 1, 28, 28) and got.dtype == torch.uint8
    assert np.array_equal(got[:, 0].numpy(), images)
    assert got_labels.tolist() == labels.tolist() and got_labels.dtype == torch.int64


def test_mnist_download_from_mirror_with_md5(tmp_path, monkeypatch):
    server = tmp_path / "server"
    images, _ = write_mnist(server, split="train")
    md5s = {p.name: paths.md5sum(p) for p in server.iterdir()}
    monkeypatch.setattr(mnist, "MNIST_MD5", md5s)
    broken = "file:///nonexistent/mirror/"  # the first mirror is down: the second one serves
    monkeypatch.setattr(mnist, "MNIST_MIRRORS", (broken, server.as_uri() + "/"))
    got, _ = load_mnist("train", root=tmp_path / "data")
    assert np.array_equal(got[:, 0].numpy(), images)
    assert sorted(p.name for p in (tmp_path / "data" / "mnist").iterdir()) == sorted(md5s)


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda raw: raw[:-10], "truncated"),
        (lambda raw: b"\x08\x08" + raw[2:], "magic"),
    ],
)
def test_mnist_damaged_files(tmp_path, monkeypatch, damage, message):
    monkeypatch.setattr(mnist, "MNIST_MD5", {})
    folder = tmp_path / "data" / "mnist"
    write_mnist(folder, compress=False)
    path = folder / mnist.MNIST_FILES["test"][0]
    path.write_bytes(damage(path.read_bytes()))
    with pytest.raises(CorruptDataError, match=message):
        load_mnist("test", root=tmp_path / "data", download=False)


def test_mnist_truncated_gzip_and_wrong_md5(tmp_path):
    folder = tmp_path / "data" / "mnist"
    write_mnist(folder)
    gz = folder / f"{mnist.MNIST_FILES['test'][0]}.gz"
    gz.write_bytes(gz.read_bytes()[:-20])
    with pytest.raises(CorruptDataError, match="wrong MD5"):  # official names: MD5 first
        load_mnist("test", root=tmp_path / "data", download=False)
    with pytest.raises(CorruptDataError, match="EOFError|truncated|gzip"):
        mnist.read_idx(gz)


def test_mnist_missing_split_message(tmp_path):
    write_mnist(tmp_path / "data" / "mnist", split="test")
    with pytest.raises(DataNotFoundError) as info:
        load_mnist("train", root=tmp_path / "data", download=False)
    message = str(info.value)
    assert "train-images-idx3-ubyte.gz" in message and mnist.MNIST_MIRRORS[0] in message
    assert "Only the test split is there" in message


# --- paths, splits, cache, helpers ----------------------------------------------------------


def test_bad_split_names_the_choices(tmp_path):
    with pytest.raises(ValueError, match="'train', 'test'"):
        load_cifar10("validation", root=tmp_path)
    with pytest.raises(ValueError, match="'train', 'test'"):
        load_mnist("val", root=tmp_path)


def test_data_and_cache_dir_resolution(tmp_path, monkeypatch, tmp_cache):
    assert data_dir() == REPO / "data"
    monkeypatch.setenv("EBJEPA_DATA", str(tmp_path / "elsewhere"))
    assert data_dir() == tmp_path / "elsewhere"
    assert data_dir(tmp_path / "explicit") == tmp_path / "explicit"
    assert cache_dir() == tmp_cache
    monkeypatch.delenv("EBJEPA_CACHE")
    assert cache_dir() == REPO / "data" / "cache"


def test_cache_is_reused_and_survives_a_damaged_file(tmp_path, tmp_cache):
    write_tree(tmp_path / "data" / "cifar10")
    first, _ = load_cifar10("test", root=tmp_path / "data")
    cached = sorted(tmp_cache.iterdir())
    assert [p.name.endswith(("-images.npy", "-labels.npy")) for p in cached] == [True, True]
    cached[0].write_bytes(b"garbage")  # a damaged cache is rebuilt, not trusted
    again, _ = load_cifar10("test", root=tmp_path / "data")
    assert torch.equal(first, again) and leftovers(tmp_cache) == []


def test_to_float():
    images = torch.tensor([[[[0, 51, 255]]]], dtype=torch.uint8)
    out = to_float(images)
    assert out.dtype == torch.float32 and out.shape == images.shape
    assert torch.allclose(out, torch.tensor([[[[0.0, 0.2, 1.0]]]]))
    with pytest.raises(TypeError, match="uint8"):
        to_float(out)


def test_random_subset_mixes_classes_and_keeps_everything_when_asked():
    from ebjepa_tutorial.data import random_subset

    labels = torch.arange(10).repeat_interleave(100)  # stored class by class
    images = torch.arange(1000)
    some, some_labels = random_subset(images, labels, 50, seed=0)
    assert len(some) == 50 and len(some_labels.unique()) >= 8
    assert torch.equal(labels[some], some_labels)
    assert torch.equal(random_subset(images, labels, 50, seed=0)[0], some)
    assert random_subset(images, labels, 5000)[0] is images
