"""The world model's loss (notebook 05), one function per term. For latents ``z`` ``(B, T, D)``
and the actions between frames ``(B, T-1, A)``, each term a mean over its elements:

    L = L_pred + alpha v(Z) + beta c(Z) + delta L_sim + omega L_idm  (paper 16, 8, 12, 1; K = 8)"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..utils import at_least_float32, mixed_precision
from .vicreg import covariance_term, variance_term


@dataclass(frozen=True)
class WorldLossCoeffs:
    """Weights of the terms; the defaults are the paper's (SIGReg, chapter 02's, off)."""

    prediction: float = 1.0
    variance: float = 16.0
    covariance: float = 8.0
    temporal: float = 12.0
    inverse_dynamics: float = 1.0
    sigreg: float = 0.0  # on every frame's latent, N-scaled


def _check_sequence(z: torch.Tensor, actions: torch.Tensor | None = None, steps: int = 1):
    if z.ndim != 3 or not 1 <= steps < z.shape[1]:
        raise ValueError(f"latents must be (batch, time, dim) with time > {steps} (the steps, "
                         f"at least 1); got {tuple(z.shape)} and {steps} steps")
    if actions is not None and (actions.ndim != 3 or actions.shape[:2] != z[:, 1:].shape[:2]):
        raise ValueError(f"actions must be (batch, time - 1, action_dim) = ({len(z)}, "
                         f"{z.shape[1] - 1}, A), one per step; got {tuple(actions.shape)}")


def with_still_steps(z: torch.Tensor, actions: torch.Tensor, stay: torch.Tensor):
    """Rollout windows with "still" steps (a planner at its goal must stand still; the data never
    does): ``z (N, K+1, D)``, ``actions (N, K, A)``, ``stay (N, K)`` bool -> the same shapes;
    where ``stay[n, k]``, step ``k`` takes a zero action and its target repeats the last frame."""
    moves = (~stay).long()
    frame = moves.cumsum(1)  # (N, K): the window's frame reached after each step
    rows = torch.arange(len(z), device=z.device)[:, None]
    taken = actions[rows, (frame - 1).clamp_min(0)] * moves[..., None]
    return torch.cat([z[:, :1], z[rows, frame]], dim=1), taken


def multistep_prediction_loss(
        predict: Callable, z: torch.Tensor, actions: torch.Tensor, steps: int = 8,
        detach_targets: bool = False, stay_probability: float = 0.0,
        generator: torch.Generator | None = None, rand: Callable = torch.rand) -> torch.Tensor:
    """The K-step loss from the first frame (the reference code's choice; the paper's Eq. 8 sums
    over every start frame), ``zhat_0 = z_0``, ``zhat_k = P(zhat_{k-1}, a_{k-1})``
    with ``predict(z (B, D), a (B, A)) -> (B, D)``, ``z (B, T, D)``, ``actions (B, T-1, A)``:

        L_pred = (1/K) sum_{k=1..K} (1/(B D)) sum_b ||zhat_k - z_k||^2,   K = steps <= T - 1

    Each step is still (:func:`with_still_steps`) with ``stay_probability``, drawn by ``rand``."""
    _check_sequence(z, actions, steps)
    if stay_probability:
        z, actions = z[:, : steps + 1], actions[:, :steps]
        stay = rand(len(z), steps, generator=generator) < stay_probability
        z, actions = with_still_steps(z, actions, stay.to(z.device))
    targets = z.detach() if detach_targets else z
    zhat, total = z[:, 0], z.new_zeros(())
    for k in range(1, steps + 1):
        zhat = predict(zhat, actions[:, k - 1])
        total = total + F.mse_loss(zhat, targets[:, k])
    return total / steps


def variance_covariance_loss(z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``v(Z)`` and ``c(Z)`` of ``(B, T, D)``, T >= 2, flattened to ``(B*T, D)`` (a dimension
    varying only along time, like the dot's position, counts as varied): two 0-d tensors."""
    _check_sequence(z)
    flat = z.reshape(-1, z.shape[-1])
    return variance_term(flat), covariance_term(flat)


def temporal_similarity_loss(z: torch.Tensor) -> torch.Tensor:
    """Mean squared change between consecutive latents ``(B, T, D)``, a 0-d tensor:

        L_sim = (1/(B (T-1) D)) sum_{b,t} ||z_{t+1} - z_t||^2"""
    _check_sequence(z)  # at least two frames: one frame has no change, and its mean is NaN
    return (z[:, 1:] - z[:, :-1]).pow(2).mean()


def inverse_dynamics_loss(predict_actions: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
                          z: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """Inverse dynamics ``g(z_t (..., D), z_{t+1} (..., D)) -> (..., A)`` against the actions:

        L_idm = (1/(B (T-1) A)) sum_{b,t} ||g(z_t, z_{t+1}) - a_t||^2"""
    return F.mse_loss(predict_actions(z[:, :-1], z[:, 1:]), actions)


def encode_for_loss(model, frames: torch.Tensor) -> torch.Tensor:
    """Frames ``(B, T, 2, 65, 65)`` -> float32 latents ``(B, T, D)`` (bf16 on a fast CUDA GPU)."""
    with mixed_precision(frames.device):
        z = model.encode(frames)
    return at_least_float32(z)
