"""Video JEPA on Moving MNIST (notebook 03): the K-step rollout loss, training, detection AP.

Each frame is encoded to a spatial latent ``z_t`` ``(C, S, S)``; the predictor
sees the last two latents and guesses the next one. Training unrolls it on
its own guesses for ``K`` steps from every start frame of a clip, compares the
guess of order ``k`` with the true encoding ``z_{s+1+k}`` and adds the
variance and covariance terms on projected latents (each location of each
frame is one sample) so that the latent cannot collapse:

    L = (1/K) sum_k mean ||zhat_k - z_{s+1+k}||^2 + std v(P(Z)) + cov c(P(Z))

Evaluation, on clips made from held-out digits: a small head, trained on
frozen latents, marks which cells of an 8x8 grid hold a digit centre; we
score it on latents predicted ``k = 1..7`` steps ahead and report the average
precision (AP) over the whole evaluation set per horizon, and their mean (mAP).

Where we differ from the reference code: its training unroll feeds order-k
predictions of *both* context frames (each made from another true context)
and averages the error over the clip's ground-truth context frames too; ours
rolls one true context forward, exactly as evaluation (and a planner) uses
the predictor, and averages over predicted frames only. Its prediction error
is also taken after the projector; ours on the latents themselves.

The notebook's runs (the K ablation) can be trained ahead of a class with
``python -m ebjepa_tutorial.video_jepa --scale class`` (see :func:`main`).
"""

from __future__ import annotations

import argparse
import hashlib
import inspect
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch
import torch.nn.functional as F

from .data.moving_mnist import centres_to_grid, generate_moving_mnist
from .exercises import Case, compare
from .losses import covariance_term, variance_term
from .metrics import average_precision_per_horizon
from .models.video import (
    VIDEO_MODEL_CONFIGS,
    DetectionHead,
    FrameDecoder,
    VideoJEPA,
    VideoModelConfig,
)
from .train import History, checkpoint_paths, fit, load_or_train, resume
from .utils import check_fields, get_device, is_int_at_least, is_non_negative, is_positive

Predictor = Callable[[torch.Tensor], torch.Tensor]  # (N, context, C, H, W) -> (N, C, H, W)


def check_rollout_args(z: torch.Tensor, context: int, steps: int, tbptt: int | None = None):
    """Raise a clear error unless ``z`` is ``(B, T, C, H, W)`` with ``T >= context + steps``."""
    if not isinstance(z, torch.Tensor) or z.ndim != 5:
        got = tuple(z.shape) if isinstance(z, torch.Tensor) else type(z).__name__
        raise ValueError(f"latents must be (batch, time, channels, height, width), got {got}")
    if not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps (K) must be an int >= 1, got {steps!r}")
    if not isinstance(context, int) or context < 1:
        raise ValueError(f"context must be an int >= 1, got {context!r}")
    if z.shape[1] < context + steps:
        raise ValueError(
            f"a clip of {z.shape[1]} frames is too short for {context} context frames and "
            f"{steps} prediction steps: use clips of at least {context + steps} frames, or "
            "fewer steps"
        )
    if tbptt is not None and (not isinstance(tbptt, int) or tbptt < 1):
        raise ValueError(f"tbptt must be None (no truncation) or an int >= 1, got {tbptt!r}")


def rollout(predictor: Predictor, window: torch.Tensor, steps: int, tbptt: int | None = None):
    """Unroll the predictor on its own outputs: ``(N, context, C, H, W) -> (N, steps, C, H, W)``.

    Each step predicts the next latent from the current window, then slides the
    window: the oldest latent drops out, the prediction comes in. With
    ``tbptt=m`` the window is detached every ``m`` steps (see :func:`rollout_loss`).
    """
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps must be an int >= 1 (predictions to unroll), got {steps!r}")
    predictions = []
    for k in range(steps):
        if tbptt is not None and k > 0 and k % tbptt == 0:
            window = window.detach()  # truncate: no gradient into earlier steps
        z_next = predictor(window)
        predictions.append(z_next)
        window = torch.cat([window[:, 1:], z_next[:, None]], dim=1)
    return torch.stack(predictions, dim=1)


def rollout_loss(predictor: Predictor, z: torch.Tensor, context: int = 2, steps: int = 4,
                 tbptt: int | None = None) -> torch.Tensor:
    """K-step rollout loss over latents ``z`` ``(B, T, C, H, W)``: a 0-d tensor.

    From every start frame ``s`` (``0 <= s <= T - context - K``) the predictor
    gets the true window ``z_s .. z_{s+context-1}`` and is unrolled on its own
    predictions for ``K = steps`` steps; prediction ``k`` is compared with the
    true ``z_{s+context-1+k}``. The loss is the mean squared error over all
    starts, orders ``k``, and elements (the orders weigh equally). Targets keep
    their gradient, as in the paper; the variance-covariance terms prevent collapse.

    ``tbptt`` (truncated back-propagation through time): ``None`` sends the
    gradient of order ``k`` back through all ``k - 1`` earlier predictions,
    which teaches the predictor to make outputs that are good *inputs* for its
    next steps. ``tbptt=m`` cuts the graph every ``m`` steps (the rolled-out
    window is detached), so a gradient crosses at most ``m`` predictor calls:
    the same forward values and loss, a different gradient. ``tbptt=1`` trains
    every step as a one-step predictor fed with its own (frozen) earlier
    outputs. Since all orders sit in one loss, each predictor call is
    back-propagated once either way: truncation changes what the gradient asks
    for (and can tame exploding rollouts), not the cost.
    """
    check_rollout_args(z, context, steps, tbptt)
    n = z.shape[1] - context - steps + 1  # rollouts per clip, one per start frame
    windows = torch.stack([z[:, j:j + n] for j in range(context)], dim=2)  # (B, n, ctx, C, H, W)
    targets = torch.stack([z[:, context + k:context + k + n] for k in range(steps)], dim=2)
    predictions = rollout(predictor, windows.flatten(0, 1), steps, tbptt)  # (B*n, K, C, H, W)
    return F.mse_loss(predictions, targets.flatten(0, 1))


@dataclass(frozen=True)
class VideoJEPAConfig:
    """One training run. Defaults: the class scale (~10 minutes on 2 CPU cores)."""

    model: VideoModelConfig = field(default_factory=lambda: VIDEO_MODEL_CONFIGS["class"])
    n_clips: int = 4000  # training clips from the training digits (make_clips; 164 MB)
    n_frames: int = 10  # frames per clip (needs >= context + rollout_steps)
    batch_size: int = 16  # clips per step (the paper: 64; per clip, small batches run faster here)
    steps: int = 600  # about 1.1 s per step on one busy CPU thread
    lr: float = 1e-3  # Adam, as in the paper
    std_coeff: float = 10.0  # the paper's weights
    cov_coeff: float = 100.0
    rollout_steps: int = 4  # K
    tbptt: int | None = None  # truncated back-propagation through time (None: full)
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
            "std_coeff": (is_non_negative, "a number >= 0"),
            "cov_coeff": (is_non_negative, "a number >= 0"),
            "tbptt": (lambda m: m is None or is_int_at_least(1)(m), "None or an int >= 1"),
        })


VIDEO_CONFIGS = {
    "ci": VideoJEPAConfig(model=VIDEO_MODEL_CONFIGS["ci"], n_clips=256, batch_size=8, steps=20),
    "class": VideoJEPAConfig(),
    # the paper: 18,000 clips of 10 frames, batch 64, 50 epochs
    "full": VideoJEPAConfig(model=VIDEO_MODEL_CONFIGS["full"], n_clips=18_000, batch_size=64,
                            steps=50 * 18_000 // 64),
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


def video_jepa_loss(model: VideoJEPA, frames: torch.Tensor, config: VideoJEPAConfig):
    """Total loss of a batch of clips ``(B, T, 1, 64, 64)`` and its unweighted terms."""
    z = model.encode(frames)
    prediction = rollout_loss(model.predictor, z, model.config.context, config.rollout_steps,
                              config.tbptt)
    projected = model.project(z)  # (B*T*S*S, D): every location of every frame is a sample
    variance, covariance = variance_term(projected), covariance_term(projected)
    total = prediction + config.std_coeff * variance + config.cov_coeff * covariance
    terms = {"prediction": prediction.item(), "variance": variance.item(),
             "covariance": covariance.item()}
    return total, terms


def train_video_jepa(config: VideoJEPAConfig, clips: torch.Tensor,
                     checkpoint: str | Path | None = None, progress: bool = True,
                     device: torch.device | str | None = None) -> tuple[VideoJEPA, History]:
    """Train on uint8 ``clips`` ``(N, T, 1, 64, 64)``; resume from ``checkpoint`` if it exists.

    Batch ``step`` is drawn from a generator seeded by ``(seed, step)``, so a
    resumed run sees the same batches as an uninterrupted one. Returns the
    model (in eval mode) and its history.
    """
    check_clips(clips, config.model.context + config.rollout_steps)
    device = get_device(device)
    torch.manual_seed(config.seed)
    model = VideoJEPA(config.model).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
    start, history = (0, History())
    if checkpoint is not None:
        start, history = resume(checkpoint, model, optimizer, config=config_dict(config))

    def batch(step: int) -> torch.Tensor:
        generator = torch.Generator().manual_seed(config.seed * 1_000_003 + step)
        return clips[torch.randint(0, len(clips), (config.batch_size,), generator=generator)]

    fit(model, optimizer, lambda frames: video_jepa_loss(model, frames.to(device), config),
        batch, config.steps, history=history, start_step=start, checkpoint=checkpoint,
        checkpoint_every=100, log_every=10, desc="video JEPA", progress=progress,
        config=config_dict(config))
    return model.eval(), history


def config_dict(config: VideoJEPAConfig) -> dict:
    """The config as a plain dict (what checkpoints store to recognise a matching run)."""
    return asdict(config)


def digits_fingerprint(digits: torch.Tensor) -> str:
    """A short hash of the training digits: a saved run is reused only with the same digits."""
    return hashlib.sha1(digits.contiguous().numpy().tobytes()).hexdigest()[:12]


def run_name(scale: str, config: VideoJEPAConfig) -> str:
    """Notebook 03's checkpoint name for ``config``: ``video_jepa_<scale>_K<K>_seed<seed>``."""
    return f"video_jepa_{scale}_K{config.rollout_steps}_seed{config.seed}"


def train_or_load(config: VideoJEPAConfig, name: str, train_digits: torch.Tensor,
                  device: torch.device | str | None = None, progress: bool = True):
    """The model of ``config``: loaded if a run with exactly this config was saved, else trained.

    Looks for ``checkpoints/<name>.pt`` (shipped with the course), then
    ``data/cache/checkpoints/<name>.pt``; a file counts only if it stores this
    config and the same ``train_digits`` (uint8 ``(D, 1, 28, 28)``, compared by
    :func:`digits_fingerprint`). Otherwise makes the run's clips, trains
    (resumable from ``<name>.partial`` in the cache) and saves. Notebook 03.
    Returns ``(model in eval mode, history)``.
    """
    torch.manual_seed(config.seed)
    model = VideoJEPA(config.model).to(get_device(device))
    cache_path, shipped = checkpoint_paths(name)
    partial = cache_path.with_suffix(".partial")

    def train() -> History:
        clips = make_clips(config, train_digits)
        trained, history = train_video_jepa(config, clips, checkpoint=partial, progress=progress,
                                            device=device)
        model.load_state_dict(trained.state_dict())
        return history

    stored = {**config_dict(config), "train_digits": digits_fingerprint(train_digits)}
    history = load_or_train(cache_path, model, train, stored, shipped, partial=partial)
    return model.eval(), history


# --- evaluation: a detection probe on frozen latents, AP per prediction horizon ---------------


def _pool(z: torch.Tensor, grid: int) -> torch.Tensor:
    """``(B, T, C, S, S) -> (B, T, C, grid, grid)`` by average pooling (the probe's first step)."""
    return F.adaptive_avg_pool2d(z.flatten(0, 1), grid).unflatten(0, z.shape[:2])


@torch.no_grad()
def grid_features(model: VideoJEPA, clips: torch.Tensor, horizons: int = 7,
                  batch_size: int = 100, grid: int = 8) -> tuple[torch.Tensor, torch.Tensor]:
    """Pooled latents of uint8 ``clips`` ``(N, T, 1, 64, 64)`` for the probe, on the CPU.

    Returns ``encoded`` ``(N, T, C, grid, grid)``, every frame encoded, and
    ``predicted`` ``(N, horizons, C, grid, grid)``: the predictor unrolled from
    the first ``context`` frames, so entry ``k - 1`` is the guess for frame
    ``context - 1 + k``, made ``k`` steps ahead.
    """
    context = model.config.context
    check_clips(clips, context + horizons)
    model.eval()
    device = next(model.parameters()).device
    encoded, predicted = [], []
    for lo in range(0, len(clips), batch_size):
        z = model.encode(clips[lo:lo + batch_size].to(device))
        predicted.append(_pool(rollout(model.predictor, z[:, :context], horizons), grid).cpu())
        encoded.append(_pool(z, grid).cpu())
    return torch.cat(encoded), torch.cat(predicted)


def fit_detection_probe(features: torch.Tensor, targets: torch.Tensor, steps: int = 400,
                        batch_size: int = 512, lr: float = 3e-3, hidden: int = 32,
                        seed: int = 0) -> DetectionHead:
    """Train a :class:`DetectionHead` on frozen latents; sigmoid / binary cross-entropy.

    ``features``: ``(M, C, g, g)`` (pooled, from :func:`grid_features`, one row
    per frame); ``targets``: 0/1 ``(M, g, g)`` from ``centres_to_grid``.
    """
    if features.shape[0] != targets.shape[0] or features.shape[-2:] != targets.shape[-2:]:
        raise ValueError(f"features {tuple(features.shape)} and targets "
                         f"{tuple(targets.shape)} must be (M, C, g, g) and (M, g, g)")
    generator = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    probe = DetectionHead(features.shape[1], hidden, grid=targets.shape[-1])
    optimizer = torch.optim.Adam(probe.parameters(), lr=lr)
    for _ in range(steps):
        index = torch.randint(0, len(features), (batch_size,), generator=generator)
        loss = F.binary_cross_entropy_with_logits(probe(features[index]), targets[index])
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    return probe.eval()


@torch.no_grad()
def detection_report(model: VideoJEPA, probe_data, eval_data, horizons: int = 7,
                     probe_steps: int = 400, seed: int = 0) -> dict:
    """Fit the probe on ``probe_data``'s encoded frames; AP per horizon on ``eval_data``.

    Both are :class:`~ebjepa_tutorial.data.moving_mnist.MovingMNISTBatch`
    (make ``eval_data`` from held-out digits). Returns float64 ``(horizons,)``
    tensors ``ap`` (probe on predicted latents), ``ap_encoded`` (on the true
    encodings of the same frames: what a perfect predictor would reach) and
    ``ap_copy`` (on the last context frame: a predictor that never moves),
    their means ``map``, ``map_encoded``, ``map_copy``, and the ``probe``.
    """
    context = model.config.context
    fit_features, _ = grid_features(model, probe_data.clips, horizons=1)  # encodings only
    with torch.enable_grad():
        probe = fit_detection_probe(fit_features.flatten(0, 1),
                                    centres_to_grid(probe_data.centres).flatten(0, 1),
                                    steps=probe_steps, seed=seed)
    encoded, predicted = grid_features(model, eval_data.clips, horizons)
    targets = centres_to_grid(eval_data.centres)[:, context:context + horizons]

    def scores(features):  # (N, H, C, g, g) -> (N, H, g, g)
        return probe(features.flatten(0, 1)).unflatten(0, features.shape[:2])

    last = encoded[:, context - 1:context].expand(-1, horizons, -1, -1, -1)
    report = {"probe": probe}
    for name, features in (("", predicted), ("_encoded", encoded[:, context:context + horizons]),
                           ("_copy", last)):
        report["ap" + name] = average_precision_per_horizon(scores(features), targets)
        report["map" + name] = float(report["ap" + name].mean())
    return report


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


# --- notebook 03's protocol and runs, from the command line ----------------------------------

PROBE_SEED, EVAL_SEED = 1001, 1002  # seeds of the evaluation clips (training clips use 0, 1, ...)


def evaluation_clips(train_digits: torch.Tensor, held_out: torch.Tensor, n_probe: int,
                     n_eval: int, n_frames: int = 10):
    """The protocol's two sets of clips, the same for every model compared.

    Probe clips (fresh clips of the training digits) fit the detection probe;
    evaluation clips, made only of ``held_out`` digits, are where AP is measured.
    """
    return (generate_moving_mnist(train_digits, n_probe, n_frames, seed=PROBE_SEED),
            generate_moving_mnist(held_out, n_eval, n_frames, seed=EVAL_SEED))


def ablation_configs(config: VideoJEPAConfig, rollout_steps=(1, 2, 4), seeds=(0, 1, 2)):
    """``config`` with every ``K`` in ``rollout_steps`` and every seed (clips and weights)."""
    return [replace(config, rollout_steps=k, seed=s) for k in rollout_steps for s in seeds]


def main(argv: list[str] | None = None) -> None:
    """Train (or load) and evaluate notebook 03's runs at a scale, printing AP per horizon.

    ``python -m ebjepa_tutorial.video_jepa --scale class`` trains the K ablation
    (K 1, 2, 4 times three seeds, about ten minutes each on 2 CPU cores) into
    ``data/cache/checkpoints/``, where the notebook finds them; an interrupted
    run resumes. Same digits, clips and probe protocol as the notebook.
    """
    from .data.mnist import load_mnist
    from .data.moving_mnist import split_digits
    from .scale import SCALES, preset

    parser = argparse.ArgumentParser(description="Train and evaluate notebook 03's video JEPAs.")
    parser.add_argument("--scale", default="class", choices=SCALES)
    parser.add_argument("--K", type=int, action="append", help="only these K (repeatable)")
    parser.add_argument("--seed", type=int, action="append", help="only these seeds (repeatable)")
    args = parser.parse_args(argv)
    cfg = preset("03", args.scale)
    train_digits, held_out = split_digits(load_mnist("test")[0], n_train=cfg.n_train_digits)
    probe_data, eval_data = evaluation_clips(train_digits, held_out, cfg.n_probe, cfg.n_eval,
                                             cfg.train.n_frames)
    print(f"protocol: AP per horizon 1..{cfg.horizons} of a detection probe on frozen latents, "
          f"fitted on {cfg.n_probe} clips of training digits, scored on {cfg.n_eval} clips of "
          f"{len(held_out)} held-out MNIST test digits")
    torch.manual_seed(cfg.train.seed)
    runs = [("random init", VideoJEPA(cfg.train.model).eval())]
    for config in ablation_configs(cfg.train, args.K or cfg.rollout_steps, args.seed or cfg.seeds):
        start = time.perf_counter()
        model, _ = train_or_load(config, run_name(args.scale, config), train_digits)
        print(f"{run_name(args.scale, config)}: ready in {time.perf_counter() - start:.0f} s")
        runs.append((f"K={config.rollout_steps} seed={config.seed}", model))
    for label, model in runs:
        report = detection_report(model.cpu(), probe_data, eval_data, cfg.horizons,
                                  cfg.probe_steps)
        aps = " ".join(f"{ap:.3f}" for ap in report["ap"].tolist())
        print(f"{label}: mAP {report['map']:.3f} (AP {aps}; true encodings "
              f"{report['map_encoded']:.3f}, copy last frame {report['map_copy']:.3f})")


# --- the exercise of notebook 03: "implement the K-step rollout loss" -----------------------


def _toy_predictor(kind: str, weight: torch.Tensor | None = None) -> Predictor:
    """Toy predictors ``(N, context, C, H, W) -> (N, C, H, W)`` with rollouts easy to follow."""
    if kind == "shift":  # the last latent plus 0.5: order k of a rollout is z_last + 0.5 k
        return lambda window: window[:, -1] + 0.5
    if kind == "velocity":  # constant velocity: exact on latents that move in straight lines
        return lambda window: 2 * window[:, -1] - window[:, -2]
    if kind == "mean":  # uses the whole window, however long
        return lambda window: window.mean(dim=1) + 0.1
    # a fixed nonlinear map of the whole window, weight (context, C, C)
    return lambda window: torch.tanh(torch.einsum("nkchw,kcd->ndhw", window, weight))


def _rollout_case(what: str, kind: str, z: torch.Tensor, context: int, steps: int,
                  tbptt: int | None = None, seed: int = 0):
    """Arguments of one check: what to compare (loss ``value``, ``grad_z`` or ``grad_weight``)."""
    weight = torch.randn(context, z.shape[2], z.shape[2],
                         generator=torch.Generator().manual_seed(seed)) / z.shape[2] ** 0.5
    return (what, kind, weight, z, context, steps, tbptt)


def _run_rollout_loss(loss_fn: Callable) -> Callable:
    """Wrap a rollout loss so that one call returns the loss value or one of its gradients."""
    def run(what, kind, weight, z, context, steps, tbptt):
        weight, z = weight.clone().requires_grad_(), z.clone().requires_grad_()
        kwargs = {"context": context, "steps": steps}
        if tbptt is not None:
            kwargs["tbptt"] = tbptt
        loss = loss_fn(_toy_predictor(kind, weight), z, **kwargs)
        if what == "value" or not isinstance(loss, torch.Tensor):
            return loss
        wrt = z if what == "grad_z" else weight
        grad = torch.autograd.grad(loss, wrt, allow_unused=True)[0]
        grad = torch.zeros_like(wrt) if grad is None else grad
        return grad[:, -1] if what == "grad_z" else grad  # z's last frame is only a target
    run.__name__ = getattr(loss_fn, "__name__", "your function")
    return run


def check_rollout_loss(fn: Callable) -> bool:
    """Notebook 03: ``rollout_loss(predictor, z, context=2, steps=4[, tbptt=None])`` -> 0-d tensor.

    Compares the loss and its gradients with :func:`rollout_loss` on random
    latents and toy predictors. The ``tbptt`` cases run only if ``fn`` takes a
    ``tbptt`` argument.
    """
    g = torch.Generator().manual_seed(7)
    drift = torch.arange(7.0)[None, :, None, None, None] * torch.randn(1, 1, 2, 3, 3, generator=g)
    cases = [
        ("the predictor 'last latent + 0.5', random latents (2, 8, 3, 4, 4), context 2, K 3",
         _rollout_case("value", "shift", torch.randn(2, 8, 3, 4, 4, generator=g), 2, 3)),
        ("a constant-velocity predictor on latents moving in straight lines (the loss is 0)",
         _rollout_case("value", "velocity", drift, 2, 4)),
        ("a constant-velocity predictor, random latents (2, 9, 2, 4, 4), K 4",
         _rollout_case("value", "velocity", torch.randn(2, 9, 2, 4, 4, generator=g), 2, 4)),
        ("a nonlinear predictor, random latents (3, 10, 4, 4, 4), K 4",
         _rollout_case("value", "mixer", torch.randn(3, 10, 4, 4, 4, generator=g), 2, 4)),
        ("a predictor averaging its window, context 3 (not 2), K 2",
         _rollout_case("value", "mean", torch.randn(2, 7, 2, 3, 3, generator=g), 3, 2)),
        ("one step (K 1), latents (4, 5, 2, 2, 2)",
         _rollout_case("value", "mixer", torch.randn(4, 5, 2, 2, 2, generator=g), 2, 1)),
        ("the shortest clip, T = context + K = 5 frames",
         _rollout_case("value", "velocity", torch.randn(2, 5, 2, 3, 3, generator=g), 2, 3)),
        ("the gradient with respect to the last latent z[:, -1], a target (keep its gradient)",
         _rollout_case("grad_z", "mixer", torch.randn(2, 8, 3, 3, 3, generator=g), 2, 4)),
        ("the gradient with respect to the predictor's weights, K 4",
         _rollout_case("grad_weight", "mixer", torch.randn(2, 8, 3, 3, 3, generator=g), 2, 4)),
    ]
    if "tbptt" in inspect.signature(fn).parameters:
        z = torch.randn(2, 9, 3, 3, 3, generator=g)
        cases += [(f"the gradient with respect to the predictor's weights, K 5, tbptt={m}",
                   _rollout_case("grad_weight", "mixer", z, 2, 5, tbptt=m)) for m in (1, 2)]
        cases.append(("the loss value with tbptt=2 (truncation must not change it)",
                      _rollout_case("value", "mixer", z, 2, 5, tbptt=2)))
    else:
        print("(your function has no tbptt argument: the truncation cases are skipped)")
    return compare(_run_rollout_loss(fn), _run_rollout_loss(rollout_loss),
                   [Case(description, args) for description, args in cases])


if __name__ == "__main__":
    main()
