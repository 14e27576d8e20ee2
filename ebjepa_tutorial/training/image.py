"""Image JEPA on CIFAR-10 (notebooks 01, VICReg, and 02, SIGReg): two views of each image
through one encoder and a projector, and a regulariser against collapse; the encoder is kept."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from .. import augment, distributed
from ..losses.sigreg import sigreg_loss
from ..losses.vicreg import vicreg, vicreg_loss
from ..models.encoders import ResNet18, build_projector
from ..utils import at_least_float32, memory_format, mixed_precision
from .checkpoints import checkpoint_paths, run_identity, step_identity
from .loop import History, load_or_train, run_steps, step_generator
from .optim import split_decay_params, warmup_cosine_scheduler

LOG_EVERY, CHECKPOINT_EVERY = 10, 250  # steps between the history's rows, and between saves
WEIGHT_DECAY = 1e-4  # AdamW's, on weight matrices only (optim.split_decay_params)
LR = 2e-3  # AdamW's peak rate (warm-up, then cosine to 0), the same at every scale


@dataclass(frozen=True)
class VICReg:
    """VICReg's weights. The two views' regularisers are averaged (losses.vicreg_loss) where
    the reference code adds them, so its 1 / 1 / 80 reads 1 / 2 / 160 here."""

    inv_coeff: float = 1.0
    std_coeff: float = 2.0
    cov_coeff: float = 160.0


@dataclass(frozen=True)
class SIGReg:
    """Invariance + ``lam`` x SIGReg on ``slices`` random directions; ``scale_by_n``: the
    statistic times N, as LeJEPA (False: the paper's, with a lambda N times larger)."""

    lam: float = 0.1
    slices: int = 256
    scale_by_n: bool = True


@dataclass(frozen=True)
class ImageJEPAConfig:
    """One training run (``course.presets`` holds each scale's). The defaults, an earlier
    recipe, stay as they are: a stored identity leaves out the fields that equal them."""

    loss: VICReg | SIGReg | None = VICReg()  # None: invariance alone (no regulariser: collapses)
    widths: tuple[int, int, int, int] = (16, 32, 64, 128)  # ResNet stage widths
    blocks_per_stage: int = 2  # BasicBlocks per ResNet stage: 2 is ResNet-18, 1 is ResNet-10
    image_size: int = 16  # training views are this many pixels wide
    eval_image_size: int = 32  # the side of the images the probes see (32: CIFAR-10's own)
    projector: tuple[int, int] | None = (1024, 1024)  # (hidden, output); None: no projector
    batch_size: int = 256  # the global batch: per-process batch x processes under torchrun
    steps: int = 2000
    warmup_steps: int = 200  # linear warm-up from step 0 to LR, then cosine to 0
    seed: int = 0

    def __post_init__(self):
        if not self.steps >= 1:  # else the warm-up's bound below would be blamed
            raise ValueError(f"ImageJEPAConfig.steps must be an int >= 1, got {self.steps}")
        if not 0 <= self.warmup_steps < self.steps:
            raise ValueError(f"ImageJEPAConfig.warmup_steps must be an int in 0..steps-1 = "
                             f"{self.steps - 1}, got {self.warmup_steps}")

    @property
    def method(self) -> str:
        """``"vicreg"``, ``"sigreg"`` or ``"invariance"``: the loss, in one word."""
        return type(self.loss).__name__.lower() if self.loss is not None else "invariance"


class ImageJEPA(nn.Module):
    """Encoder followed by a projector: ``(B, 3, S, S) -> (B, D_out)``; ``.encoder`` is kept."""

    def __init__(self, config: ImageJEPAConfig):
        super().__init__()
        self.encoder = ResNet18(config.widths, blocks_per_stage=config.blocks_per_stage)
        hidden, out = config.projector or (0, 0)
        depth = 3 if config.projector is not None else 0
        self.projector = build_projector(self.encoder.out_dim, hidden, out, depth=depth)

    def forward(self, views: torch.Tensor) -> torch.Tensor:
        return self.projector(self.encoder(views))


class AllViews(nn.Module):
    """``model`` on every view in one call, as DDP needs: ``(b, 3, S, S) x V -> (b, D) x V``,
    each view its own pass, so batch norm sees its batch."""

    def __init__(self, model: nn.Module):
        super().__init__()
        self.model = model

    def forward(self, *views: torch.Tensor) -> tuple[torch.Tensor, ...]:
        return tuple(self.model(view) for view in views)


def resize(images: torch.Tensor, size: int) -> torch.Tensor:
    """Normalise uint8 images ``(B, 3, 32, 32)`` and resize them to ``size`` (antialiased)."""
    images = augment.normalize(images)
    if images.shape[-1] == size:
        return images
    return F.interpolate(images, size=size, mode="bilinear", antialias=True, align_corners=False)


def embed(net: nn.Module, views) -> tuple[torch.Tensor, torch.Tensor]:
    """Both views ``(b, 3, S, S)`` through ``net``: ``(B, D)`` each, float32, every rank's rows."""
    with mixed_precision(views[0].device, cpu=True):
        embedded = net(*views)
    return tuple(distributed.gather_rows(at_least_float32(z)) for z in embedded)


def vicreg_step(net, batch, optimizer, scheduler, weights):
    """One VICReg step (notebook 01): returns the loss and a function giving its terms."""
    views, _ = batch  # two augmented views of the step's images: (b, 3, S, S) each
    z_a, z_b = embed(net, views)  # encoder, then projector: (B, D) each
    loss = vicreg(z_a, z_b, weights.inv_coeff, weights.std_coeff, weights.cov_coeff)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    scheduler.step()
    return loss.detach(), lambda: vicreg_loss(z_a.detach(), z_b.detach())[1]  # the terms


def sigreg_step(net, batch, optimizer, scheduler, weights):
    """:func:`vicreg_step` with SIGReg's loss (notebook 02), terms as a dict; weights: SIGReg."""
    views, generator = batch  # two augmented views: (b, 3, S, S) each; the step's generator
    z_a, z_b = embed(net, views)  # encoder, then projector: (B, D) each
    loss, terms = sigreg_loss(z_a, z_b, weights.lam, weights.slices, generator,
                              weights.scale_by_n)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    scheduler.step()
    return loss.detach(), terms


def package_step(config: ImageJEPAConfig):
    """The step that trains ``config`` when none is passed."""
    return sigreg_step if isinstance(config.loss, SIGReg) else vicreg_step


def train_image_jepa(config: ImageJEPAConfig, images: torch.Tensor,
                     checkpoint: str | Path | None = None, device: torch.device | str = "cpu",
                     progress: bool = True, step=None) -> tuple[ImageJEPA, History]:
    """``(model, history)`` trained on uint8 ``images (N, 3, 32, 32)``, resumable from a file."""
    torch.manual_seed(config.seed)
    # channels_last on a GPU; on the CPU it is faster but two identical runs then differ
    layout = memory_format(device)
    model = ImageJEPA(config).to(device, memory_format=layout)
    net = distributed.data_parallel(AllViews(model), device)
    optimizer = torch.optim.AdamW(split_decay_params(model, WEIGHT_DECAY), lr=LR)
    scheduler = warmup_cosine_scheduler(optimizer, config.steps, config.warmup_steps)
    run = identity(config, step=step)
    step = package_step(config) if step is None else step
    weights = VICReg(1.0, 0.0, 0.0) if config.loss is None else config.loss  # no regulariser
    images = images.to(device)  # CIFAR-10 stays on the GPU (150 MB)
    pipeline = augment.build_augmentation(augment.AugmentConfig(size=config.image_size))

    def batch(n: int):  # step n's two views of this process's rows, and its generator
        generator = step_generator(config.seed, n)
        index = torch.randint(0, len(images), (config.batch_size,), generator=generator)
        views = augment.two_views(images[index.to(images.device)], pipeline, generator)
        views = [distributed.local_rows(v).contiguous(memory_format=layout) for v in views]
        return views, generator

    model.train()
    history = run_steps(
        lambda views, i: step(net, views, optimizer, scheduler, weights), batch, config.steps,
        log_every=LOG_EVERY, desc=f"{config.method} training", progress=progress,
        checkpoint=checkpoint, parts=(model, optimizer, scheduler), identity=run,
        every=CHECKPOINT_EVERY)
    return model, history


def identity(config: ImageJEPAConfig, encoder_only: bool = False, step=None) -> dict:
    """The run's :func:`run_identity` without ``eval_image_size``: probing is not training."""
    extra = {"weights": "encoder only"} if encoder_only else {}
    # the rate stays recorded as when it was a field: the shipped files keep loading
    stored = run_identity(config, ("loss", "steps", "batch_size", "seed"), lr=LR, **extra,
                          **step_identity(step, package_step(config)))
    return {k: v for k, v in stored.items() if k != "eval_image_size"}


def train_or_load(config: ImageJEPAConfig, name: str, images: torch.Tensor, device="cpu",
                  encoder_only: bool = False, step=None):
    """``(model in eval mode, history)`` of ``config``: loaded if saved as ``name``, else trained
    on uint8 ``images (N, 3, 32, 32)`` and saved. ``encoder_only``: as the long runs ship."""
    torch.manual_seed(config.seed)
    model = ImageJEPA(config)
    module = (model.encoder if encoder_only else model).to(device)

    def train(partial: Path):
        if not torch.is_tensor(images):  # None, or the (images, labels) pair
            raise ValueError(f"no saved run {name!r} of this configuration, and no image tensor "
                             f"to train it on (got {type(images).__name__}): pass "
                             "load_cifar10('train')[0], the images without their labels")
        trained, history = train_image_jepa(config, images, partial, device, step=step)
        return (trained.encoder if encoder_only else trained), history

    path, shipped = checkpoint_paths(name)
    return load_or_train(path, module, train, identity(config, encoder_only, step), shipped)
