"""Augmentations: per-image randomness, shapes, normalisation, determinism, clear errors."""

import kornia.augmentation as K
import pytest
import torch

from ebjepa_tutorial.augment import (
    CIFAR10_MEAN,
    CIFAR10_STD,
    AugmentConfig,
    augment,
    build_augmentation,
    denormalize,
    normalize,
    to_float_images,
    two_views,
)
from ebjepa_tutorial.utils import as_generator

PIPELINE = build_augmentation()


def _images(n=8, seed=0):
    return torch.randint(0, 256, (n, 3, 32, 32), dtype=torch.uint8, generator=as_generator(seed))


def test_views_differ_per_image_when_the_image_is_repeated():
    image = _images(1)
    views = augment(image.repeat(64, 1, 1, 1), PIPELINE, as_generator(0))
    flat = views.flatten(1)
    distances = torch.cdist(flat, flat)
    off_diagonal = distances[~torch.eye(64, dtype=torch.bool)]
    assert off_diagonal.min() > 0  # no two of the 64 views are identical


def test_parameters_are_drawn_per_image():
    pipeline = build_augmentation()
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        params = pipeline.forward_parameters(torch.Size([64, 3, 32, 32]))
    by_name = {p.name.split("_")[0]: p.data for p in params}
    boxes = by_name["RandomResizedCrop"]["src"]  # (64, 4, 2) corners of each crop
    # Crop corners are whole pixels, so two of 64 boxes may coincide by chance.
    assert len(torch.unique(boxes.flatten(1), dim=0)) >= 60
    brightness = by_name["ColorJitter"]["brightness_factor"]
    assert len(torch.unique(brightness)) == 64
    flips = by_name["RandomHorizontalFlip"]["batch_prob"].float()
    assert 0 < flips.mean() < 1  # some flipped, some not


def test_output_shape_dtype_and_range():
    views = augment(_images(16), PIPELINE, as_generator(1))
    assert views.shape == (16, 3, 32, 32) and views.dtype == torch.float32
    # Normalised values lie within [(0 - mean) / std, (1 - mean) / std] per channel.
    mean = torch.tensor(CIFAR10_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(CIFAR10_STD).view(1, 3, 1, 1)
    assert (views >= (0 - mean) / std - 1e-4).all() and (views <= (1 - mean) / std + 1e-4).all()
    unnormalised = K.AugmentationSequential(*list(PIPELINE.children())[:-1])  # all but the last
    raw = augment(_images(16), unnormalised, as_generator(1))
    assert raw.min() >= 0 and raw.max() <= 1
    assert torch.allclose(views, normalize(raw), atol=1e-5)


def test_output_size_follows_the_config():
    pipeline = build_augmentation(AugmentConfig(size=16))
    assert augment(_images(4), pipeline, as_generator(0)).shape == (4, 3, 16, 16)


def test_normalize_by_hand_and_round_trip():
    images = torch.zeros(1, 3, 2, 2, dtype=torch.uint8)
    images[0, :, 0, 0] = 255
    out = normalize(images)
    assert out[0, 0, 1, 1].item() == pytest.approx(-0.4914 / 0.2470, rel=1e-5)
    assert out[0, 2, 0, 0].item() == pytest.approx((1 - 0.4465) / 0.2616, rel=1e-5)
    floats = to_float_images(_images(2))
    assert torch.allclose(denormalize(normalize(floats)), floats, atol=1e-6)


def test_normalize_uses_each_channels_own_cifar10_statistics():
    """Black and white pixels standardised with CIFAR-10's published training mean (0.4914,
    0.4822, 0.4465) and std (0.2470, 0.2435, 0.2616), all three channels written out: a
    figure copied from another channel would shift every green (middle) value."""
    images = torch.tensor([0, 255], dtype=torch.uint8).view(2, 1, 1, 1).expand(2, 3, 2, 2)
    black = [-0.4914 / 0.2470, -0.4822 / 0.2435, -0.4465 / 0.2616]
    white = [0.5086 / 0.2470, 0.5178 / 0.2435, 0.5535 / 0.2616]
    assert torch.allclose(normalize(images).mean(dim=(2, 3)), torch.tensor([black, white]),
                          atol=1e-5)


def test_denormalize_clips_to_what_can_be_shown():
    """Values past normalize's black and white (a model's output, say) come back as 0 and 1,
    the range imshow takes for float images, not below or above it."""
    images = torch.tensor([-10.0, 10.0]).view(2, 1, 1, 1).expand(2, 3, 1, 1)
    assert denormalize(images).flatten(1).tolist() == [[0.0] * 3, [1.0] * 3]


def test_uint8_and_float_inputs_give_the_same_views():
    images = _images(4)
    from_uint8 = augment(images, PIPELINE, as_generator(3))
    from_float = augment(images.float() / 255, PIPELINE, as_generator(3))
    assert torch.allclose(from_uint8, from_float)


def test_same_generator_state_gives_same_views_and_leaves_global_rng_alone():
    images = _images(8)
    torch.manual_seed(123)
    before = torch.rand(1)
    torch.manual_seed(123)
    a1, b1 = two_views(images, PIPELINE, as_generator(7))
    after = torch.rand(1)
    a2, b2 = two_views(images, PIPELINE, as_generator(7))
    assert torch.equal(a1, a2) and torch.equal(b1, b2)
    assert not torch.equal(a1, b1)  # the two views of one call differ
    assert not torch.equal(a1, two_views(images, PIPELINE, as_generator(8))[0])
    assert torch.equal(before, after)  # augmenting did not consume the global RNG


def test_views_on_another_device_fork_that_devices_random_stream(monkeypatch):
    """On a GPU the pipeline draws from the device's own generator: augment forks that one
    (not only the CPU's), so seeding it leaves the caller's GPU stream as it was."""
    import contextlib

    forked = []

    @contextlib.contextmanager
    def fork_rng(devices, device_type):
        forked.append((devices, device_type))
        yield

    monkeypatch.setattr(torch.random, "fork_rng", fork_rng)
    monkeypatch.setattr(torch, "manual_seed", lambda seed: None)  # no GPU here to seed
    images = torch.empty(2, 3, 8, 8, dtype=torch.uint8, device="meta")  # stands in for cuda
    assert augment(images, lambda x: x, as_generator(0)).device == images.device
    assert forked == [([images.device], "meta")]


@pytest.mark.parametrize(
    "bad, match",
    [
        (torch.rand(3, 32, 32), "batch"),
        (torch.rand(2, 1, 32, 32), "3 colour channels"),
        (torch.rand(2, 32, 32, 3), "3 colour channels"),
        (torch.rand(2, 3, 32, 32) * 4 - 2, r"\[0, 1\].*normalised images\? augment raw ones"),
        (torch.rand(2, 3, 32, 32) * 255, r"\[0, 1\].*make them uint8"),  # never divided by 255
        (torch.arange(384).view(2, 3, 8, 8) % 256, r"torch.int64 in \[0, 255\].*make them uint8"),
        (torch.full((2, 3, 8, 8), 1.2), r"\[0, 1\].*clamp them"),  # a jitter's overshoot
        (torch.rand(2, 3, 32, 32).index_fill_(2, torch.tensor([5]), float("nan")), "nan"),
    ],
)
def test_bad_input_is_named(bad, match):
    with pytest.raises(ValueError, match=match):
        augment(bad, PIPELINE, as_generator(0))


def test_each_setting_of_the_config_reaches_its_augmentation():
    config = AugmentConfig(size=24, crop_scale=(0.3, 0.9), jitter_p=0.7, grayscale_p=0.15,
                           solarize_p=0.05, flip_p=0.25)
    steps = {type(m).__name__: m for m in build_augmentation(config).children()}
    torch.manual_seed(0)
    shape = torch.Size([4000, 3, 32, 32])
    crop = steps["RandomResizedCrop"].forward_parameters(shape)
    corners = crop["src"]  # (B, 4, 2): the crop's corners in the 32-px image, clockwise
    area = ((corners[:, 1, 0] - corners[:, 0, 0] + 1) * (corners[:, 2, 1] - corners[:, 1, 1] + 1)
            / 32**2)  # the fraction kept, within a pixel's rounding of crop_scale
    assert 0.27 < area.min() < 0.33 and 0.87 < area.max() < 0.93
    assert tuple(crop["output_size"][0].tolist()) == (24, 24)
    for name, p in [("ColorJitter", 0.7), ("RandomGrayscale", 0.15), ("RandomSolarize", 0.05),
                    ("RandomHorizontalFlip", 0.25)]:  # the share of images each one changes
        applied = steps[name].forward_parameters(shape)["batch_prob"].float().mean()
        assert abs(applied - p) < 0.03, name


def test_the_default_recipe_is_the_one_its_docstring_names():
    """AugmentConfig()'s pipeline, measured: crops keep 20% to 100% of the area, and colour
    jitter, grayscale, solarisation and flips reach 80%, 20%, 10% and 50% of the images
    (the SimCLR / VICReg CIFAR-10 settings that the chapters' figures come from)."""
    steps = {type(m).__name__: m for m in PIPELINE.children()}
    shape = torch.Size([4000, 3, 32, 32])
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        corners = steps["RandomResizedCrop"].forward_parameters(shape)["src"]
        applied = {name: steps[name].forward_parameters(shape)["batch_prob"].float().mean()
                   for name in ("ColorJitter", "RandomGrayscale", "RandomSolarize",
                                "RandomHorizontalFlip")}
    area = ((corners[:, 1, 0] - corners[:, 0, 0] + 1) * (corners[:, 2, 1] - corners[:, 1, 1] + 1)
            / 32**2)
    assert 0.17 < area.min() < 0.23 and area.max() > 0.97
    expected = {"ColorJitter": 0.8, "RandomGrayscale": 0.2, "RandomSolarize": 0.1,
                "RandomHorizontalFlip": 0.5}
    for name, p in expected.items():
        assert abs(applied[name] - p) < 0.03, name


def test_colour_jitter_draws_the_vicreg_strengths():
    """Brightness and contrast factors from [0.6, 1.4], saturation from [0.8, 1.2] and hue
    shifts from [-0.1, 0.1] (VICReg's CIFAR-10 jitter, 0.4, 0.4, 0.2, 0.1): each range is
    filled and not exceeded."""
    jitter = next(m for m in PIPELINE.children() if isinstance(m, K.ColorJitter))
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        params = jitter.forward_parameters(torch.Size([4000, 3, 32, 32]))
    ranges = {"brightness_factor": (0.6, 1.4), "contrast_factor": (0.6, 1.4),
              "saturation_factor": (0.8, 1.2), "hue_factor": (-0.1, 0.1)}
    for key, (low, high) in ranges.items():
        values = params[key]
        assert low - 1e-6 <= values.min() < low + 0.01, key
        assert high - 0.01 < values.max() <= high + 1e-6, key


def test_solarize_inverts_exactly_the_pixels_from_one_half_up():
    """BYOL's solarisation: a pixel below 0.5 is kept and one at or above it becomes 1 - x,
    with nothing added first (a drawn threshold or an addition would move other pixels)."""
    pipeline = build_augmentation(AugmentConfig(solarize_p=1.0))
    solarize = next(m for m in pipeline.children() if isinstance(m, K.RandomSolarize))
    x = torch.linspace(0.01, 0.99, 3 * 8 * 8).view(1, 3, 8, 8).repeat(16, 1, 1, 1)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        out = solarize(x)
    assert torch.allclose(out, torch.where(x < 0.5, x, 1 - x), atol=1e-6)
