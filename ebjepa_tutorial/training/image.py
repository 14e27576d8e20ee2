"""Image JEPA on CIFAR-10: the training recipe of notebooks 01 (VICReg) and 02 (SIGReg).

Two augmented views of each image go through one encoder and a projector;
the energy of a pair is the squared distance between the two embeddings
(the predictor is the identity), and a regulariser keeps the embeddings from
collapsing: VICReg's variance and covariance terms, or SIGReg.

The encoder is what we keep; the projector exists only for training. Quality
is measured with a linear probe and a kNN classifier on frozen encoder
features of un-augmented images (see :mod:`ebjepa_tutorial.evaluation.classify`), at
their own size: ``eval_image_size``, 32 px (CIFAR-10's native size) by
default, whatever size the training views had. The ResNet ends in a global
average pool, so one network takes images of any size.

Several processes (``torchrun``, see :mod:`ebjepa_tutorial.distributed`): the
config's ``batch_size`` is the global batch, and global batch = per-rank batch x
world size. Every rank draws and augments the same global batch (seeded by the
step) and keeps its own rows, so the data, the views and SIGReg's directions do
not depend on the world size (at the price of augmenting the whole batch on
every rank); the regularisers see the global batch. Batch norm normalises over
each rank's rows, unless ``sync_batchnorm`` (GPUs only).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from .. import augment, distributed, losses
from ..losses import sigreg
from ..models.encoders import ENCODERS, build_encoder
from ..models.heads import build_projector
from ..utils import (
    at_least_float32,
    check_fields,
    is_int_at_least,
    is_non_negative,
    is_positive,
    memory_format,
    mixed_precision,
)
from .checkpoints import checkpoint_paths, run_identity
from .loop import History, fit, load_or_train, resume, step_generator
from .optim import LARS, split_decay_params, warmup_cosine_scheduler

LOSSES = ("vicreg", "sigreg", "invariance")
EVAL_FIELDS = ("eval_image_size",)  # how a run is scored, not how it is trained
LOCAL_FIELDS = ("local_views", "local_size", "local_crop_scale")  # multi-crop's


@dataclass(frozen=True)
class ImageJEPAConfig:
    """Everything that defines a training run. Defaults: the class-scale VICReg run."""

    loss: str = "vicreg"  # "vicreg", "sigreg", or "invariance" (no regulariser: collapses)
    encoder: str = "resnet18"  # or "vit_s"
    widths: tuple[int, int, int, int] = (16, 32, 64, 128)  # ResNet stage widths
    blocks_per_stage: int = 2  # BasicBlocks per ResNet stage: 2 is ResNet-18, 1 is ResNet-10
    image_size: int = 16  # training views are this many pixels wide
    # multi-crop: this many more views of each image, smaller crops of local_crop_scale of its
    # area at local_size px, pulled towards the two global views (0: two views)
    local_views: int = 0
    local_size: int = 8
    local_crop_scale: tuple[float, float] = (0.05, 0.3)
    # The linear probe and kNN see un-augmented images at this side; CIFAR-10 is 32 px
    # natively, so 32 means no resizing.
    eval_image_size: int = 32
    projector: tuple[int, int] | None = (1024, 1024)  # (hidden, output); None: no projector
    batch_size: int = 256  # the global batch: per-rank batch x world size under torchrun
    steps: int = 2000
    warmup_steps: int = 200  # linear warm-up from step 0, then cosine to 0
    optimizer: str = "adamw"  # "adamw" (CPU scales) or "lars" (the paper's)
    lr: float = 2e-3
    weight_decay: float = 1e-4
    # VICReg weights, covariance averaged over D(D-1) entries as in the EB-JEPA paper, but
    # the two views' regularisers averaged (losses.vicreg_loss), where the papers add them:
    # the paper's 1 / 1 / 80 reads 1 / 2 / 160 here (the results page compares the two).
    inv_coeff: float = 1.0
    std_coeff: float = 2.0
    cov_coeff: float = 160.0
    sigreg_lambda: float = 0.1  # SIGReg weight ...
    sigreg_scale_by_n: bool = True  # ... on the statistic times N (LeJEPA); False: the paper's
    sigreg_slices: int = 256
    seed: int = 0

    def __post_init__(self):
        if self.loss not in LOSSES:
            raise ValueError(f"unknown loss {self.loss!r}; choose one of {', '.join(LOSSES)}")
        if self.optimizer not in ("adamw", "lars"):
            raise ValueError(f"unknown optimizer {self.optimizer!r}; choose 'adamw' or 'lars'")
        if self.encoder not in ENCODERS:
            raise ValueError(f"unknown encoder {self.encoder!r}; choose one of "
                             f"{', '.join(sorted(ENCODERS))}")
        pixels = (is_int_at_least(1), "a positive int (pixels per side)")
        positive, non_negative = (is_positive, "a number > 0"), (is_non_negative, "a number >= 0")
        check_fields(self, {
            "steps": (is_int_at_least(1), "an int >= 1"),
            "warmup_steps": (lambda w: is_int_at_least(0)(w) and w < self.steps,
                             f"an int in 0..steps-1 = {self.steps - 1}"),
            "batch_size": (is_int_at_least(2), "an int >= 2 (a batch of one has no variance)"),
            "image_size": pixels, "eval_image_size": pixels, "local_size": pixels,
            "local_views": (is_int_at_least(0), "an int >= 0 (0: two views, no multi-crop)"),
            "local_crop_scale": (lambda c: len(c) == 2 and 0 < c[0] <= c[1] <= 1,
                                 "two area fractions 0 < low <= high <= 1"),
            "widths": (lambda w: len(w) == 4 and all(map(is_int_at_least(1), w)),
                       "four positive ints (the ResNet stage widths)"),
            "blocks_per_stage": (is_int_at_least(1), "an int >= 1 (2: ResNet-18, 1: ResNet-10)"),
            "projector": (lambda p: p is None or (len(p) == 2 and all(map(is_int_at_least(1), p))),
                          "None or two positive ints (hidden, output)"),
            "lr": positive, "weight_decay": non_negative, "inv_coeff": non_negative,
            "std_coeff": non_negative, "cov_coeff": non_negative, "sigreg_lambda": non_negative,
            "sigreg_slices": (is_int_at_least(1), "an int >= 1 (random directions)"),
        })
        if self.encoder == "vit_s" and self.eval_image_size != self.image_size:
            raise ValueError(
                f"a ViT is built for one image size: eval_image_size ({self.eval_image_size}) "
                f"must equal image_size ({self.image_size}) with encoder='vit_s'")
        if self.encoder == "vit_s" and self.local_views and self.local_size != self.image_size:
            raise ValueError(
                f"a ViT is built for one image size: local_size ({self.local_size}) must equal "
                f"image_size ({self.image_size}) with encoder='vit_s' and local views")


class ImageJEPA(nn.Module):
    """Encoder followed by a projector: ``(B, 3, S, S) -> (B, D_out)``; ``.encoder`` is kept."""

    def __init__(self, config: ImageJEPAConfig):
        super().__init__()
        kwargs = ({"widths": config.widths, "blocks_per_stage": config.blocks_per_stage}
                  if config.encoder == "resnet18" else {"image_size": config.image_size})
        self.encoder = build_encoder(config.encoder, **kwargs)
        hidden, out = config.projector if config.projector is not None else (0, 0)
        depth = 3 if config.projector is not None else 0
        self.projector = build_projector(self.encoder.out_dim, hidden, out, depth=depth)

    def forward(self, views: torch.Tensor) -> torch.Tensor:
        return self.projector(self.encoder(views))


class AllViews(nn.Module):
    """``model`` on every view in one call: ``(b, 3, S_v, S_v) x V -> (b, D) x V``.

    DistributedDataParallel pairs each forward call with one backward, so the
    views must go through a single call of the wrapped module. Each view is its own
    forward pass, so batch norm normalises each view's batch, as with one view.
    """

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


def jepa_loss(config: ImageJEPAConfig, z_a, z_b, generator=None, across_ranks=False,
              local=()):
    """The training loss of two embedded views ``(B, D)``: returns ``(loss, terms)``.

    ``across_ranks``: the regulariser sees the global batch of all ranks (a no-op in
    one process); see :func:`losses.vicreg_loss` and :func:`sigreg.sigreg_loss`.
    ``local``: the embedded local views of multi-crop, each ``(B, D)``.
    """
    if config.loss == "vicreg":
        return losses.vicreg_loss(z_a, z_b, config.inv_coeff, config.std_coeff, config.cov_coeff,
                                  across_ranks=across_ranks, local=local)
    if config.loss == "sigreg":
        return sigreg.sigreg_loss(z_a, z_b, lam=config.sigreg_lambda,
                                  num_slices=config.sigreg_slices, generator=generator,
                                  scale_by_n=config.sigreg_scale_by_n, across_ranks=across_ranks,
                                  local=local)
    invariance = losses.multi_view_invariance(z_a, z_b, local)
    return invariance, {"invariance": invariance.detach()}


def view_maker(config: ImageJEPAConfig):
    """``views(images, generator)``: two global views of uint8 ``images`` ``(B, 3, 32, 32)`` at
    ``image_size``, then ``local_views`` smaller ones at ``local_size``, a list of
    ``(B, 3, S_v, S_v)``. The augmentations are built once, here."""
    local = augment.AugmentConfig(size=config.local_size, crop_scale=config.local_crop_scale)
    global_pipeline = augment.build_augmentation(augment.AugmentConfig(size=config.image_size))
    local_pipeline = augment.build_augmentation(local)

    def views(images: torch.Tensor, generator: torch.Generator) -> list[torch.Tensor]:
        return [*augment.two_views(images, global_pipeline, generator),
                *(augment.augment(images, local_pipeline, generator)
                  for _ in range(config.local_views))]

    return views


def make_optimizer(model: nn.Module, config: ImageJEPAConfig):
    """AdamW or LARS, with biases and norm parameters excluded from weight decay."""
    if config.optimizer == "lars":
        return LARS(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    groups = split_decay_params(model, config.weight_decay)
    return torch.optim.AdamW(groups, lr=config.lr)


def train_image_jepa(
    config: ImageJEPAConfig,
    images: torch.Tensor,
    checkpoint: str | Path | None = None,
    device: torch.device | str = "cpu",
    progress: bool = True,
    checkpoint_every: int = 250,
    sync_batchnorm: bool = False,
) -> tuple[ImageJEPA, History]:
    """Train on uint8 ``images`` ``(N, 3, 32, 32)``; resume from ``checkpoint`` if it exists.

    Batch ``step`` (indices and augmentations) is drawn from a generator seeded
    with ``(seed, step)``, so a resumed run matches an uninterrupted one.

    Inside a process group (``torchrun``) it trains with DistributedDataParallel:
    ``config.batch_size`` is the global batch, and global batch = per-rank batch x
    world size (a world size that does not divide it is refused). Rank 0 alone
    writes ``checkpoint``, which resumes on any world size. ``sync_batchnorm``
    (off by default; GPUs only) normalises over the global batch, not each rank's.
    """
    distributed.per_rank_batch(config.batch_size)  # refuses an uneven split before any work
    torch.manual_seed(config.seed)
    # channels_last on a GPU; on the CPU it is faster but two identical runs then differ
    layout = memory_format(device)
    model = ImageJEPA(config).to(device, memory_format=layout)
    net = distributed.data_parallel(AllViews(model), device, sync_batchnorm)
    optimizer = make_optimizer(model, config)
    scheduler = warmup_cosine_scheduler(optimizer, config.steps, config.warmup_steps)
    make_views = view_maker(config)
    start, history = (0, History())
    if checkpoint is not None:
        start, history = resume(checkpoint, model, optimizer, scheduler, identity(config))

    images = images.to(device)  # CIFAR-10 is 150 MB as uint8: it stays on the GPU

    def batch(step: int):
        generator = step_generator(config.seed, step)
        index = torch.randint(0, len(images), (config.batch_size,), generator=generator)
        views = make_views(images[index.to(images.device)], generator)
        # every rank made the same global batch; each keeps its rows (all of them on one)
        views = (distributed.local_rows(v).contiguous(memory_format=layout) for v in views)
        return tuple(views), generator

    def loss(views_and_generator):
        views, generator = views_and_generator
        # bf16 networks on a GPU or a CPU with bf16 instructions; the loss in float32
        with mixed_precision(device, cpu=True):
            embedded = net(*views)
        z_a, z_b, *local = map(at_least_float32, embedded)
        return jepa_loss(config, z_a, z_b, generator, across_ranks=True, local=local)

    fit(model, optimizer, loss, batch, config.steps, scheduler=scheduler, history=history,
        start_step=start, checkpoint=checkpoint, checkpoint_every=checkpoint_every, log_every=10,
        desc=f"{config.loss} training", progress=progress, config=identity(config))
    return model, history


def seconds_per_step(config: ImageJEPAConfig, images: torch.Tensor, steps: int = 5,
                     device: torch.device | str = "cpu") -> float:
    """Wall time of one training step of ``config`` on this machine, in seconds.

    Times a run of ``1 + steps`` steps and one of 1 step and divides the
    difference by ``steps``: building the model and the first (slower) step
    cancel out. A 1-step run before both pays the process's one-time costs
    (without it, the first call reads low).
    Turns a number of steps into minutes on the machine at hand.
    """
    def run(n: int) -> float:
        start = time.perf_counter()
        train_image_jepa(replace(config, steps=n, warmup_steps=0), images, device=device,
                         progress=False)
        return time.perf_counter() - start

    run(1)
    first = run(1)
    return max(run(1 + steps) - first, 0.0) / steps


# fields added after runs were stored, with the value those runs had
_ADDED_LATER = {"blocks_per_stage": 2}


def _unused_fields(config: ImageJEPAConfig) -> tuple[str, ...]:
    # a two-view ResNet-18 run reads as it did before multi-crop and the block count
    # existed, so its stored files still match
    unused = () if config.local_views else LOCAL_FIELDS
    return unused + tuple(k for k, v in _ADDED_LATER.items() if getattr(config, k) == v)


def settings(config: ImageJEPAConfig) -> dict:
    """``config`` as a dict, without multi-crop's fields when it is off (``local_views`` 0)."""
    return {k: v for k, v in asdict(config).items() if k not in _unused_fields(config)}


def identity(config: ImageJEPAConfig, encoder_only: bool = False) -> dict:
    """What a checkpoint stores to recognise its run: the config without ``EVAL_FIELDS``
    (and without multi-crop's fields when it is off).

    How a network will be probed does not change how it is trained. A file of
    the encoder alone is marked, so it is never read as a whole model.
    """
    stored = run_identity(config, **({"weights": "encoder only"} if encoder_only else {}))
    return {k: v for k, v in stored.items() if k not in EVAL_FIELDS + _unused_fields(config)}


def _partial(name: str) -> Path:
    """Where the run ``name`` saves its resumable state while it trains (in the cache)."""
    return checkpoint_paths(name)[0].with_suffix(".partial")


def _train_into(module: nn.Module, config, images, name: str, device, keep) -> History:
    """Train ``config`` (resumable from ``<name>.partial``); copy ``keep(model)`` to ``module``."""
    trained, history = train_image_jepa(config, images, checkpoint=_partial(name), device=device)
    module.load_state_dict(keep(trained).state_dict())
    return history  # load_or_train deletes the partial file once the model is saved


def train_or_load(config: ImageJEPAConfig, name: str, images: torch.Tensor, device="cpu",
                  encoder_only: bool = False):
    """The model of ``config``: loaded if this run was saved, else trained on ``images``.

    Looks for ``checkpoints/<name>.pt`` (shipped with the course), then
    ``data/cache/checkpoints/<name>.pt``; otherwise trains on uint8 ``images``
    ``(N, 3, 32, 32)`` (resumable from ``<name>.partial`` in the cache) and
    saves. With ``encoder_only`` it keeps and stores the encoder alone, as the
    longer shipped runs are (the projector is three quarters of the weights at
    class scale, and only training needs it). Returns ``(model or encoder in eval
    mode, history)``.
    """
    torch.manual_seed(config.seed)
    model = ImageJEPA(config)
    module = (model.encoder if encoder_only else model).to(device)
    keep = (lambda m: m.encoder) if encoder_only else (lambda m: m)
    cache_path, shipped = checkpoint_paths(name)
    history = load_or_train(cache_path, module, lambda: _train_into(
        module, config, images, name, device, keep), identity(config, encoder_only), shipped,
        partial=_partial(name))
    return module.eval(), history
