"""Every chapter's ``full`` preset (the paper's configuration, meant for a GPU) trains for real.

Nothing else runs these configs before someone pays for a GPU, so each test takes a ``full``
preset with its full model sizes, optimiser and loss weights, shrinks only the amount of work
(a batch of 2-4, one or two steps, a few generated samples) and checks what the step did: a
finite loss made of the configured terms, every parameter moved, outputs of the configured
shapes, a plan of the configured horizon. Each takes seconds on one CPU core.
"""

from __future__ import annotations

import math
from contextlib import nullcontext
from dataclasses import replace

import pytest
import torch

from ebjepa_tutorial import planning
from ebjepa_tutorial.course.presets import image_preset, preset
from ebjepa_tutorial.data.moving_mnist import generate_moving_mnist
from ebjepa_tutorial.envs import generate_trajectories
from ebjepa_tutorial.envs.two_rooms import transition
from ebjepa_tutorial.models.video import VIDEO_MODEL_CONFIGS, VideoJEPA
from ebjepa_tutorial.models.world import WORLD_CONFIGS
from ebjepa_tutorial.training import image, video, world
from ebjepa_tutorial.training.video import VIDEO_CONFIGS
from research import train_world
from research.train_video import notebook

# `make test` runs these; `make test-fast` (its 30 s budget) leaves them out
pytestmark = pytest.mark.slow


def _initial(build, seed: int) -> dict[str, torch.Tensor]:
    """The weights a training function starts from: it seeds torch with ``seed``, then builds."""
    torch.manual_seed(seed)
    return {name: p.detach().clone() for name, p in build().named_parameters()}


def _unchanged(before: dict[str, torch.Tensor], model: torch.nn.Module) -> list[str]:
    """Names of the parameters that training left exactly as they were."""
    return [name for name, p in model.named_parameters() if torch.equal(p, before[name])]


def _check_total(history, weights: dict[str, float]) -> None:
    """The first step's logged loss is finite and is its logged terms times the weights."""
    total = sum(weight * history[name][0] for name, weight in weights.items())
    assert math.isfinite(history["loss"][0])
    assert history["loss"][0] == pytest.approx(total, rel=1e-4, abs=1e-6)


# -- chapters 01 and 02: the full-width ResNet-18 image JEPA ---------------------------------
def _random_images(n: int = 8) -> torch.Tensor:
    """uint8 ``(n, 3, 32, 32)`` noise: CIFAR-10's shape, no download."""
    generator = torch.Generator().manual_seed(0)
    return torch.randint(0, 256, (n, 3, 32, 32), dtype=torch.uint8, generator=generator)


def _image_step(config: image.ImageJEPAConfig, batch_size: int = 4):
    """One step of ``config`` at ``batch_size``, at the schedule's peak rate (no warm-up).

    Returns the config that ran, the starting weights, the model and its history.
    """
    config = replace(config, steps=1, warmup_steps=0, batch_size=batch_size)
    before = _initial(lambda: image.ImageJEPA(config), config.seed)
    with pytest.MonkeyPatch.context() as patch:
        # in float32 on every host: on a CPU with bf16 the step would run lowered, and a
        # parameter whose true gradient is zero (a bias before the projector's batch norm)
        # would move by rounding on one host and not on another
        patch.setattr(image, "mixed_precision", lambda *args, **kwargs: nullcontext())
        model, history = image.train_image_jepa(config, _random_images(), progress=False)
    return config, before, model, history


def _check_adamw_step(config, before, model) -> None:
    """AdamW's first step moves every parameter, no entry by more than ``lr`` and the largest
    by ``lr``: Adam's first update is ``lr * g / (|g| + eps)`` per entry, whatever the
    gradient's scale (an entry whose gradient is rounding noise moves less)."""
    assert _unchanged(before, model) == []
    moved = {name: (p.detach() - before[name]).abs().max().item()
             for name, p in model.named_parameters()}
    assert max(moved.values()) == pytest.approx(image.LR, rel=1e-2)
    assert all(m <= image.LR * 1.01 for m in moved.values()), moved


def _image_weights(config) -> dict[str, float]:
    if isinstance(config.loss, image.VICReg):
        return {"invariance": config.loss.inv_coeff, "variance": config.loss.std_coeff,
                "covariance": config.loss.cov_coeff}
    return {"invariance": 1.0, "sigreg": config.loss.lam}


@pytest.mark.parametrize("loss", ["vicreg", "sigreg"])
def test_full_resnet18_image_jepa_takes_a_step(loss):
    full = image_preset("full", loss).config
    assert (full.widths, full.blocks_per_stage) == ((64, 128, 256, 512), 2)
    if loss == "sigreg":  # the paper's: a 2048-128 projector, lambda 10 on the plain statistic
        assert (full.projector, full.loss) == ((2048, 128), image.SIGReg(10.0, scale_by_n=False))
    config, before, model, history = _image_step(full)
    _check_adamw_step(config, before, model)
    _check_total(history, _image_weights(config))
    views = image.resize(_random_images(2), config.image_size)  # (2, 3, 32, 32)
    assert model.encoder(views).shape == (2, 512)
    assert model(views).shape == (2, config.projector[1])


# -- chapter 03: the paper's video JEPA on Moving MNIST -------------------------------------
def test_full_video_jepa_takes_a_step():
    full = preset("03", "full").train
    assert full == VIDEO_CONFIGS["full"] and full.model == VIDEO_MODEL_CONFIGS["full"]
    config = replace(full, n_clips=2, batch_size=2, steps=1)
    digits = torch.randint(0, 256, (4, 1, 28, 28), dtype=torch.uint8,
                           generator=torch.Generator().manual_seed(0))
    clips = generate_moving_mnist(digits, 2, config.n_frames).clips  # (2, 10, 1, 64, 64)
    before = _initial(lambda: VideoJEPA(config.model), config.seed)
    model, history = notebook().train_video_jepa(config, clips, video.video_jepa_step,
                                                 device="cpu")
    assert _unchanged(before, model) == []  # Adam: every parameter with a gradient moves
    _check_total(history, {"prediction": 1.0, "variance": video.STD_COEFF,
                           "covariance": video.COV_COEFF})
    with torch.no_grad():  # the paper's full-resolution latent: 16 channels on 64 x 64
        z = model.encode(clips)
        window = z[:, : config.model.context]
        assert z.shape == (2, config.n_frames, 16, 64, 64)
        assert model.predictor(window).shape == (2, 16, 64, 64)
        assert model.project(z[:, :1]).shape == (2 * 64 * 64, config.model.projector_dim)


# -- chapter 05: the full world model on Two Rooms trajectories ----------------------------
def _trajectories(n: int = 4):
    return generate_trajectories(n, world.TRAJECTORY_ACTIONS, seed=0)  # 17 frames each


def test_full_world_model_takes_two_steps():
    """Two steps: the predictor's output layer starts at zero, so the GRU under it gets its
    first gradient only on the second step."""
    full = preset("05", "full").train
    assert full.model == WORLD_CONFIGS["full"] and full.model.input_size == 65
    config = replace(full, n_trajectories=4, batch_size=4, steps=2)
    data = _trajectories()
    before = _initial(lambda: world.WorldModel(config.model), config.seed)
    loop = train_world.notebook().train_world_model  # notebook 05's
    model, history = loop(config, data, world.world_model_step, device="cpu", progress=False)
    assert _unchanged(before, model) == []
    weights = {name: getattr(config.coeffs, name) for name in history if name not in (
        "step", "loss")}
    assert set(weights) >= {"prediction", "variance", "covariance", "temporal",
                            "inverse_dynamics"}
    _check_total(history, weights)
    assert len(history["loss"]) == 2 and all(map(math.isfinite, history["loss"]))
    with torch.no_grad():
        z = model.encode(data.frames(slice(0, 2)))
        assert z.shape == (2, world.TRAJECTORY_ACTIONS + 1, 256)
        futures = model.rollout(z[:, 0], data.actions[:2])
        assert futures.shape == (2, world.TRAJECTORY_ACTIONS, 256)


# -- chapter 06: one re-plan of the paper's planner ----------------------------------------
def test_full_planner_replans_once_with_a_full_world_model(monkeypatch):
    """One re-plan of the full MPPI (H = 90, J = 20) in one episode, through run_episodes."""
    sizes = preset("06", "full")
    config = sizes.planner
    assert (config.horizon, config.iterations, config.execute, config.noise.period) == (
        90, 20, 1, 1)
    model = world.new_model(sizes.world, _trajectories(8))  # full size, untrained
    # An untrained predictor is the identity (its output layer is zero), so every plan
    # would cost the same; random output weights make the imagined futures depend on actions.
    torch.nn.init.normal_(model.predictor.out.weight, std=0.05)
    plans, real_plan = [], planning.plan

    def recording_plan(*args, **kwargs):  # the same plan, keeping every iteration's samples
        plans.append(real_plan(*args, **kwargs, record=True))
        return plans[-1]

    monkeypatch.setattr(planning, "plan", recording_plan)
    result = planning.run_episodes(model, [sizes.first_seed], config, steps=config.execute)
    assert len(plans) == 1  # execute = 1 step, so one re-plan
    made = plans[0]
    assert made.mean.shape == (1, config.horizon, 2)
    assert made.costs.shape == (1, config.iterations) and torch.isfinite(made.costs).all()
    assert len(made.history) == config.iterations
    for actions, costs in made.history:  # (1, N, H, 2) sampled plans, (1, N) their energies
        assert actions.shape == (1, config.samples, config.horizon, 2)
        assert actions.norm(dim=-1).max() <= config.noise.bound + 1e-5
        assert costs.std() > 0  # the energy tells the plans apart
    assert ((made.std >= planning.MIN_STD) & (made.std <= config.noise.bound)).all()
    assert result.paths.shape == (1, config.execute + 1, 2)
    moved = transition(result.paths[:, 0], made.mean[:, 0], result.episodes.layouts)
    torch.testing.assert_close(result.paths[:, 1], moved)  # the plan's first action was taken
