"""The video JEPA's K-step loss (notebook 03), unrolled two ways (the same at K = 1): "parallel"
(the paper's) or "autoregressive" (one true context rolled forward, as a planner does). Unlike the
paper's code, we average over predicted frames only, on the latents (not after the projector)."""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F

Predictor = Callable[[torch.Tensor], torch.Tensor]  # (N, context, C, H, W) -> (N, C, H, W)


def _check_args(z: torch.Tensor, context: int, steps: int):
    if z.ndim != 5 or steps < 1 or z.shape[1] < context + steps:
        raise ValueError(f"latents must be (batch, time >= context + steps = {context} + {steps}, "
                         f"C, H, W), steps >= 1; got {tuple(z.shape)} (a clip too short?)")


def rollout(predictor: Predictor, window: torch.Tensor, steps: int):
    """Unroll the predictor on its own outputs: ``(N, context, C, H, W) -> (N, steps, C, H, W)``;
    each step slides the window (the oldest latent out, the prediction in)."""
    predictions = []
    for _ in range(steps):
        z_next = predictor(window)
        predictions.append(z_next)
        window = torch.cat([window[:, 1:], z_next[:, None]], dim=1)
    return torch.stack(predictions, dim=1)


def rollout_loss(predictor: Predictor, z: torch.Tensor, context: int = 2, steps: int = 4,
                 detach_later: bool = False) -> torch.Tensor:
    """The autoregressive K-step MSE over latents ``z (B, T, C, H, W)``, a 0-d tensor: from every
    start ``s``, K = ``steps`` steps from the true ``z_s .. z_{s+context-1}``, prediction ``k``
    against ``z_{s+context-1+k}``. ``detach_later``: orders 2..K on ``z.detach()``."""
    _check_args(z, context, steps)
    if detach_later and steps > 1:
        n = z.shape[1] - context - steps + 1  # the order-1 term of the same n starts
        first = rollout_loss(predictor, z[:, :n + context], context, 1)
        later = _rollouts(predictor, z.detach(), context, steps)
        return (first + (steps - 1) * F.mse_loss(*(x[:, 1:] for x in later))) / steps
    return F.mse_loss(*_rollouts(predictor, z, context, steps))


def _rollouts(predictor: Predictor, z: torch.Tensor, context: int, steps: int):
    """Predictions and targets ``(B * n, K, C, H, W)`` of the rollouts from every start."""
    n = z.shape[1] - context - steps + 1  # rollouts per clip, one per start frame
    windows = torch.stack([z[:, j:j + n] for j in range(context)], dim=2)  # (B, n, ctx, C, H, W)
    targets = torch.stack([z[:, context + k:context + k + n] for k in range(steps)], dim=2)
    return rollout(predictor, windows.flatten(0, 1), steps), targets.flatten(0, 1)


def parallel_unroll(predictor: Predictor, z: torch.Tensor, context: int = 2, steps: int = 4):
    """The paper's parallel unroll of ``z (B, T, C, H, W)``: ``steps`` tensors ``(B, T - context,
    C, H, W)``; step k predicts each frame t >= context from frames t - context .. t - 1 of step
    k-1's sequence (the true latents at step 1; the true first ``context`` kept)."""
    _check_args(z, context, steps)
    sequence, out = z, []
    for _ in range(steps):
        n = sequence.shape[1] - context  # one window per predicted frame
        windows = torch.stack([sequence[:, j:j + n] for j in range(context)], dim=2)
        predictions = predictor(windows.flatten(0, 1)).unflatten(0, windows.shape[:2])
        out.append(predictions)
        sequence = torch.cat([z[:, :context], predictions], dim=1)
    return out


def parallel_rollout_loss(predictor: Predictor, z: torch.Tensor, context: int = 2,
                          steps: int = 4, detach_later: bool = False) -> torch.Tensor:
    """The K-step loss of the paper's parallel unroll (its Eqs. 8 to 10), averaged over the
    predicted frames as the course does, over latents ``z`` ``(B, T, C, H, W)``:

        L_pred = (1/K) sum_k 1/(B (T-c) C H W) sum_{b, t >= c} ||z~^(k)_{b,t} - z_{b,t}||^2

    with ``c`` the context and ``z~^(k)`` step k of :func:`parallel_unroll`. ``detach_later``
    (the course's, not the paper's): steps 2..K unroll from, and aim at, ``z.detach()``."""
    errors = []
    if detach_later and steps > 1:  # step 1 on the latents, steps 2..K on detached ones
        errors.append(parallel_rollout_loss(predictor, z, context, 1))
        z = z.detach()
    predictions = parallel_unroll(predictor, z, context, steps)[len(errors):]
    errors += [F.mse_loss(p, z[:, context:]) for p in predictions]
    return torch.stack(errors).mean()


UNROLLS = {"autoregressive": rollout_loss, "parallel": parallel_rollout_loss}  # name -> loss
