"""Video JEPA on Moving MNIST (notebook 03): the runs' configs, the course's step and a run's
identity; the loop that repeats the step is written in the notebook. A step,
:func:`video_jepa_step`, takes the K-step loss plus the variance and covariance of the
projected latents (each location a sample):

    L = (1/K) sum_k mean over elements (zhat_k - z)^2 + std v(P(Z)) + cov c(P(Z))
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field, replace

import torch

from .. import distributed
from ..data.moving_mnist import generate_moving_mnist
from ..losses.rollout import UNROLLS, parallel_rollout_loss, rollout_loss
from ..models.video import VIDEO_MODEL_CONFIGS, VideoModelConfig
from ..utils import at_least_float32, mixed_precision
from .checkpoints import run_identity, step_identity

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


def ablation_configs(config: VideoJEPAConfig, rollout_steps=(1, 2, 4), seeds=(0, 1, 2)):
    """``config`` with every ``K`` in ``rollout_steps`` and every seed (clips and weights)."""
    return [replace(config, rollout_steps=k, seed=s) for k in rollout_steps for s in seeds]
