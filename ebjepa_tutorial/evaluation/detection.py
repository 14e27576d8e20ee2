"""Notebook 03's evaluation: a probe on frozen video latents marks the cells of an 8x8 grid that
hold a digit centre, scored by average precision (AP) on latents predicted k steps ahead."""

import torch
import torch.nn.functional as F

from ..data.moving_mnist import GRID, centres_to_grid, generate_moving_mnist
from ..losses.rollout import UNROLLS, parallel_unroll, rollout
from ..models.video import VideoJEPA, detection_head
from ..utils import evaluating
from .metrics import average_precision


def _pool(z: torch.Tensor) -> torch.Tensor:
    """``(B, T, C, S, S) -> (B, T, C, 8, 8)`` by average pooling (the probe's first step)."""
    return F.adaptive_avg_pool2d(z.flatten(0, 1), GRID).unflatten(0, z.shape[:2])


def check_clips(clips: torch.Tensor, min_frames: int) -> None:
    """Raise unless ``clips`` is uint8 ``(N, T, 1, 64, 64)`` with ``T >= min_frames``."""
    if (not isinstance(clips, torch.Tensor) or clips.dtype != torch.uint8 or clips.ndim != 5
            or clips.shape[2:] != (1, 64, 64) or clips.shape[1] < min_frames):
        got = (f"{tuple(clips.shape)} {clips.dtype}" if isinstance(clips, torch.Tensor)
               else type(clips).__name__)
        raise ValueError(f"clips must be uint8 (N, T, 1, 64, 64) with T at least {min_frames} "
                         f"(context + prediction steps), generate_moving_mnist's batch.clips; "
                         f"got {got}")


@torch.no_grad()
def grid_features(model: VideoJEPA, clips: torch.Tensor, horizons: int = 7,
                  unroll: str = "parallel"):
    """Pooled latents on the CPU of uint8 ``clips (N, T, 1, 64, 64)``: ``encoded (N, T, C, 8, 8)``
    and, for k = 1..``horizons``, ``predicted[k - 1] (N, F_k, C, 8, 8)``: frames from
    ``context - 1 + k`` on (``parallel``: all later ones; else that one), predicted k ahead.
    The model runs in eval mode and is handed back in its own."""
    context = model.config.context
    check_clips(clips, context + horizons)
    if unroll not in UNROLLS:
        raise ValueError(f"unroll must be one of {sorted(UNROLLS)}, got {unroll!r}")
    device = next(model.parameters()).device
    encoded, predicted = [], []
    with evaluating(model):
        for lo in range(0, len(clips), 100):
            z = model.encode(clips[lo:lo + 100].to(device))
            if unroll == "parallel":  # step k's predictions from frame context - 1 + k on
                steps = parallel_unroll(model.predictor, z, context, horizons)
                predicted.append([_pool(p[:, k:]).cpu() for k, p in enumerate(steps)])
            else:  # one rollout from the first context frames: entry k - 1 is k steps ahead
                steps = _pool(rollout(model.predictor, z[:, :context], horizons)).cpu()
                predicted.append(list(steps.split(1, dim=1)))
            encoded.append(_pool(z).cpu())
    return torch.cat(encoded), [torch.cat(k_steps) for k_steps in zip(*predicted)]


def fit_detection_probe(features: torch.Tensor, targets: torch.Tensor,
                        steps: int = 400) -> torch.nn.Sequential:
    """Train a ``detection_head`` (seeded; binary cross-entropy, Adam at 3e-3, batches
    of 512) on frozen pooled latents ``(M, C, g, g)`` for 0/1 ``targets`` ``(M, g, g)``."""
    generator = torch.Generator().manual_seed(0)
    with torch.random.fork_rng(devices=[]):  # seeded initial weights; the caller's draws go on
        torch.manual_seed(0)
        probe = detection_head(features.shape[1], grid=targets.shape[-1])
    optimizer = torch.optim.Adam(probe.parameters(), lr=3e-3)
    for _ in range(steps):
        index = torch.randint(0, len(features), (512,), generator=generator)
        loss = F.binary_cross_entropy_with_logits(probe(features[index]), targets[index])
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    return probe.eval()


@torch.no_grad()
def detection_report(model: VideoJEPA, probe_data, eval_data, horizons: int = 7,
                     probe_steps: int = 400, unroll: str = "parallel") -> dict:
    """The ``probe`` fitted on ``probe_data``; AP per horizon on ``eval_data``, ``(horizons,)``:
    ``ap`` (predicted by ``unroll``), ``ap_encoded`` (true latents: a perfect predictor),
    ``ap_copy`` (the latest true latent: a predictor that never moves); their means ``map...``."""
    context = model.config.context
    fit_features, _ = grid_features(model, probe_data.clips, horizons=1)  # encodings only
    with torch.enable_grad():
        probe = fit_detection_probe(fit_features.flatten(0, 1),
                                    centres_to_grid(probe_data.centres).flatten(0, 1),
                                    steps=probe_steps)
    encoded, predicted = grid_features(model, eval_data.clips, horizons, unroll=unroll)
    cells = centres_to_grid(eval_data.centres)  # (N, T, g, g)
    # Horizon k scores frames from context - 1 + k on: the paper's parallel unroll every later
    # frame too (each k steps past its latest true latent), the rollout (a planner's) that one.
    frames = [slice(context - 1 + k, cells.shape[1] if unroll == "parallel" else context + k)
              for k in range(1, horizons + 1)]
    latest = [slice(f.start - k, f.stop - k) for k, f in enumerate(frames, 1)]  # true latents

    def aps(features):  # [(N, F_k, C, g, g) for k = 1..horizons] -> float64 (horizons,)
        return torch.tensor([average_precision(probe(f.flatten(0, 1)), cells[:, s].flatten(0, 1))
                             for f, s in zip(features, frames)], dtype=torch.float64)

    report = {"probe": probe, "ap": aps(predicted),
              "ap_encoded": aps([encoded[:, f] for f in frames]),
              "ap_copy": aps([encoded[:, f] for f in latest])}
    return report | {"map" + name[2:]: float(report[name].mean())
                     for name in ("ap", "ap_encoded", "ap_copy")}


def evaluation_clips(train_digits: torch.Tensor, held_out: torch.Tensor, n_probe: int,
                     n_eval: int, n_frames: int = 10):
    """``(probe clips, eval clips)``: fresh clips of the training digits fit the probe, clips of
    ``held_out`` digits alone are where AP is measured (seeds 1001, 1002; training: 0, 1, ...)."""
    return (generate_moving_mnist(train_digits, n_probe, n_frames, seed=1001),
            generate_moving_mnist(held_out, n_eval, n_frames, seed=1002))
