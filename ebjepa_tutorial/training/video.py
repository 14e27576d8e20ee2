"""Video JEPA on Moving MNIST (notebook 03): the run's config, its clips, training, load-or-train.

One training step, :func:`video_jepa_step` (notebook 03 shows the same code in a cell and
can pass an edited copy as ``step``), takes the K-step loss
(:mod:`ebjepa_tutorial.losses.rollout`, unrolled the paper's parallel way or
autoregressively) plus the variance and covariance terms on projected latents (each
location of each frame is one sample), so that the latent cannot collapse:

    L = (1/K) sum_k mean ||zhat_k - z||^2 + std v(P(Z)) + cov c(P(Z))

(std = :data:`STD_COEFF`, cov = :data:`COV_COEFF`: the paper's weights, in every run)

then its gradient, the optimiser's step and the scheduler's. The class run is a curriculum:
its first half trains K = 1 (the encoder learns what to predict), its second half K steps
with orders 2..K on detached latents (the predictor learns to build on its own guesses);
the paper trains K steps throughout, every order reaching the encoder.

Evaluation lives in :mod:`ebjepa_tutorial.evaluation.detection`; the command
that trains notebook 03's runs ahead of a class is
``python -m research.train_video --scale class``.

Several processes (``torchrun``, see :mod:`ebjepa_tutorial.distributed`): the
config's ``batch_size`` is the global batch (clips), and global batch = per-rank batch x
world size. Every rank draws the same global batch (seeded by the step) and keeps its own
clips; the rollout loss is a mean over them, while the variance and covariance are those of
every location of every frame of the global batch, and the step averages the gradients over
the ranks itself (as chapter 05's does; no DistributedDataParallel wrapper). Batch norm (in
the encoder, the predictor and the projector) normalises over each rank's frames, unless
``sync_batchnorm`` (GPUs only).
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch
import torch.nn.functional as F

from .. import distributed
from ..data.moving_mnist import generate_moving_mnist
from ..losses.rollout import UNROLLS, parallel_rollout_loss, rollout_loss
from ..models.video import VIDEO_MODEL_CONFIGS, FrameDecoder, VideoJEPA, VideoModelConfig
from ..utils import (
    at_least_float32,
    check_fields,
    get_device,
    is_int_at_least,
    is_non_negative,
    is_positive,
    mixed_precision,
)
from .checkpoints import checkpoint_paths, run_identity, save_or_warn, step_identity
from .loop import (
    History,
    load_or_train,
    resume,
    run_steps,
    saver,
    step_generator,
    training_state,
)
from .optim import warmup_cosine_scheduler

LOG_EVERY = 10  # steps between the history's rows: reading a value waits for the GPU
CHECKPOINT_EVERY = 100  # steps between saves of a resumable run
STD_COEFF = 10.0  # std, the variance term's weight: the paper's, in every run of the course
COV_COEFF = 100.0  # cov, the covariance term's weight: likewise


@dataclass(frozen=True)
class Recipe:
    """Where the class run trains otherwise than the paper, to learn more per CPU-minute
    (notebook 03, section 6 and the optional section's curriculum). The defaults are the
    class run's; :data:`PAPER_RECIPE` is the paper's (the ``full`` preset)."""

    cosine: bool = True  # decay the rate to 0 by a half cosine (the paper: constant)
    # convolutions in channels_last: faster on CPUs too. PyTorch's CPU backward in
    # this layout crashes on some strided 1x1 convolutions at 64x64 (the ci encoder's);
    # a test checks each class-encoder convolution against the default layout
    channels_last: bool = True
    # a curriculum: this fraction of the steps trains one-step prediction (K = 1), the
    # rest the K-step rollout (the paper: 0, K steps throughout). Runs of one seed that
    # differ only in K are then the same run until the switch
    one_step_fraction: float = 0.5
    # orders 2..K unroll from detached latents: they train the predictor alone, and the
    # encoder learns from one-step errors only (the paper: False)
    detach_later_orders: bool = True

    def __post_init__(self):
        check_fields(self, {"one_step_fraction": (lambda f: is_non_negative(f) and f < 1,
                                                  "a number in [0, 1)")})


PAPER_RECIPE = Recipe(cosine=False, channels_last=False, one_step_fraction=0.0,
                      detach_later_orders=False)


@dataclass(frozen=True)
class VideoJEPAConfig:
    """One training run. Defaults: the class scale (~10 minutes on 2 CPU cores)."""

    model: VideoModelConfig = field(default_factory=lambda: VIDEO_MODEL_CONFIGS["class"])
    n_clips: int = 4000  # training clips from the training digits (make_clips; 164 MB)
    n_frames: int = 10  # frames per clip (needs >= context + rollout_steps)
    batch_size: int = 16  # clips per step (the paper: 64; per clip, small batches run faster here)
    steps: int = 2400  # sized for a class period on a laptop CPU
    lr: float = 3e-3  # Adam's base rate (the paper: 1e-3, constant)
    rollout_steps: int = 4  # K
    # how the K-step loss unrolls (losses.rollout.UNROLLS): "parallel", the paper's, or
    # "autoregressive", one true context rolled forward as a planner does (the same at K = 1)
    unroll: str = "parallel"
    recipe: Recipe = field(default_factory=Recipe)  # the class run's; PAPER_RECIPE: the paper's
    seed: int = 0

    def __post_init__(self):
        at_least = {name: (is_int_at_least(1), "an int >= 1")
                    for name in ("n_clips", "batch_size", "steps", "rollout_steps")}
        frames = self.model.context + self.rollout_steps if is_int_at_least(1)(
            self.rollout_steps) else self.model.context + 1
        check_fields(self, {
            **at_least,
            "n_frames": (is_int_at_least(frames),
                         f"an int >= context + rollout_steps = {frames}"),
            "lr": (is_positive, "a number > 0"),
            "unroll": (lambda u: u in UNROLLS, f"one of {sorted(UNROLLS)}"),
        })

    def rollout_steps_at(self, step: int) -> int:
        """K at optimiser step ``step``: 1 during the recipe's ``one_step_fraction`` of the run."""
        return 1 if step < self.switch_step else self.rollout_steps

    @property
    def switch_step(self) -> int:
        """The steps trained at K = 1 before the rollout begins (0 without a curriculum)."""
        return math.ceil(self.recipe.one_step_fraction * self.steps)

    def shares_start_with(self, other: VideoJEPAConfig) -> bool:
        """Whether ``other`` is this run with another K, hence the same run until the switch."""
        return (other.rollout_steps != self.rollout_steps and self.switch_step > 0
                and replace(other, rollout_steps=self.rollout_steps) == self)


VIDEO_CONFIGS = {
    "ci": VideoJEPAConfig(model=VIDEO_MODEL_CONFIGS["ci"], n_clips=256, batch_size=8, steps=20,
                          recipe=Recipe(channels_last=False)),
    "class": VideoJEPAConfig(),
    # the paper: 18,000 clips of 10 frames, batch 64, 50 epochs at a constant 1e-3
    "full": VideoJEPAConfig(model=VIDEO_MODEL_CONFIGS["full"], n_clips=18_000, batch_size=64,
                            steps=50 * 18_000 // 64, lr=1e-3, recipe=PAPER_RECIPE),
}


def make_clips(config: VideoJEPAConfig, train_digits: torch.Tensor) -> torch.Tensor:
    """The run's training clips: uint8 ``(n_clips, n_frames, 1, 64, 64)`` from ``train_digits``.

    Pass the first half of ``split_digits``; evaluation clips come from the other half.
    """
    batch = generate_moving_mnist(train_digits, config.n_clips, config.n_frames, seed=config.seed)
    return batch.clips


def check_clips(clips: torch.Tensor, min_frames: int) -> None:
    """Raise unless ``clips`` is uint8 ``(N, T, 1, 64, 64)`` with ``T >= min_frames``."""
    if not isinstance(clips, torch.Tensor) or clips.ndim != 5 or clips.shape[2:] != (1, 64, 64):
        got = tuple(clips.shape) if isinstance(clips, torch.Tensor) else type(clips).__name__
        raise ValueError(f"clips must be (N, T, 1, 64, 64) from generate_moving_mnist, got {got}")
    if clips.dtype != torch.uint8:
        raise TypeError(f"clips must be uint8 (as generated), got {clips.dtype}")
    if clips.shape[1] < min_frames:
        raise ValueError(f"clips have {clips.shape[1]} frames; this needs at least {min_frames} "
                         "(context + prediction steps): generate longer clips")


def video_jepa_step(model, optimizer, scheduler, frames, k, config):
    """One training step (notebook 03 shows it; tests/test_one_source_video.py keeps the two
    the same): the loss of a batch of clips, its gradient, the update.

    ``model``: a :class:`VideoJEPA` in train mode; ``frames``: this rank's clips, uint8
    ``(b, T, 1, 64, 64)``; ``k``: K of this step (:meth:`VideoJEPAConfig.rollout_steps_at`:
    1 in the curriculum's first half); ``config``: the :class:`VideoJEPAConfig` (no
    annotations here: the notebook's copy reads as plain Python). Under ``torchrun`` the
    variance and covariance are those of the global batch and the gradients are averaged over
    the ranks, so every rank takes the update one process would take on the whole batch.
    Returns ``(total, terms)``, detached: a 0-d tensor and the unweighted terms.
    """
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


def _check_run(config: VideoJEPAConfig, clips, handover, both: bool) -> None:
    """Refuse a bad run before any work: a handover to another run, ``after_step`` and a
    checkpoint together (``both``), an uneven split over ranks, clips too short."""
    for other, _ in handover:
        if not config.shares_start_with(other):
            raise ValueError(f"a run can hand over its K = 1 half only to the same run with "
                             f"another K; got {other} for {config}")
    if both:
        raise ValueError("after_step is not saved in a checkpoint: give one or the other")
    if distributed.world_size() > 1:  # (one process may take one-clip batches)
        distributed.per_rank_batch(config.batch_size)
    check_clips(clips, config.model.context + config.rollout_steps)


def new_model(config: VideoJEPAConfig, device, sync_batchnorm: bool = False) -> VideoJEPA:
    """The run's initial model on ``device``, the same on every rank (seeded by the run);
    ``sync_batchnorm``: its batch norms normalise over the global batch (GPUs, torchrun)."""
    torch.manual_seed(config.seed)
    layout = torch.channels_last if config.recipe.channels_last else torch.contiguous_format
    model = VideoJEPA(config.model).to(device, memory_format=layout)
    return distributed.with_sync_batchnorm(model, device) if sync_batchnorm else model


def new_scheduler(optimizer: torch.optim.Optimizer, config: VideoJEPAConfig):
    """The rate over the run: a half cosine to 0 (``config.recipe.cosine``), else constant (the
    paper's); a scheduler either way, so that the step always calls ``scheduler.step()``."""
    if config.recipe.cosine:
        return warmup_cosine_scheduler(optimizer, config.steps, 0)
    return torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: 1.0)


def train_video_jepa(config: VideoJEPAConfig, clips: torch.Tensor,
                     checkpoint: str | Path | None = None, progress: bool = True,
                     device: torch.device | str | None = None,
                     sync_batchnorm: bool = False, after_step=None,
                     handover: Sequence[tuple[VideoJEPAConfig, str | Path]] = (),
                     step=None) -> tuple[VideoJEPA, History]:
    """Train on uint8 ``clips`` ``(N, T, 1, 64, 64)``, each update a ``step`` (default
    :func:`video_jepa_step`; notebook 03 passes its cell's); resume from ``checkpoint``.
    Batches come from generators seeded by ``(seed, step)``, so a resumed run sees the same
    ones. Under ``torchrun``, ``config.batch_size`` is the global batch (global batch =
    per-rank batch x world size), rank 0 alone writes ``checkpoint`` (it resumes on any world
    size), and ``sync_batchnorm`` (GPUs only) normalises over the global batch.
    ``after_step(model, step)``, after each update, can score the model as it trains (it is
    not saved: no ``checkpoint``). ``handover``: ``(config, path)`` of runs that are this one
    with another K, saved to ``path`` at the switch. Returns the model (eval mode), history.
    """
    step = step or video_jepa_step
    _check_run(config, clips, handover, after_step is not None and checkpoint is not None)
    device = get_device(device)
    model = new_model(config, device, sync_batchnorm)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
    scheduler = new_scheduler(optimizer, config)
    parts = (model, optimizer, scheduler)
    start, history = resume(checkpoint, *parts, identity(config, step=step))  # (0, empty): none

    def update(frames_and_k: tuple[torch.Tensor, int], n: int):
        total, terms = step(*parts, *frames_and_k, config)
        if after_step is not None:
            after_step(model, n)
        return total, terms

    model.train()
    run_steps(update, _batches(config, clips, device), config.steps, start_step=start,
              history=history, log_every=LOG_EVERY, desc="video JEPA", progress=progress,
              after=_saves(config, checkpoint, handover, step, parts, history))
    return model.eval(), history


def _batches(config: VideoJEPAConfig, clips: torch.Tensor, device):
    """``batch(step) -> (frames, k)``: this rank's clips of step ``step``'s global batch,
    ``(b, T, 1, 64, 64)`` uint8 on ``device``, and K of that step."""

    def batch(step: int) -> tuple[torch.Tensor, int]:
        generator = step_generator(config.seed, step)
        index = torch.randint(0, len(clips), (config.batch_size,), generator=generator)
        # every rank drew the global batch and keeps its own rows (all of them in one process)
        return clips[distributed.local_rows(index)].to(device), config.rollout_steps_at(step)

    return batch


def _saves(config: VideoJEPAConfig, checkpoint, handover, step, parts, history: History):
    """``after(done)`` for :func:`run_steps`: the state of ``parts`` (model, optimiser,
    scheduler) saved to ``checkpoint`` every :data:`CHECKPOINT_EVERY` steps and at the end, and
    at the switch to each ``handover`` path as that run's (its identity), this one up to there.
    """
    model, optimizer, scheduler = parts

    def state(done: int, run: dict) -> dict:  # what resume() reads back; rank 0 alone writes
        return training_state(done, run, history, model, optimizer, scheduler)

    own = identity(config, step=step)
    save = saver(checkpoint, lambda done: state(done, own), config.steps, CHECKPOINT_EVERY)

    def after(done: int) -> None:
        save(done)
        for other, path in handover:
            if done == config.switch_step:
                save_or_warn(Path(path), **state(done, identity(other, step=step)))

    return after


def identity(config: VideoJEPAConfig, train_digits: torch.Tensor | None = None,
             step=None) -> dict:
    """What a checkpoint stores to recognise its run: ``config``, for a finished run the
    digits its clips were made from (:func:`digits_fingerprint`), and an edited ``step``'s
    code (:func:`~.checkpoints.step_identity`)."""
    edited = step_identity(step, video_jepa_step)
    if train_digits is None:  # a run in progress: its clips are fixed by the caller
        return run_identity(config, VIDEO_ALWAYS, **edited)
    return run_identity(config, VIDEO_ALWAYS, train_digits=digits_fingerprint(train_digits),
                        **edited)


VIDEO_ALWAYS = ("steps", "batch_size", "lr", "rollout_steps", "seed")


def digits_fingerprint(digits: torch.Tensor) -> str:
    """A short hash of the training digits: a saved run is reused only with the same digits."""
    return hashlib.sha1(digits.contiguous().numpy().tobytes()).hexdigest()[:12]


def run_name(scale: str, config: VideoJEPAConfig) -> str:
    """Notebook 03's checkpoint name for ``config``: ``video_jepa_<scale>_K<K>_seed<seed>``."""
    return f"video_jepa_{scale}_K{config.rollout_steps}_seed{config.seed}"


def train_or_load(config: VideoJEPAConfig, name: str, train_digits: torch.Tensor,
                  device: torch.device | str | None = None, progress: bool = True,
                  sync_batchnorm: bool = False,
                  siblings: Sequence[tuple[VideoJEPAConfig, str]] = (), step=None):
    """The model of ``config``: loaded if a run with exactly this config was saved, else trained.

    Looks for ``checkpoints/<name>.pt`` (shipped with the course), then
    ``data/cache/checkpoints/<name>.pt``; a file counts only if it stores this
    config and the same ``train_digits`` (uint8 ``(D, 1, 28, 28)``, compared by
    :func:`digits_fingerprint`). Otherwise makes the run's clips, trains
    (resumable from ``<name>.partial`` in the cache) and saves. Notebook 03.
    Returns ``(model in eval mode, history)``. In a process group every rank trains
    (:func:`train_video_jepa`, with ``sync_batchnorm``); rank 0 reads and writes the files.
    ``siblings``: ``(config, name)`` of runs that are this one with another K; those not
    saved or started yet get this run's state at the switch as their ``.partial``, so
    they train only their rollout half.
    ``step``: the training step (:func:`train_video_jepa`). A step whose code differs from
    :func:`video_jepa_step` (a learner's edit) is a run of its own: its identity holds a hash
    of its code, so it never loads, or replaces, the course's run.
    """
    torch.manual_seed(config.seed)
    model = VideoJEPA(config.model).to(get_device(device))
    cache_path, shipped = checkpoint_paths(name)
    partial = cache_path.with_suffix(".partial")

    def train() -> History:
        clips = make_clips(config, train_digits)
        trained, history = train_video_jepa(config, clips, checkpoint=partial, progress=progress,
                                            device=device, sync_batchnorm=sync_batchnorm,
                                            handover=_not_started(siblings), step=step)
        model.load_state_dict(trained.state_dict())
        return history

    history = load_or_train(cache_path, model, train, identity(config, train_digits, step), shipped,
                            partial=partial)
    return model.eval(), history


def _not_started(siblings: Sequence[tuple[VideoJEPAConfig, str]]):
    """``(config, its .partial)`` of the ``siblings`` with no file yet, shipped or cached."""
    waiting = []
    for config, name in siblings:
        cache_path, shipped = checkpoint_paths(name)
        partial = cache_path.with_suffix(".partial")
        if not any(path.exists() for path in (cache_path, shipped, partial)):
            waiting.append((config, partial))
    return waiting


# --- a decoder, to draw latents as pictures ---------------------------------------------------


def fit_decoder(model: VideoJEPA, clips: torch.Tensor, steps: int = 200, batch_size: int = 32,
                lr: float = 1e-3, seed: int = 0) -> FrameDecoder:
    """Train a :class:`FrameDecoder` from frozen latents back to frames, for pictures only.

    ``clips``: uint8 ``(N, T, 1, 64, 64)``; each step decodes ``batch_size``
    random frames; the loss is a per-pixel binary cross-entropy. Decode with
    ``torch.sigmoid(decoder(z))``, ``z`` ``(N, C, S, S)`` encoded or predicted.
    """
    check_clips(clips, 1)
    model.eval()
    device = next(model.parameters()).device
    generator = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    decoder = FrameDecoder(model.config.latent_channels, model.config.latent_side).to(device)
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


