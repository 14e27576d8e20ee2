"""Configurations and arguments that cannot work are refused at once, naming the field."""

import dataclasses

import pytest
import torch

from ebjepa_tutorial.course.presets import PRESETS, SCALES
from ebjepa_tutorial.models.video import VideoJEPA
from ebjepa_tutorial.training.image import ImageJEPAConfig
from ebjepa_tutorial.training.video import VIDEO_CONFIGS, VideoJEPAConfig
from research.refit import RefitConfig


@pytest.mark.parametrize("config, change, message", [
    (ImageJEPAConfig, {"steps": 100}, "warmup_steps must be an int in 0..steps-1 = 99, got 200"),
    (ImageJEPAConfig, {"steps": 0}, "ImageJEPAConfig.steps must be an int >= 1, got 0"),
    (VideoJEPAConfig, {"unroll": "teacher"}, "unroll must be one of \\['autoregressive', "),
    (RefitConfig, {"hidden": 0}, "RefitConfig.hidden must be an int >= 1"),
])
def test_a_config_that_cannot_work_names_its_field(config, change, message):
    with pytest.raises(ValueError, match=message):
        config(**change)


def _configs(value):
    """Every dataclass inside ``value`` (itself, its fields, tuples of them), depth first."""
    if dataclasses.is_dataclass(value):
        yield value
        for field in dataclasses.fields(value):
            yield from _configs(getattr(value, field.name))
    elif isinstance(value, tuple):
        for item in value:
            yield from _configs(item)


def test_every_preset_is_a_valid_config():
    # every notebook has a preset at every scale, and every config inside one passes its
    # checks again when rebuilt (dataclasses.replace reruns __post_init__), so a check
    # added later cannot be silently broken by a preset built before it
    assert set(PRESETS) == {f"{n:02d}" for n in range(8)}
    checked = 0
    for notebook, scales in PRESETS.items():
        assert set(scales) == set(SCALES), notebook
        for preset in scales.values():
            for config in _configs(preset):
                dataclasses.replace(config)
                checked += 1
    assert checked > 100  # the planners, recipes, models and noise of every preset


def test_float_frames_outside_0_1_are_refused_and_uint8_accepted():
    """0..255 floats (a forgotten / 255) and standardised frames (negative) are refused."""
    model = VideoJEPA(VIDEO_CONFIGS["ci"].model)
    frames = torch.randint(0, 256, (1, 2, 1, 64, 64), dtype=torch.uint8)
    scaled = frames.float() / 255
    for wrong in (frames.float(), (scaled - scaled.mean()) / scaled.std()):
        with pytest.raises(ValueError, match=r"uint8 or float in 0\.\.1"):
            model.encode(wrong)
    assert torch.equal(model.encode(frames), model.encode(frames.float() / 255))
