"""Image JEPA on CIFAR-10: the training recipe of notebooks 01 (VICReg) and 02 (SIGReg).

Two augmented views of each image go through one encoder and a projector;
the energy of a pair is the squared distance between the two embeddings
(the predictor is the identity), and a regulariser keeps the embeddings from
collapsing: VICReg's variance and covariance terms, or SIGReg.

The encoder is what we keep; the projector exists only for training. Quality
is measured with a linear probe and a kNN classifier on frozen encoder
features of un-augmented images (:mod:`ebjepa_tutorial.evaluation.classify`) at
``eval_image_size``, whatever size the training views had: the ResNet ends in a
global average pool, so one network takes images of any size.

Several processes (``torchrun``, :mod:`ebjepa_tutorial.distributed`): ``batch_size`` is
the global batch, and global batch = per-rank batch x world size. Every rank draws and
augments the same global batch (seeded by the step) and keeps its own rows, then gathers
every rank's embeddings before the loss, which thus sees the global batch as in one process.
Batch norm normalises over each rank's rows, unless ``sync_batchnorm`` (GPUs only).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from .. import augment, distributed, losses
from ..losses.sigreg import sigreg_loss
from ..losses.vicreg import vicreg, vicreg_terms
from ..models.encoders import ResNet18
from ..models.heads import build_projector
from ..utils import (
    at_least_float32,
    check_fields,
    is_int_at_least,
    is_non_negative,
    memory_format,
    mixed_precision,
)
from .checkpoints import checkpoint_paths, run_identity, step_identity
from .loop import (
    History,
    load_or_train,
    resume,
    run_steps,
    saver,
    step_generator,
    training_state,
)
from .optim import split_decay_params, warmup_cosine_scheduler

EVAL_FIELDS = ("eval_image_size",)  # how a run is scored, not how it is trained
LOG_EVERY = 10  # steps between the history's rows: reading a value waits for the GPU
WEIGHT_DECAY = 1e-4  # AdamW's, on weight matrices only (optim.split_decay_params)
LR = 2e-3  # AdamW's peak rate (warm-up, then cosine to 0), the same at every scale


@dataclass(frozen=True)
class VICReg:
    """VICReg's weights: covariance averaged over D(D-1) entries as in the EB-JEPA paper, but
    the two views' regularisers averaged (losses.vicreg_loss) where the papers add them: the
    paper's 1 / 1 / 80 reads 1 / 2 / 160 here (the results page compares the two)."""

    inv_coeff: float = 1.0
    std_coeff: float = 2.0
    cov_coeff: float = 160.0

    def __post_init__(self):
        check_fields(self, {name: (is_non_negative, "a number >= 0")
                            for name in ("inv_coeff", "std_coeff", "cov_coeff")})

    def __call__(self, z_a, z_b, generator=None):
        return losses.vicreg_loss(z_a, z_b, self.inv_coeff, self.std_coeff, self.cov_coeff)


@dataclass(frozen=True)
class SIGReg:
    """Invariance + ``lam`` x SIGReg on ``slices`` random directions a step; ``scale_by_n``:
    the statistic times N, as LeJEPA (False: the paper's, with a lambda N times larger)."""

    lam: float = 0.1
    slices: int = 256
    scale_by_n: bool = True

    def __post_init__(self):
        check_fields(self, {"lam": (is_non_negative, "a number >= 0"),
                            "slices": (is_int_at_least(1), "an int >= 1 (random directions)")})

    def __call__(self, z_a, z_b, generator=None):
        return sigreg_loss(z_a, z_b, self.lam, self.slices, generator, self.scale_by_n)


@dataclass(frozen=True)
class ImageJEPAConfig:
    """Everything that defines a training run. Defaults: the class-scale VICReg run."""

    loss: VICReg | SIGReg | None = VICReg()  # None: invariance alone (no regulariser: collapses)
    widths: tuple[int, int, int, int] = (16, 32, 64, 128)  # ResNet stage widths
    blocks_per_stage: int = 2  # BasicBlocks per ResNet stage: 2 is ResNet-18, 1 is ResNet-10
    image_size: int = 16  # training views are this many pixels wide
    # the linear probe and kNN see un-augmented images at this side (32: CIFAR-10's own)
    eval_image_size: int = 32
    projector: tuple[int, int] | None = (1024, 1024)  # (hidden, output); None: no projector
    batch_size: int = 256  # the global batch: per-rank batch x world size under torchrun
    steps: int = 2000
    warmup_steps: int = 200  # linear warm-up from step 0 to LR, then cosine to 0
    seed: int = 0

    def __post_init__(self):
        if not (self.loss is None or isinstance(self.loss, (VICReg, SIGReg))):
            raise ValueError(f"ImageJEPAConfig.loss must be VICReg(...), SIGReg(...) or None "
                             f"(invariance alone), got {self.loss!r}")
        pixels = (is_int_at_least(1), "a positive int (pixels per side)")
        check_fields(self, {
            "steps": (is_int_at_least(1), "an int >= 1"),
            "warmup_steps": (lambda w: is_int_at_least(0)(w) and w < self.steps,
                             f"an int in 0..steps-1 = {self.steps - 1}"),
            "batch_size": (is_int_at_least(2), "an int >= 2 (a batch of one has no variance)"),
            "image_size": pixels, "eval_image_size": pixels,
            "widths": (lambda w: len(w) == 4 and all(map(is_int_at_least(1), w)),
                       "four positive ints (the ResNet stage widths)"),
            "blocks_per_stage": (is_int_at_least(1), "an int >= 1 (2: ResNet-18, 1: ResNet-10)"),
            "projector": (lambda p: p is None or (len(p) == 2 and all(map(is_int_at_least(1), p))),
                          "None or two positive ints (hidden, output)"),
        })

    @property
    def method(self) -> str:
        """``"vicreg"``, ``"sigreg"`` or ``"invariance"``: the loss, in one word."""
        return type(self.loss).__name__.lower() if self.loss is not None else "invariance"


class ImageJEPA(nn.Module):
    """Encoder followed by a projector: ``(B, 3, S, S) -> (B, D_out)``; ``.encoder`` is kept."""

    def __init__(self, config: ImageJEPAConfig):
        super().__init__()
        self.encoder = ResNet18(config.widths, blocks_per_stage=config.blocks_per_stage)
        hidden, out = config.projector if config.projector is not None else (0, 0)
        depth = 3 if config.projector is not None else 0
        self.projector = build_projector(self.encoder.out_dim, hidden, out, depth=depth)

    def forward(self, views: torch.Tensor) -> torch.Tensor:
        return self.projector(self.encoder(views))


class AllViews(nn.Module):
    """``model`` on every view in one call: ``(b, 3, S, S) x V -> (b, D) x V``.

    DistributedDataParallel pairs each forward call with one backward, so the views must go
    through a single call of the wrapped module. Each view is its own forward pass, so batch
    norm normalises each view's batch, as with one view.
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


def jepa_loss(config: ImageJEPAConfig, z_a, z_b, generator=None):
    """The training loss of two embedded views ``(B, D)``: returns ``(loss, terms)``."""
    if config.loss is not None:
        return config.loss(z_a, z_b, generator)
    invariance = losses.invariance_term(z_a, z_b)
    return invariance, {"invariance": invariance.detach()}


def make_optimizer(model: nn.Module, config: ImageJEPAConfig) -> torch.optim.AdamW:
    """AdamW at :data:`LR`, with biases and norm parameters excluded from weight decay."""
    return torch.optim.AdamW(split_decay_params(model, WEIGHT_DECAY), lr=LR)


def embed(net: nn.Module, views) -> tuple[torch.Tensor, torch.Tensor]:
    """Both views ``(b, 3, S, S)`` through ``net`` (encoder, then projector): ``(B, D)`` each.

    The networks run in bf16 where that is fast (:func:`mixed_precision`), the loss gets
    float32; under ``torchrun`` every rank's rows are gathered, so the loss sees the global
    batch (gradients reach each rank's own rows).
    """
    with mixed_precision(views[0].device, cpu=True):
        embedded = net(*views)
    z_a, z_b = (distributed.gather_rows(at_least_float32(z)) for z in embedded)
    return z_a, z_b


def vicreg_step(net, batch, optimizer, scheduler, weights):
    """One VICReg training step (notebook 01 shows it; tests/test_one_source.py keeps the two
    the same). ``batch``: the step's two views and generator; ``weights``: a :class:`VICReg`.
    Returns the loss and, for the steps the loop logs, a function giving the unweighted terms.
    """
    views, _ = batch  # two augmented views of the step's images: (b, 3, S, S) each
    z_a, z_b = embed(net, views)  # encoder, then projector: (B, D) each
    loss = vicreg(z_a, z_b, weights.inv_coeff, weights.std_coeff, weights.cov_coeff)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    scheduler.step()
    return loss.detach(), lambda: vicreg_terms(z_a.detach(), z_b.detach())


def sigreg_step(net, batch, optimizer, scheduler, weights):
    """One SIGReg training step (notebook 02 shows it): :func:`vicreg_step` with SIGReg's
    loss. ``weights``: a :class:`SIGReg`; the directions are drawn from the step's generator."""
    views, generator = batch  # two augmented views: (b, 3, S, S) each; the step's generator
    z_a, z_b = embed(net, views)  # encoder, then projector: (B, D) each
    loss, terms = sigreg_loss(z_a, z_b, weights.lam, weights.slices, generator,
                              weights.scale_by_n)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    optimizer.step()
    scheduler.step()
    return loss.detach(), terms


INVARIANCE_ONLY = VICReg(1.0, 0.0, 0.0)  # the step of ``loss=None``: no regulariser


def package_step(config: ImageJEPAConfig):
    """The step that trains ``config`` when none is passed: :func:`sigreg_step` for SIGReg,
    else :func:`vicreg_step` (``loss=None``: with :data:`INVARIANCE_ONLY`'s weights)."""
    return sigreg_step if isinstance(config.loss, SIGReg) else vicreg_step


def train_image_jepa(config: ImageJEPAConfig, images: torch.Tensor,
                     checkpoint: str | Path | None = None, device: torch.device | str = "cpu",
                     progress: bool = True, checkpoint_every: int = 250,
                     sync_batchnorm: bool = False, step=None) -> tuple[ImageJEPA, History]:
    """Train on uint8 ``images (N, 3, 32, 32)``, each update a ``step(net, batch, optimizer,
    scheduler, weights)`` (default :func:`package_step`; notebooks 01 and 02 pass their
    cell's); resume from ``checkpoint``. Batches come from generators seeded by ``(seed,
    step)``, so a resumed run sees the same ones. Under ``torchrun`` it trains with DDP:
    ``config.batch_size`` is the global batch (global batch = per-rank batch x world size),
    rank 0 alone writes ``checkpoint``, and ``sync_batchnorm`` (GPUs only) normalises over the
    global batch.
    """
    distributed.per_rank_batch(config.batch_size)  # refuses an uneven split before any work
    torch.manual_seed(config.seed)
    # channels_last on a GPU; on the CPU it is faster but two identical runs then differ
    layout = memory_format(device)
    model = ImageJEPA(config).to(device, memory_format=layout)
    net = distributed.data_parallel(AllViews(model), device, sync_batchnorm)
    optimizer = make_optimizer(model, config)
    scheduler = warmup_cosine_scheduler(optimizer, config.steps, config.warmup_steps)
    run = identity(config, step=step)
    start, history = resume(checkpoint, model, optimizer, scheduler, run)  # (0, empty): none
    batch = _batches(config, images.to(device), layout)  # CIFAR-10 stays on the GPU (150 MB)

    def state(done: int) -> dict:  # what resume() reads back; rank 0 alone writes
        return training_state(done, run, history, model, optimizer, scheduler)

    model.train()
    step = package_step(config) if step is None else step
    weights = INVARIANCE_ONLY if config.loss is None else config.loss
    run_steps(lambda views, i: step(net, views, optimizer, scheduler, weights), batch,
              config.steps, start_step=start, history=history, log_every=LOG_EVERY,
              desc=f"{config.method} training", progress=progress,
              after=saver(checkpoint, state, config.steps, checkpoint_every))
    return model, history


def _batches(config: ImageJEPAConfig, images: torch.Tensor, layout):
    """``batch(step)``: the step's two views of this rank's rows, ``(b, 3, S, S)`` each, and
    the step's generator (SIGReg draws its directions from it)."""
    pipeline = augment.build_augmentation(augment.AugmentConfig(size=config.image_size))

    def batch(step: int):
        generator = step_generator(config.seed, step)
        index = torch.randint(0, len(images), (config.batch_size,), generator=generator)
        views = augment.two_views(images[index.to(images.device)], pipeline, generator)
        # every rank made the same global batch; each keeps its rows (all of them on one)
        views = [distributed.local_rows(v).contiguous(memory_format=layout) for v in views]
        return views, generator

    return batch


def seconds_per_step(config: ImageJEPAConfig, images: torch.Tensor, steps: int = 5,
                     device: torch.device | str = "cpu") -> float:
    """Wall time of one training step of ``config`` on this machine, in seconds.

    Times a run of ``1 + steps`` steps and one of 1 step and divides the difference by
    ``steps``: building the model and the first (slower) step cancel out. A 1-step run
    before both pays the process's one-time costs (without it, the first call reads low).
    """
    def run(n: int) -> float:
        start = time.perf_counter()
        train_image_jepa(replace(config, steps=n, warmup_steps=0), images, device=device,
                         progress=False)
        return time.perf_counter() - start

    run(1)
    first = run(1)
    return max(run(1 + steps) - first, 0.0) / steps


def identity(config: ImageJEPAConfig, encoder_only: bool = False, step=None) -> dict:
    """What a checkpoint stores to recognise its run (:func:`run_identity`), without
    ``EVAL_FIELDS``: how a network will be probed does not change how it is trained. A file
    of the encoder alone is marked, so it is never read as a whole model. A ``step`` whose
    code differs from :func:`package_step`'s (an edited cell) is another run
    (:func:`~.checkpoints.step_identity`).
    """
    always = ("loss", "steps", "batch_size", "seed")
    extra = {"weights": "encoder only"} if encoder_only else {}
    # the rate stays recorded as when it was a field: the shipped files keep loading, and
    # files of another LR would not
    stored = run_identity(config, always, lr=LR, **extra,
                          **step_identity(step, package_step(config)))
    return {k: v for k, v in stored.items() if k not in EVAL_FIELDS}


def _partial(name: str) -> Path:
    """Where the run ``name`` saves its resumable state while it trains (in the cache)."""
    return checkpoint_paths(name)[0].with_suffix(".partial")


def _train_into(module: nn.Module, config, images, name: str, device, keep, step) -> History:
    """Train ``config`` (resumable from ``<name>.partial``); copy ``keep(model)`` to ``module``."""
    trained, history = train_image_jepa(config, images, checkpoint=_partial(name), device=device,
                                        step=step)
    module.load_state_dict(keep(trained).state_dict())
    return history  # load_or_train deletes the partial file once the model is saved


def train_or_load(config: ImageJEPAConfig, name: str, images: torch.Tensor, device="cpu",
                  encoder_only: bool = False, step=None):
    """The model of ``config``: loaded if this run was saved, else trained on ``images``.

    Looks for ``checkpoints/<name>.pt`` (shipped with the course), then
    ``data/cache/checkpoints/<name>.pt``; otherwise trains on uint8 ``images``
    ``(N, 3, 32, 32)`` (resumable from ``<name>.partial`` in the cache) and
    saves. With ``encoder_only`` it keeps and stores the encoder alone, as the
    longer shipped runs are (the projector is three quarters of the weights at
    class scale, and only training needs it). ``step``: the training step
    (:func:`train_image_jepa`); an edited one is its own run (:func:`identity`). Returns
    ``(model or encoder in eval mode, history)``.
    """
    torch.manual_seed(config.seed)
    model = ImageJEPA(config)
    module = (model.encoder if encoder_only else model).to(device)
    keep = (lambda m: m.encoder) if encoder_only else (lambda m: m)
    cache_path, shipped = checkpoint_paths(name)
    history = load_or_train(cache_path, module, lambda: _train_into(
        module, config, images, name, device, keep, step),
        identity(config, encoder_only, step), shipped, partial=_partial(name))
    return module.eval(), history
