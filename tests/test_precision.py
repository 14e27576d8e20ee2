"""Mixed precision on a GPU (and for the image and video networks on a CPU with bf16
instructions): the networks run in bfloat16, the losses' batch statistics in float32.

There is no GPU here, so the GPU's autocast is stood in for by the CPU's bfloat16 autocast
(patched into the training modules): it lowers the same matmuls and convolutions.
"""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from ebjepa_tutorial import distributed, utils
from ebjepa_tutorial.data.moving_mnist import generate_moving_mnist
from ebjepa_tutorial.models.video import VideoJEPA
from ebjepa_tutorial.training import image, video
from ebjepa_tutorial.training.video import VIDEO_CONFIGS
from research.train_video import notebook


def test_on_the_cpu_nothing_is_lowered_or_reordered():
    with utils.mixed_precision("cpu"):
        product = torch.ones(4, 4) @ torch.ones(4, 4)
    assert product.dtype == torch.float32
    assert utils.memory_format("cpu") == torch.contiguous_format
    assert utils.memory_format("cuda") == torch.channels_last


@pytest.mark.parametrize("has_bf16", [True, False])
def test_a_cpu_lowers_only_when_asked_and_able(monkeypatch, has_bf16):
    for check in ("_is_avx512_bf16_supported", "_is_amx_tile_supported"):  # the CPU's bf16
        monkeypatch.setattr(torch.cpu, check, lambda: has_bf16, raising=False)
    with utils.mixed_precision("cpu", cpu=True):
        asked = torch.ones(4, 4) @ torch.ones(4, 4)
    with utils.mixed_precision("cpu"):
        not_asked = torch.ones(4, 4) @ torch.ones(4, 4)
    assert asked.dtype == (torch.bfloat16 if has_bf16 else torch.float32)
    assert not_asked.dtype == torch.float32  # the world models keep float32 on any CPU


def record_calls(monkeypatch, module) -> list[dict]:
    """The keyword arguments of each call of ``module.mixed_precision``."""
    calls = []
    monkeypatch.setattr(module, "mixed_precision", lambda *a, **k: calls.append(k) or
                        utils.mixed_precision(*a, **k))
    return calls


def test_image_training_asks_for_bf16_on_the_cpu(monkeypatch):
    calls = record_calls(monkeypatch, image)
    config = image.ImageJEPAConfig(widths=(4, 8, 8, 8), projector=(16, 16), batch_size=8,
                                   steps=2, warmup_steps=0)
    image.train_image_jepa(config, torch.randint(0, 256, (16, 3, 32, 32), dtype=torch.uint8),
                           progress=False)
    assert calls and all(k == {"cpu": True} for k in calls)


def test_video_training_asks_for_bf16_on_the_cpu(monkeypatch):
    calls = record_calls(monkeypatch, video)
    config = replace(VIDEO_CONFIGS["ci"], steps=2, batch_size=4)
    digits = torch.randint(0, 256, (20, 1, 28, 28), dtype=torch.uint8)
    clips = generate_moving_mnist(digits, 8, config.n_frames, seed=0).clips
    notebook().train_video_jepa(config, clips, video.video_jepa_step, device="cpu")
    assert len(calls) == 2 and all(k == {"cpu": True} for k in calls)


def cpu_bf16(device, **_):
    return torch.autocast("cpu", dtype=torch.bfloat16)


def spy(monkeypatch, module, name: str) -> list[torch.dtype]:
    """Record the dtype of the first argument each call of ``module.name`` receives."""
    seen, original = [], getattr(module, name)

    def wrapper(*args, **kwargs):
        first = next(a for a in args if isinstance(a, torch.Tensor))
        seen.append(first.dtype)
        return original(*args, **kwargs)

    monkeypatch.setattr(module, name, wrapper)
    return seen


@pytest.mark.parametrize("loss", [image.VICReg(), image.SIGReg()])
def test_image_training_lowers_the_network_and_not_the_loss(monkeypatch, loss):
    monkeypatch.setattr(image, "mixed_precision", cpu_bf16)
    # the loss the training step calls: VICReg's weighted sum, or SIGReg's loss
    received = spy(monkeypatch, image, "vicreg" if loss == image.VICReg() else "sigreg_loss")
    outputs = []
    monkeypatch.setattr(image.ImageJEPA, "forward",
                        lambda self, v: outputs.append(z := self.projector(self.encoder(v))) or z)
    config = image.ImageJEPAConfig(loss=loss, widths=(4, 8, 8, 8), projector=(16, 16),
                                   batch_size=8, steps=2, warmup_steps=0)
    images = torch.randint(0, 256, (32, 3, 32, 32), dtype=torch.uint8)
    _, history = image.train_image_jepa(config, images, progress=False)
    assert {z.dtype for z in outputs} == {torch.bfloat16}  # the network ran lowered
    assert set(received) == {torch.float32}  # ... and the loss was given float32
    assert all(map(torch.isfinite, map(torch.tensor, history["loss"])))


def test_video_training_keeps_variance_and_covariance_in_float32(monkeypatch):
    monkeypatch.setattr(video, "mixed_precision", cpu_bf16)
    received = spy(monkeypatch, distributed, "variance_and_covariance")  # the step's
    config = replace(VIDEO_CONFIGS["ci"], steps=2, batch_size=4)
    digits = torch.randint(0, 256, (20, 1, 28, 28), dtype=torch.uint8)
    clips = generate_moving_mnist(digits, 8, config.n_frames, seed=0).clips
    model = VideoJEPA(config.model).train()
    encoded = []
    model.encoder.register_forward_hook(lambda module, args, out: encoded.append(out.dtype))
    optimizer = torch.optim.Adam(model.parameters())
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda n: 1.0)
    loss, terms = video.video_jepa_step(model, optimizer, scheduler, clips[:4],
                                        config.rollout_steps, config)
    assert encoded == [torch.bfloat16] and received == [torch.float32]
    assert loss.dtype == torch.float32 and torch.isfinite(loss)
    _, history = notebook().train_video_jepa(config, clips, video.video_jepa_step, device="cpu")
    assert received == [torch.float32] * 3  # the step above, then training's two
    assert all(map(torch.isfinite, map(torch.tensor, history["loss"])))


def test_world_training_lowers_only_the_encoder(monkeypatch):
    from ebjepa_tutorial.envs import generate_trajectories
    from ebjepa_tutorial.losses import world as world_losses
    from ebjepa_tutorial.models.world import WORLD_CONFIGS, WorldModel
    from ebjepa_tutorial.training import world

    monkeypatch.setattr(world_losses, "mixed_precision", cpu_bf16)  # encode_for_loss's
    received = spy(monkeypatch, world, "variance_covariance_loss")  # the step's
    data = generate_trajectories(4, 4, seed=0)
    model = WorldModel(WORLD_CONFIGS["ci"])
    frames = data.frames()  # (4, 5, 2, 65, 65)
    model.fit_input_stats(frames)
    encoded = []
    model.encoder.register_forward_hook(lambda module, args, out: encoded.append(out.dtype))
    config = world.WorldTrainConfig(model=WORLD_CONFIGS["ci"], rollout_steps=2)
    loss, terms = world.world_model_step(model, world.new_optimizer(model, config), frames,
                                         data.actions, torch.Generator().manual_seed(0), config,
                                         step=0)
    assert encoded == [torch.bfloat16] and received == [torch.float32]
    assert loss.dtype == torch.float32 and torch.isfinite(loss)
