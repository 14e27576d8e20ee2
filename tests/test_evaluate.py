"""Linear probe and kNN on synthetic features; features of a frozen encoder."""

import math

import pytest
import torch

from ebjepa_tutorial.augment import CIFAR10_MEAN, CIFAR10_STD
from ebjepa_tutorial.evaluation.classify import (
    accuracy,
    embed,
    knn_predict,
    linear_probe,
    probe_encoder,
)
from ebjepa_tutorial.models.encoders import ResNet18
from ebjepa_tutorial.training.image import ImageJEPAConfig
from ebjepa_tutorial.utils import as_generator


def _clusters(n, num_classes=4, dim=16, spread=0.3, seed=0):
    """Points around ``num_classes`` random centres on the unit sphere: separable classes."""
    gen = as_generator(seed)
    centres = torch.nn.functional.normalize(
        torch.randn(num_classes, dim, generator=as_generator(99)), dim=1
    )
    labels = torch.randint(0, num_classes, (n,), generator=gen)
    return centres[labels] * 3 + spread * torch.randn(n, dim, generator=gen), labels


def test_linear_probe_separable_data():
    x_train, y_train = _clusters(600, seed=0)
    x_test, y_test = _clusters(300, seed=1)
    test_accuracy, probe = linear_probe(x_train, y_train, x_test, y_test)
    assert test_accuracy > 0.98
    logits = probe(x_test)
    assert logits.shape == (300, 4) and accuracy(logits, y_test) == test_accuracy


def test_linear_probe_random_labels_is_at_chance():
    gen = as_generator(0)
    x_train, x_test = torch.randn(1000, 16, generator=gen), torch.randn(1000, 16, generator=gen)
    y_train = torch.randint(0, 10, (1000,), generator=gen)
    y_test = torch.randint(0, 10, (1000,), generator=gen)
    test_accuracy, _ = linear_probe(x_train, y_train, x_test, y_test)
    assert 0.04 < test_accuracy < 0.17  # chance is 0.10


def test_linear_probe_is_seeded():
    x, y = _clusters(200)
    (_, a), (_, b) = linear_probe(x, y, x, y), linear_probe(x, y, x, y)
    assert torch.equal(a.head.weight, b.head.weight)


def test_knn_separable_and_random():
    x_train, y_train = _clusters(500, seed=0)
    x_test, y_test = _clusters(200, seed=1)
    assert (knn_predict(x_train, y_train, x_test) == y_test).float().mean() > 0.98
    gen = as_generator(2)
    noise_train, noise_test = (
        torch.randn(2000, 16, generator=gen),
        torch.randn(1000, 16, generator=gen),
    )
    labels_train = torch.randint(0, 10, (2000,), generator=gen)
    labels_test = torch.randint(0, 10, (1000,), generator=gen)
    chance = (knn_predict(noise_train, labels_train, noise_test) == labels_test).float().mean()
    assert 0.05 < chance < 0.16


def test_knn_votes_by_hand():
    train = torch.tensor([[1.0, 0.0], [0.9, 0.1], [0.0, 1.0]])
    labels = torch.tensor([0, 0, 1])
    query = torch.tensor([[0.6, 0.8], [1.0, 0.05]])
    # All three train rows vote (k = min(20, 3)): a majority would say class 0 for both,
    # but the temperature's weights favour the much closer class-1 neighbour for the first
    # query (cosine 0.8 vs 0.6 and 0.68).
    assert knn_predict(train, labels, query).tolist() == [1, 0]
    # the single nearest row (class 0, cosine 1) loses to five slightly farther class-1 rows
    # (cosine 0.99 each: 5 exp(0.99 / 0.07) > exp(1 / 0.07)), where 1-NN would say class 0
    angle = math.acos(0.99)
    near = [[math.cos(angle), math.sin(angle)]] * 5
    assert knn_predict(torch.tensor([[1.0, 0.0]] + near), torch.tensor([0] + [1] * 5),
                       torch.tensor([[1.0, 0.0]])).tolist() == [1]
    # similarity is the cosine, not the dot product: a long row pointing away does not win
    assert knn_predict(torch.tensor([[0.5, 0.0], [10.0, 10.0]]), torch.tensor([0, 1]),
                       torch.tensor([[1.0, 0.0]])).tolist() == [0]


def test_embed_is_frozen_and_restores_the_mode():
    torch.manual_seed(0)
    encoder = ResNet18(widths=(4, 8, 8, 8))
    encoder.train()
    images = torch.randint(0, 256, (10, 3, 32, 32), dtype=torch.uint8, generator=as_generator(0))
    feats = embed(encoder, images, 32)
    assert feats.shape == (10, 8) and feats.dtype == torch.float32 and not feats.requires_grad
    assert encoder.training  # the caller's mode is restored
    # Eval mode: each image's features do not depend on the rest of its batch.
    again = embed(encoder, images[:3], 32)
    assert torch.allclose(feats[:3], again, atol=1e-5)
    with pytest.raises(TypeError, match="uint8"):
        embed(encoder, images.float(), 32)


class _ChannelMeans(torch.nn.Module):
    """An "encoder" whose features are each channel's mean: ``(N, 3, S, S) -> (N, 3)``."""

    def __init__(self):
        super().__init__()
        self.anchor = torch.nn.Parameter(torch.zeros(()))  # embed reads the device from it

    def forward(self, x):
        return x.mean(dim=(2, 3))


@pytest.mark.parametrize("size", [32, 16])
def test_embed_normalises_with_the_cifar_statistics_before_the_encoder(size):
    # a flat image stays flat when resized, so its features are (value / 255 - mean) / std
    # per channel at every size: a missing /255, a missing normalisation or a resize that
    # darkens the borders would each give other numbers
    levels = torch.tensor([[0, 128, 255], [40, 200, 90]], dtype=torch.uint8)  # (N, 3)
    images = levels[:, :, None, None].expand(2, 3, 32, 32).contiguous()
    mean, std = torch.tensor(CIFAR10_MEAN), torch.tensor(CIFAR10_STD)
    expected = (levels.float() / 255 - mean) / std
    assert torch.allclose(embed(_ChannelMeans(), images, size), expected, atol=1e-5)


def test_the_linear_probe_standardises_with_the_training_features():
    # train: class 0 at x = -1, class 1 at x = +1, both shifted by 100; test: class 1 only.
    # Standardised with the training statistics, every test point lands at +1 and is right;
    # standardised with the test set's own, they would land around 0, half of them wrong.
    gen = as_generator(0)
    y_train = torch.arange(200) % 2
    x_train = 100 + (2 * y_train.float() - 1)[:, None] + 0.1 * torch.randn(200, 1, generator=gen)
    x_test = 101 + 0.1 * torch.randn(50, 1, generator=gen)
    test_accuracy, probe = linear_probe(x_train, y_train, x_test, torch.ones(50, dtype=torch.long))
    assert test_accuracy == 1.0
    assert torch.allclose(probe.mean, x_train.mean(dim=0))
    assert torch.allclose(probe.std, x_train.std(dim=0) + 1e-6)


def test_knn_ignores_the_length_of_a_query():
    """Cosine similarity on both sides: a query scaled by any factor has the same neighbours
    and the same weighted vote. Here the nearest row (class 0, cosine 1) outweighs two at
    cosine 0.9 (exp(1 / 0.07) > 2 exp(0.9 / 0.07)); a query left unnormalised at a tenth of
    its length would flatten the weights into a majority for class 1."""
    far = [[0.9, math.sqrt(1 - 0.81)]] * 2
    train, labels = torch.tensor([[1.0, 0.0]] + far), torch.tensor([0, 1, 1])
    for scale in (0.1, 1.0, 3.0):
        assert knn_predict(train, labels, torch.tensor([[scale, 0.0]])).tolist() == [0], scale


def test_a_dead_feature_leaves_the_linear_probe_finite():
    """A feature that never varies (a ReLU unit off for every image, common in a trained
    encoder) has standard deviation 0: the probe's + 1e-6 keeps its standardised value at 0,
    not 0 / 0, so the other features still classify."""
    x_train, y_train = _clusters(300, seed=0)
    x_test, y_test = _clusters(100, seed=1)

    def with_dead(x):
        return torch.cat([x, torch.zeros(len(x), 1)], dim=1)

    test_accuracy, probe = linear_probe(with_dead(x_train), y_train, with_dead(x_test), y_test)
    assert test_accuracy > 0.95 and torch.isfinite(probe(with_dead(x_test))).all()


def test_probe_encoder_fits_on_the_train_split_and_scores_on_the_test_split():
    """Both scores come from models fitted to the train split: when the test split labels
    red images 1 and blue images 0, the opposite of train, the probe and the kNN are wrong on
    every test image. Fitting either to the test split (the kNN finding each test image
    itself among its neighbours) would score 100%."""
    gen = as_generator(0)

    def split(red_label):
        red = torch.rand(20, generator=gen) < 0.5
        red_rgb, blue_rgb = torch.tensor([200, 30, 30]), torch.tensor([30, 30, 200])
        colours = torch.where(red[:, None], red_rgb, blue_rgb)
        colours = colours + torch.randint(-20, 21, (20, 3), generator=gen)
        images = colours.to(torch.uint8)[:, :, None, None].expand(20, 3, 32, 32).contiguous()
        return images, torch.where(red, red_label, 1 - red_label)

    scores = probe_encoder(_ChannelMeans(), ImageJEPAConfig(), split(0), split(1))
    assert scores == {"probe_acc": 0.0, "knn_acc": 0.0}


def test_the_returned_probe_standardises_raw_features_itself():
    """The probe linear_probe hands back takes raw features: on the training features, far
    from 0 (class 0 at 99, class 1 at 101), it is right on every row. A head fed them without
    the stored train statistics would put every row on one side."""
    gen = as_generator(0)
    y_train = torch.arange(200) % 2
    x_train = 100 + (2 * y_train.float() - 1)[:, None] + 0.1 * torch.randn(200, 1, generator=gen)
    _, probe = linear_probe(x_train, y_train, x_train, y_train)
    with torch.no_grad():
        assert accuracy(probe(x_train), y_train) == 1.0
