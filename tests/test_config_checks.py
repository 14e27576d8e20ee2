"""Configurations and arguments that cannot work are refused at once, naming the field."""

import dataclasses

import pytest
import torch

from ebjepa_tutorial.course.presets import PRESETS
from ebjepa_tutorial.losses.rollout import rollout
from ebjepa_tutorial.losses.sigreg import sigreg_loss
from ebjepa_tutorial.models.video import VideoJEPA
from ebjepa_tutorial.training.image import ImageJEPAConfig, SIGReg, VICReg
from ebjepa_tutorial.training.video import VIDEO_CONFIGS, VideoJEPAConfig
from ebjepa_tutorial.training.video import Recipe as VideoRecipe
from ebjepa_tutorial.training.world import Recipe, WorldTrainConfig
from research.refit import RefitConfig


@pytest.mark.parametrize("config, change, message", [
    (ImageJEPAConfig, {"projector": (64,)}, "projector must be None or two positive ints"),
    (ImageJEPAConfig, {"batch_size": 0}, "batch_size must be an int >= 2"),
    (ImageJEPAConfig, {"steps": 100}, "warmup_steps must be an int in 0..steps-1 = 99, got 200"),
    (ImageJEPAConfig, {"widths": (16, 32)}, "widths must be four positive ints"),
    (VICReg, {"cov_coeff": float("nan")}, "VICReg.cov_coeff must be a number >= 0"),
    (SIGReg, {"lam": -1.0}, "SIGReg.lam must be a number >= 0"),
    (VideoJEPAConfig, {"batch_size": 0}, "VideoJEPAConfig.batch_size must be an int >= 1"),
    (VideoJEPAConfig, {"n_frames": 5}, "n_frames must be an int >= context \\+ rollout_steps = 6"),
    (VideoJEPAConfig, {"rollout_steps": 0}, "rollout_steps must be an int >= 1"),
    (VideoJEPAConfig, {"unroll": "teacher"}, "unroll must be one of \\['autoregressive', "),
    (VideoRecipe, {"one_step_fraction": 1.0},
     "Recipe.one_step_fraction must be a number in \\[0, 1\\)"),
    (WorldTrainConfig, {"batch_size": 0}, "WorldTrainConfig.batch_size must be an int >= 2"),
    (WorldTrainConfig, {"rollout_steps": 17}, "rollout_steps must be an int in 1..16"),
    (Recipe, {"stay_probability": 1.0}, "Recipe.stay_probability must be a number in \\[0, 1"),
    (Recipe, {"window": 1}, "Recipe.window must be 0 \\(whole trajectories\\) or an int in 2..17"),
    (WorldTrainConfig, {"recipe": Recipe(window=5)}, "window must hold rollout_steps \\+ 1 = 9"),
    (WorldTrainConfig, {"lr": 0.0}, "WorldTrainConfig.lr must be a number > 0"),
    (RefitConfig, {"hidden": 0}, "RefitConfig.hidden must be an int >= 1"),
])
def test_a_config_that_cannot_work_names_its_field(config, change, message):
    with pytest.raises(ValueError, match=message):
        config(**change)


def test_every_preset_is_a_valid_config():
    # building scale.PRESETS ran every __post_init__; the replaced copies must pass too
    for notebook in ("01", "02"):
        for preset in PRESETS[notebook].values():
            dataclasses.replace(preset.long_config)
    assert all(PRESETS[n] for n in PRESETS)


def test_sigreg_without_directions_is_refused():
    z = torch.randn(8, 4)
    with pytest.raises(ValueError, match="num_slices must be an int >= 1"):
        sigreg_loss(z, z + 1, num_slices=0)


def test_rollout_of_zero_steps_is_refused():
    model = VideoJEPA(VIDEO_CONFIGS["ci"].model)
    window = torch.zeros(1, 2, model.config.latent_channels, 16, 16)
    with pytest.raises(ValueError, match="steps must be an int >= 1"):
        rollout(model.predictor, window, 0)


def test_float_frames_in_0_255_are_refused_and_uint8_accepted():
    model = VideoJEPA(VIDEO_CONFIGS["ci"].model)
    frames = torch.randint(0, 256, (1, 2, 1, 64, 64), dtype=torch.uint8)
    with pytest.raises(ValueError, match="float frames must be in 0..1, got values up to 2"):
        model.encode(frames.float())
    assert torch.equal(model.encode(frames), model.encode(frames.float() / 255))
