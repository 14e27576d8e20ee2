"""Video JEPA on Moving MNIST (notebook 03). A step, :func:`video_jepa_step`, takes the K-step
loss plus the variance and covariance of the projected latents (each location a sample):

    L = (1/K) sum_k mean ||zhat_k - z||^2 + std v(P(Z)) + cov c(P(Z))
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
import torch.nn.functional as F

from .. import distributed
from ..data.moving_mnist import generate_moving_mnist
from ..losses.rollout import UNROLLS, parallel_rollout_loss, rollout_loss
from ..models.video import VIDEO_MODEL_CONFIGS, VideoJEPA, VideoModelConfig, frame_decoder
from ..utils import at_least_float32, get_device, mixed_precision
from .checkpoints import checkpoint_paths, run_identity, step_identity
from .loop import History, load_or_train, run_steps, step_generator
from .optim import warmup_cosine_scheduler

LOG_EVERY, CHECKPOINT_EVERY = 10, 100  # steps between the history's rows, and between saves
STD_COEFF = 10.0  # std, the variance term's weight: the paper's, in every run of the course
COV_COEFF = 100.0  # cov, the covariance term's weight: likewise


@dataclass(frozen=True)
class Recipe:
    """The class run's departures from the paper, to learn more per CPU-minute (notebook 03)."""

    cosine: bool = True  # decay the rate to 0 by a half cosine (the paper: constant)
    channels_last: bool = True  # convolutions in channels_last: faster, on CPUs too
    one_step_fraction: float = 0.5  # this share of the steps trains K = 1 (the paper: 0)
    detach_later_orders: bool = True  # orders 2..K unroll from detached latents


PAPER_RECIPE = Recipe(cosine=False, channels_last=False, one_step_fraction=0.0,
                      detach_later_orders=False)


@dataclass(frozen=True)
class VideoJEPAConfig:
    """One training run. Defaults: the class scale (~10 minutes on 2 CPU cores)."""

    model: VideoModelConfig = field(default_factory=lambda: VIDEO_MODEL_CONFIGS["class"])
    n_clips: int = 4000  # training clips from the training digits (make_clips; 164 MB)
    n_frames: int = 10  # frames per clip (needs >= context + rollout_steps)
    batch_size: int = 16  # clips per step, the global batch under torchrun (the paper: 64)
    steps: int = 2400  # sized for a class period on a laptop CPU
    lr: float = 3e-3  # Adam's base rate (the paper: 1e-3, constant)
    rollout_steps: int = 4  # K
    unroll: str = "parallel"  # the paper's, or "autoregressive" (losses.rollout.UNROLLS)
    recipe: Recipe = field(default_factory=Recipe)  # the class run's; PAPER_RECIPE: the paper's
    seed: int = 0

    def __post_init__(self):
        if self.unroll not in UNROLLS:
            raise ValueError(f"VideoJEPAConfig.unroll must be one of {sorted(UNROLLS)}, "
                             f"got {self.unroll!r}")

    @property
    def switch_step(self) -> int:
        """The steps trained at K = 1 before the rollout begins."""
        return math.ceil(self.recipe.one_step_fraction * self.steps)


VIDEO_CONFIGS = {
    # PyTorch's CPU backward crashes in channels_last on the ci encoder's strided 1x1 convolutions
    "ci": VideoJEPAConfig(model=VIDEO_MODEL_CONFIGS["ci"], n_clips=256, batch_size=8, steps=20,
                          recipe=Recipe(channels_last=False)),
    "class": VideoJEPAConfig(),
    # the paper: 18,000 clips of 10 frames, batch 64, 50 epochs at a constant 1e-3
    "full": VideoJEPAConfig(model=VIDEO_MODEL_CONFIGS["full"], n_clips=18_000, batch_size=64,
                            steps=50 * 18_000 // 64, lr=1e-3, recipe=PAPER_RECIPE),
}


def make_clips(config: VideoJEPAConfig, train_digits: torch.Tensor) -> torch.Tensor:
    """The run's training clips from ``train_digits``: uint8 ``(n_clips, n_frames, 1, 64, 64)``."""
    return generate_moving_mnist(train_digits, config.n_clips, config.n_frames,
                                 seed=config.seed).clips


def check_clips(clips: torch.Tensor, min_frames: int) -> None:
    """Raise unless ``clips`` is uint8 ``(N, T, 1, 64, 64)`` with ``T >= min_frames``."""
    if (not isinstance(clips, torch.Tensor) or clips.dtype != torch.uint8 or clips.ndim != 5
            or clips.shape[2:] != (1, 64, 64) or clips.shape[1] < min_frames):
        got = (f"{tuple(clips.shape)} {clips.dtype}" if isinstance(clips, torch.Tensor)
               else type(clips).__name__)
        raise ValueError(f"clips must be uint8 (N, T, 1, 64, 64) with T at least {min_frames} "
                         f"(context + prediction steps), from generate_moving_mnist; got {got}")


def video_jepa_step(model, optimizer, scheduler, frames, k, config):
    """One step (notebook 03) on uint8 clips ``frames (b, T, 1, 64, 64)`` with ``k`` prediction
    steps: returns the detached total and terms."""
    with mixed_precision(frames.device, cpu=True):  # bf16 networks where fast; statistics in fp32
        z = model.encode(frames)  # Z: (b, T, C, S, S), every frame on its own
        multistep_loss = parallel_rollout_loss if config.unroll == "parallel" else rollout_loss
        prediction = multistep_loss(model.predictor, z, model.config.context, k,
                                    config.recipe.detach_later_orders)  # L_pred (exercise 1)
        projected = model.project(z)  # h(Z): (b*T*S*S, D), every location of every frame a row
    # v and c of every process's rows under torchrun (the global batch), else of these rows
    variance, covariance = distributed.variance_and_covariance(at_least_float32(projected))
    total = prediction + STD_COEFF * variance + COV_COEFF * covariance  # L
    optimizer.zero_grad(set_to_none=True)  # drop the last step's gradients
    total.backward()  # dL/d(every weight): encoder, predictor, projector
    distributed.average_gradients(model.parameters())  # torchrun: the mean over processes
    optimizer.step()  # Adam
    scheduler.step()  # the learning rate of the next step
    terms = {"prediction": prediction, "variance": variance, "covariance": covariance}
    return total.detach(), {name: value.detach() for name, value in terms.items()}


def new_scheduler(optimizer: torch.optim.Optimizer, config: VideoJEPAConfig):
    """The rate over the run: a half cosine to 0 (``config.recipe.cosine``), else constant."""
    if config.recipe.cosine:
        return warmup_cosine_scheduler(optimizer, config.steps, 0)
    return torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: 1.0)


def train_video_jepa(config: VideoJEPAConfig, clips: torch.Tensor,
                     checkpoint: str | Path | None = None, progress: bool = True,
                     device: torch.device | str | None = None, step=None,
                     after=None) -> tuple[VideoJEPA, History]:
    """``(model in eval mode, history)`` trained on uint8 ``clips (N, T, 1, 64, 64)``, resumable
    from ``checkpoint``; ``after(done, (model, optimizer, scheduler), history)`` after each step."""
    step = step or video_jepa_step
    check_clips(clips, config.model.context + config.rollout_steps)
    device = get_device(device)
    torch.manual_seed(config.seed)  # the same initial model in every process
    layout = torch.channels_last if config.recipe.channels_last else torch.contiguous_format
    model = VideoJEPA(config.model).to(device, memory_format=layout)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
    parts = (model, optimizer, new_scheduler(optimizer, config))

    def batch(n: int) -> tuple[torch.Tensor, int]:  # this process's clips of step n, and K
        index = torch.randint(0, len(clips), (config.batch_size,),
                              generator=step_generator(config.seed, n))
        k = 1 if n < config.switch_step else config.rollout_steps
        return clips[distributed.local_rows(index)].to(device), k

    model.train()
    history = run_steps(
        lambda frames_and_k, n: step(*parts, *frames_and_k, config), batch, config.steps,
        log_every=LOG_EVERY, desc="video JEPA", progress=progress, checkpoint=checkpoint,
        parts=parts, identity=identity(config, step=step), every=CHECKPOINT_EVERY,
        after=None if after is None else lambda done, history: after(done, parts, history))
    return model.eval(), history


def identity(config: VideoJEPAConfig, train_digits: torch.Tensor | None = None,
             step=None) -> dict:
    """The run's :func:`run_identity`, a hash of the digits of its clips, an edited ``step``'s."""
    digits = {} if train_digits is None else {"train_digits": hashlib.sha1(
        train_digits.contiguous().numpy().tobytes()).hexdigest()[:12]}
    return run_identity(config, ("steps", "batch_size", "lr", "rollout_steps", "seed"),
                        **digits, **step_identity(step, video_jepa_step))


def run_name(scale: str, config: VideoJEPAConfig) -> str:
    """``video_jepa_<scale>_K<K>_seed<seed>``, notebook 03's name for the run ``config``."""
    return f"video_jepa_{scale}_K{config.rollout_steps}_seed{config.seed}"


def train_or_load(config: VideoJEPAConfig, name: str, train_digits: torch.Tensor,
                  device: torch.device | str | None = None, step=None, **options):
    """``(model in eval mode, history)`` of ``config``: loaded if saved as ``name``, else trained
    on clips of ``train_digits (D, 1, 28, 28)`` and saved."""
    torch.manual_seed(config.seed)
    model = VideoJEPA(config.model).to(get_device(device))
    path, shipped = checkpoint_paths(name)
    return load_or_train(path, model, lambda partial: train_video_jepa(
        config, make_clips(config, train_digits), partial, device=device, step=step, **options),
        identity(config, train_digits, step), shipped)


def fit_decoder(model: VideoJEPA, clips: torch.Tensor, steps: int = 200, batch_size: int = 32,
                lr: float = 1e-3, seed: int = 0) -> torch.nn.Sequential:
    """A ``frame_decoder`` fitted on frozen latents of uint8 ``clips (N, T, 1, 64, 64)``,
    for pictures only: frames ``torch.sigmoid(decoder(z))`` of ``z (N, C, S, S)``."""
    check_clips(clips, 1)
    model.eval()
    device = next(model.parameters()).device
    generator = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    decoder = frame_decoder(model.config.latent_channels, model.config.latent_side).to(device)
    optimizer = torch.optim.Adam(decoder.parameters(), lr=lr)
    frames = clips.flatten(0, 1)  # (N*T, 1, 64, 64)
    for _ in range(steps):
        batch = frames[torch.randint(0, len(frames), (batch_size,), generator=generator)]
        batch = batch[:, None].to(device)  # (B, 1, 1, 64, 64): clips of one frame
        with torch.no_grad():
            z = model.encode(batch)[:, 0]
        loss = F.binary_cross_entropy_with_logits(decoder(z), batch[:, 0].float() / 255)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    return decoder.eval()


def ablation_configs(config: VideoJEPAConfig, rollout_steps=(1, 2, 4), seeds=(0, 1, 2)):
    """``config`` with every ``K`` in ``rollout_steps`` and every seed (clips and weights)."""
    return [replace(config, rollout_steps=k, seed=s) for k in rollout_steps for s in seeds]
