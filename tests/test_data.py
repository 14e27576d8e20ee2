"""Tests of ebjepa_tutorial.data: real loads from the shared copies, and every
download, corruption and missing-data path on small files generated here.

All caches go to tmp folders (EBJEPA_CACHE); torchvision's downloads are served
from ``file://`` URLs, since these machines have no internet.
"""

import functools
import gzip
import hashlib
import http.server
import io
import os
import pickle
import tarfile
import tempfile
import threading
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
)
from ebjepa_tutorial.data.cifar10 import find_cifar10
from ebjepa_tutorial.data.mnist import find_mnist

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = os.environ.get("EBJEPA_DATA")  # read before the fixture below clears it


@pytest.fixture
def datasets():
    """``torchvision.datasets``, imported by the tests that patch it: importing torchvision takes
    over a second, which every pytest worker would otherwise pay while collecting this file."""
    from torchvision import datasets

    return datasets


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


def shared_data(holds=lambda folder: (folder / "cifar10-jpeg.tar.gz").is_file(),
                what: str = "the CIFAR-10 copy cifar10-jpeg.tar.gz") -> Path:
    """EBJEPA_DATA, else the development copy beside the repository (../shared/data),
    whichever ``holds(folder)`` the files ``what`` names; the test is skipped if neither does.
    Other test files call it too."""
    for candidate in (SHARED_DATA, REPO.parent / "shared" / "data"):
        if candidate and holds(Path(candidate)):
            return Path(candidate)
    pytest.skip(f"{what} is not on this machine: set EBJEPA_DATA to a folder holding it "
                "(or provide ../shared/data)")


@pytest.fixture(scope="module")
def real_loads(tmp_path_factory):
    """Load CIFAR-10 test and MNIST test twice each from the shared copies; count the images
    the second load of CIFAR-10 decoded (its cache should make that none)."""
    root = shared_data()
    decoded = []
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("EBJEPA_CACHE", str(tmp_path_factory.mktemp("real_cache")))
        read = cifar10._read_packed
        mp.setattr(cifar10, "_read_packed", lambda *a: decoded.append(a) or read(*a))
        results = {}
        for name, load in (("cifar", load_cifar10), ("mnist", load_mnist)):
            first = load("test", root=root, download=False)
            before = len(decoded)
            second = load("test", root=root, download=False)
            results[name] = (first, second, len(decoded) - before)
    return results


@pytest.mark.slow  # decodes the real files: seconds
def test_real_cifar10_test_split(real_loads):
    (images, labels), (again, again_labels), decoded_again = real_loads["cifar"]
    assert images.shape == (10_000, 3, 32, 32) and images.dtype == torch.uint8
    assert labels.shape == (10_000,) and labels.dtype == torch.int64
    assert labels.bincount().tolist() == [1_000] * 10
    # Published per-channel means of the CIFAR-10 test set: 0.494, 0.485, 0.450 (x 255).
    means = images.float().mean(dim=(0, 2, 3))
    assert torch.allclose(means, torch.tensor([126.0, 123.7, 114.9]), atol=2.0)
    assert 55 < images.float().std() < 70
    assert torch.equal(images, again) and torch.equal(labels, again_labels)
    assert decoded_again == 0  # the second load read the cached arrays


@pytest.mark.slow
def test_real_mnist_test_split(real_loads):
    (images, labels), (again, _), _ = real_loads["mnist"]
    assert images.shape == (10_000, 1, 28, 28) and images.dtype == torch.uint8
    # The MNIST test set's digit counts, 0 to 9.
    expected = [980, 1135, 1032, 1010, 982, 892, 958, 1028, 974, 1009]
    assert labels.bincount().tolist() == expected
    assert 30 < images.float().mean() < 37  # mostly black background
    assert torch.equal(images, again)


# --- the official archive, downloaded by torchvision from a local HTTP server ---------------


class QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


@pytest.fixture
def served(tmp_path):
    """(folder, url): a local HTTP server for the files put in ``folder``."""
    folder = tmp_path / "server"
    folder.mkdir()
    handler = functools.partial(QuietHandler, directory=str(folder))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)  # a free port
    # poll often: shutdown() waits up to one poll interval (0.5 s by default) per test
    threading.Thread(target=server.serve_forever, args=(0.01,), daemon=True).start()
    yield folder, f"http://127.0.0.1:{server.server_port}/"
    server.shutdown()
    server.server_close()


def fake_batch(n: int, seed: int) -> dict:
    """A batch in the official layout: data (n, 3072) uint8, labels a list."""
    rng = np.random.default_rng(seed)
    data = rng.integers(0, 256, size=(n, 3072), dtype=np.uint8)
    labels = [int(v) for v in rng.integers(0, 10, size=n)]
    return {"batch_label": "fake", "labels": labels, "data": data, "filenames": ["x"] * n}


def md5(raw: bytes) -> str:
    return hashlib.md5(raw).hexdigest()


@pytest.fixture
def official(served, monkeypatch, datasets):
    """A small cifar-10-python.tar.gz on the local server, its MD5s set as torchvision's.

    Returns the batches by name. torchvision checks the archive and every file in it.
    """
    batches = {f"data_batch_{i}": fake_batch(3, i) for i in range(1, 6)}
    batches["test_batch"] = fake_batch(3, 99)
    raws = {name: pickle.dumps(batch, protocol=2) for name, batch in batches.items()}
    raws["batches.meta"] = pickle.dumps({"label_names": list(CIFAR10_CLASSES)}, protocol=2)
    folder, url = served
    archive_path = folder / datasets.CIFAR10.filename
    with tarfile.open(archive_path, "w:gz") as archive:
        for name, raw in raws.items():
            info = tarfile.TarInfo(f"cifar-10-batches-py/{name}")
            info.size = len(raw)
            archive.addfile(info, io.BytesIO(raw))
    monkeypatch.setattr(datasets.CIFAR10, "url", url + archive_path.name)
    monkeypatch.setattr(datasets.CIFAR10, "tgz_md5", md5(archive_path.read_bytes()))
    monkeypatch.setattr(datasets.CIFAR10, "train_list",
                        [[f"data_batch_{i}", md5(raws[f"data_batch_{i}"])] for i in range(1, 6)])
    monkeypatch.setattr(datasets.CIFAR10, "test_list", [["test_batch", md5(raws["test_batch"])]])
    monkeypatch.setattr(datasets.CIFAR10, "meta", {"filename": "batches.meta", "key": "label_names",
                                                   "md5": md5(raws["batches.meta"])})
    return batches


def test_download_official_archive_and_read_pixel_layout(tmp_path, official):
    images, labels = load_cifar10("train", root=tmp_path / "data")
    assert images.shape == (15, 3, 32, 32) and images.dtype == torch.uint8
    assert labels.dtype == torch.int64
    # Each row of the official batch holds the red, then green, then blue 32x32 plane.
    first = official["data_batch_1"]["data"][0]
    assert np.array_equal(images[0, 1].numpy(), first[1024:2048].reshape(32, 32))
    assert labels[:3].tolist() == official["data_batch_1"]["labels"]
    assert find_cifar10(tmp_path / "data") == tmp_path / "data" / "cifar-10-batches-py"
    test, _ = load_cifar10("test", root=tmp_path / "data", download=False)  # from disk now
    assert len(test) == 3


def test_a_foreign_or_damaged_batch_is_refused_before_it_is_unpickled(tmp_path, official):
    load_cifar10("test", root=tmp_path / "data")
    batch = tmp_path / "data" / "cifar-10-batches-py" / "test_batch"
    batch.write_bytes(pickle.dumps(Exploit()))
    with pytest.raises(CorruptDataError, match=r"damaged or incomplete \(its checksum fails\); "
                                               "delete the folder") as refused:
        load_cifar10("test", root=tmp_path / "data", download=False)
    assert "download=True" not in str(refused.value)  # torchvision's advice does not apply
    assert not (tmp_path / "pwned").exists()


class Exploit:
    """A pickle that would run code if it were loaded."""

    def __reduce__(self):
        return (os.system, ("touch pwned",))


def test_missing_data_without_network(tmp_path, served, monkeypatch, datasets):
    data = tmp_path / "data"
    with pytest.raises(DataNotFoundError) as raised:
        load_cifar10("test", root=data, download=False)
    message = str(raised.value)
    assert "cifar-10-batches-py" in message and "EBJEPA_DATA" in message
    assert "download=True" in message and not data.exists()  # nothing fetched, nothing made
    monkeypatch.setattr(datasets.CIFAR10, "url", served[1] + "nowhere.tar.gz")  # HTTP 404
    with pytest.raises(DataNotFoundError, match="The download failed"):
        load_cifar10("test", root=data)


# --- class folders, packed as cifar10*.tar.gz -------------------------------------------------


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


def pack(tree: Path, data: Path, top: str = "") -> Path:
    """``tree``'s split folders packed as data/cifar10-mine.tar.gz, under ``top/`` if given."""
    data.mkdir(parents=True, exist_ok=True)
    with tarfile.open(data / "cifar10-mine.tar.gz", "w:gz") as archive:
        for split in sorted(tree.iterdir()):
            archive.add(split, arcname=f"{top}/{split.name}" if top else split.name)
    return data / "cifar10-mine.tar.gz"


def write_packed(data: Path, split: str = "test") -> np.ndarray:
    """write_tree, packed into ``data``; returns the expected array."""
    expected = write_tree(data.parent / "tree", split)
    pack(data.parent / "tree", data)
    return expected


def test_packed_tree(tmp_path):
    expected = write_packed(tmp_path / "data")
    images, labels = load_cifar10("test", root=tmp_path / "data", download=False)
    assert np.array_equal(images.numpy(), expected)
    assert labels.tolist() == [c for c in range(10) for _ in range(2)]
    assert find_cifar10(tmp_path / "data") == tmp_path / "data" / "cifar10-mine.tar.gz"


def test_find_cifar10_prefers_the_official_folder_then_the_first_archive_by_name(tmp_path):
    """The order the docstring and the missing-data message promise: the extracted official
    release over any packed copy, and of several packed copies the first by name (a choice
    that does not hang on the order the file system lists them in)."""
    assert find_cifar10(tmp_path) is None
    for name in ("cifar10-b.tar.gz", "cifar10-a.tar.gz"):
        (tmp_path / name).write_bytes(b"")
    assert find_cifar10(tmp_path) == tmp_path / "cifar10-a.tar.gz"
    (tmp_path / "cifar-10-batches-py").mkdir()
    assert find_cifar10(tmp_path) == tmp_path / "cifar-10-batches-py"


@pytest.mark.parametrize("top", ["mine", "./mine"])  # `tar czf x.tar.gz ./mine` writes "./"
def test_packed_tree_with_top_folder(tmp_path, top):
    expected = write_tree(tmp_path / "src")
    pack(tmp_path / "src", tmp_path / "data", top=top)
    images, labels = load_cifar10("test", root=tmp_path / "data", download=False)
    assert np.array_equal(images.numpy(), expected) and labels[-1] == 9
    with pytest.raises(DataNotFoundError, match="holds no train/<class>/ folders"):
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


def test_packed_members_that_could_land_outside_the_unpacked_folder_are_skipped(tmp_path):
    expected = write_tree(tmp_path / "src")
    packed = tmp_path / "data" / "cifar10-evil.tar.gz"
    packed.parent.mkdir()
    escaped = f"escaped-{tmp_path.name}"
    with tarfile.open(packed, "w:gz") as archive:
        archive.add(tmp_path / "src" / "test", arcname="test")
        # each "test" by its first parts, so in the split: a climb out of the folder, an
        # absolute path, and a link to the outside that a later file would be written through
        archive.addfile(tarfile.TarInfo(f"test/../../{escaped}.txt"), io.BytesIO())
        archive.addfile(tarfile.TarInfo(f"/test/{escaped}.txt"), io.BytesIO())
        link = tarfile.TarInfo("test/cat/out")
        link.type, link.linkname = tarfile.SYMTYPE, tempfile.gettempdir()
        archive.addfile(link)
        archive.addfile(tarfile.TarInfo(f"test/cat/out/{escaped}-linked.txt"), io.BytesIO())
    images, _ = load_cifar10("test", root=tmp_path / "data", download=False)
    assert np.array_equal(images.numpy(), expected)  # the split's images, and nothing else
    assert not list(Path(tempfile.gettempdir()).glob(f"{escaped}*"))
    assert not (Path("/test") / f"{escaped}.txt").exists()


def test_other_sizes_missing_class_and_cache_invalidation(tmp_path):
    tree, data = tmp_path / "src", tmp_path / "data"
    write_tree(tree)
    Image.new("L", (64, 48), 200).save(tree / "test" / "cat" / "big.png")
    pack(tree, data)
    images, labels = load_cifar10("test", root=data)
    assert images.shape == (21, 3, 32, 32) and (images[labels == 3][-1] == 200).all()
    (tree / "test" / "cat" / "big.png").unlink()  # a replaced archive is not served from cache
    pack(tree, data)
    assert len(load_cifar10("test", root=data)[0]) == 20
    for f in (tree / "test" / "dog").iterdir():
        f.unlink()
    pack(tree, data)
    with pytest.raises(DataNotFoundError, match="dog"):
        load_cifar10("test", root=data, download=False)


def test_an_image_of_another_shape_keeps_its_centred_square_not_a_squashed_whole(tmp_path):
    """A 64x48 image gives its middle 48x48 square, resized to 32x32: the black bands in its
    outer 6 columns (of the 8 each side outside that square) are cut off. Squashing the whole
    width into 32 px would keep them, and distort every non-square image."""
    tree = tmp_path / "src"
    write_tree(tree)
    wide = np.full((48, 64, 3), 255, dtype=np.uint8)
    wide[:, :6] = wide[:, -6:] = 0
    Image.fromarray(wide).save(tree / "test" / "cat" / "wide.png")  # sorts after 0001.png
    pack(tree, tmp_path / "data")
    images, labels = load_cifar10("test", root=tmp_path / "data", download=False)
    cropped = images[labels == 3][-1]
    assert cropped.shape == (3, 32, 32) and cropped.min() >= 250  # white, edges included

# --- MNIST IDX files ------------------------------------------------------------------------


def idx_bytes(array: np.ndarray, type_code: int = 8) -> bytes:
    """The IDX encoding of an array: magic 0 0 type ndim, big-endian sizes, values."""
    header = bytes([0, 0, type_code, array.ndim])
    return header + b"".join(d.to_bytes(4, "big") for d in array.shape) + array.tobytes()


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
@pytest.mark.parametrize("folder", ["mnist", "MNIST/raw", "."])
def test_mnist_from_folder(tmp_path, compress, folder):
    images, labels = write_mnist(tmp_path / "data" / folder, compress=compress)
    got, got_labels = load_mnist("test", root=tmp_path / "data", download=False)
    assert got.shape == (5, 1, 28, 28) and got.dtype == torch.uint8
    assert np.array_equal(got[:, 0].numpy(), images)
    assert got_labels.tolist() == labels.tolist() and got_labels.dtype == torch.int64


def test_mnist_download_through_torchvision_with_md5(tmp_path, served, monkeypatch, datasets):
    server, url = served
    images, _ = write_mnist(server, split="train")
    write_mnist(server, split="test")
    resources = [(p.name, md5(p.read_bytes())) for p in sorted(server.iterdir())]
    monkeypatch.setattr(datasets.MNIST, "resources", resources)
    broken = url + "down/"  # the first mirror answers 404: the second one serves
    monkeypatch.setattr(datasets.MNIST, "mirrors", [broken, url])
    got, _ = load_mnist("train", root=tmp_path / "data")
    assert np.array_equal(got[:, 0].numpy(), images)
    assert find_mnist(tmp_path / "data", "test")[0].parent == tmp_path / "data" / "MNIST" / "raw"


@pytest.mark.parametrize("damage, compress", [
    (lambda raw: raw[:-10], False),  # cut short: fewer values than the header announces
    (lambda raw: b"\x08\x08" + raw[2:], False),  # not an IDX file
    (lambda raw: raw[:-20], True),  # a gzip stream cut short
    (lambda raw: raw[:2] + b"\x0d" + raw[3:], True),  # float32 values, not unsigned bytes
], ids=["truncated", "magic", "truncated-gzip", "floats"])
def test_mnist_damaged_files_are_named(tmp_path, damage, compress):
    folder = tmp_path / "data" / "mnist"
    write_mnist(folder, compress=compress)
    path = folder / (mnist.MNIST_FILES["test"][0] + (".gz" if compress else ""))
    path.write_bytes(damage(path.read_bytes()))
    with pytest.raises(CorruptDataError, match=f"cannot read {path}.*replace it"):
        load_mnist("test", root=tmp_path / "data", download=False)


def test_mnist_missing_split_message(tmp_path, datasets):
    write_mnist(tmp_path / "data" / "mnist", split="test")
    with pytest.raises(DataNotFoundError) as info:
        load_mnist("train", root=tmp_path / "data", download=False)
    message = str(info.value)
    assert "train-images-idx3-ubyte.gz" in message and datasets.MNIST.mirrors[0] in message


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


def test_the_default_folders_do_not_depend_on_the_working_directory(tmp_path, monkeypatch):
    """Without EBJEPA_DATA / EBJEPA_CACHE the data and cache live in the checkout's data/,
    wherever Python was started: notebooks run from notebooks/, scripts from anywhere."""
    monkeypatch.delenv("EBJEPA_CACHE")
    monkeypatch.chdir(tmp_path)
    assert data_dir() == REPO / "data"
    assert cache_dir() == REPO / "data" / "cache"


def test_cache_is_reused_and_survives_a_damaged_file(tmp_path, tmp_cache):
    write_packed(tmp_path / "data")
    first, _ = load_cifar10("test", root=tmp_path / "data")
    cached = sorted(tmp_cache.iterdir())
    assert [p.name.endswith(("-images.npy", "-labels.npy")) for p in cached] == [True, True]
    cached[0].write_bytes(b"garbage")  # a damaged cache is rebuilt, not trusted
    again, _ = load_cifar10("test", root=tmp_path / "data")
    assert torch.equal(first, again) and leftovers(tmp_cache) == []


def test_random_subset_mixes_classes_and_keeps_everything_when_asked():
    from ebjepa_tutorial.data import random_subset

    labels = torch.arange(10).repeat_interleave(100)  # stored class by class
    images = torch.arange(1000)
    some, some_labels = random_subset(images, labels, 50, seed=0)
    assert len(some) == 50 and len(some_labels.unique()) >= 8
    assert torch.equal(labels[some], some_labels)
    assert torch.equal(random_subset(images, labels, 50, seed=0)[0], some)
    assert random_subset(images, labels, 5000)[0] is images
