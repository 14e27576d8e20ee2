"""The K-step rollout loss of the video JEPA (notebook 03; the paper's multistep loss).

Each frame is encoded to a spatial latent ``z_t`` ``(C, S, S)``; the predictor
sees the last ``context`` latents and guesses the next one. Training unrolls
it on its own guesses for ``K`` steps from every start frame of a clip and
compares the guess of order ``k`` with the true encoding.

Where we differ from the reference code: its training unroll feeds order-k
predictions of *both* context frames (each made from another true context)
and averages the error over the clip's ground-truth context frames too; ours
rolls one true context forward, exactly as evaluation (and a planner) uses
the predictor, and averages over predicted frames only. Its prediction error
is also taken after the projector; ours on the latents themselves.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F

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
