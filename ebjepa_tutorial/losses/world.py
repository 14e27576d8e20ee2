"""The loss of the action-conditioned world model (notebook 05), one function per term.

For latents ``z`` of a batch of trajectories ``(B, T, D)`` and the actions between their
frames ``(B, T-1, A)``, the paper trains the encoder, predictor and inverse-dynamics head on

    L = L_pred + alpha v(Z) + beta c(Z) + delta L_sim + omega L_idm

with alpha 16 (variance), beta 8 (covariance), delta 12 (temporal similarity), omega 1
(inverse dynamics) and K = 8 prediction steps; SIGReg (chapter 02) can join them. Every term
averages over its elements, so no coefficient depends on ``B``, ``T`` or ``D``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..utils import at_least_float32, mixed_precision
from .vicreg import covariance_term, variance_term


@dataclass(frozen=True)
class WorldLossCoeffs:
    """Weights of the terms; the defaults are the paper's."""

    prediction: float = 1.0
    variance: float = 16.0
    covariance: float = 8.0
    temporal: float = 12.0
    inverse_dynamics: float = 1.0
    sigreg: float = 0.0  # SIGReg on every frame's latent, N-scaled as in chapter 02 (0: off)


def _check_sequence(z: torch.Tensor, actions: torch.Tensor | None = None) -> None:
    if z.ndim != 3 or z.shape[1] < 2:
        raise ValueError(f"latents must be (batch, time >= 2, dim), got {tuple(z.shape)}")
    if actions is not None and (actions.ndim != 3 or actions.shape[:2] != z[:, 1:].shape[:2]):
        raise ValueError(f"actions must be (batch, time - 1, action_dim) = ({len(z)}, "
                         f"{z.shape[1] - 1}, A): one action between each pair of consecutive "
                         f"frames; got {tuple(actions.shape)}")


def with_still_steps(z: torch.Tensor, actions: torch.Tensor, stay: torch.Tensor):
    """Rollout windows with "still" steps spliced in: ``z (N, K+1, D)``, ``actions (N, K, A)``,
    ``stay (N, K)`` bool -> the same shapes.

    Where ``stay[n, k]``, step ``k`` takes a zero action and its target repeats the previous
    frame; elsewhere the window's next action and frame follow (a window with ``s`` stays ends
    ``s`` frames early). The data never stands still, but a planner at its goal must.
    """
    moves = (~stay).long()
    frame = moves.cumsum(1)  # (N, K): the window's frame reached after each step
    rows = torch.arange(len(z), device=z.device)[:, None]
    taken = actions[rows, (frame - 1).clamp_min(0)] * moves[..., None]
    return torch.cat([z[:, :1], z[rows, frame]], dim=1), taken


def multistep_prediction_loss(
    predict: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], z: torch.Tensor,
    actions: torch.Tensor, steps: int = 8, detach_targets: bool = False,
    stay_probability: float = 0.0, generator: torch.Generator | None = None,
    rand: Callable = torch.rand,
) -> torch.Tensor:
    """Mean squared error of ``steps``-step rollouts from the first frame under the true actions.

    ``zhat_0 = z_0``, ``zhat_k = P(zhat_{k-1}, a_{k-1})`` and

        L_pred = (1/K) sum_{k=1..K} (1/(B D)) sum_b ||zhat_k - z_k||^2

    (the paper's Eq. 8 also sums over later start frames; its code, and the course, do not).
    ``predict(z (B, D), a (B, A)) -> (B, D)``; ``z``: ``(B, T, D)``; ``actions``: ``(B, T-1, A)``;
    ``1 <= steps <= T-1``. With ``stay_probability > 0`` each step is, with that probability, a
    still step (:func:`with_still_steps`), drawn by ``rand`` (``torch.rand``'s signature) from
    ``generator``. Targets keep their gradient, as in the paper's code, unless ``detach_targets``.
    """
    _check_sequence(z, actions)
    if not 1 <= steps <= z.shape[1] - 1:
        raise ValueError(f"steps must be in 1..{z.shape[1] - 1} (T - 1), got {steps}")
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
    """``v(Z)`` and ``c(Z)`` (:mod:`~ebjepa_tutorial.losses.vicreg`) over every frame of
    ``(B, T, D)``, flattened to ``(B*T, D)``: a dimension that varies only along time, like the
    dot's position, counts as varied. Two 0-d tensors."""
    _check_sequence(z)
    flat = z.reshape(-1, z.shape[-1])
    return variance_term(flat), covariance_term(flat)


def temporal_similarity_loss(z: torch.Tensor) -> torch.Tensor:
    """Mean squared change between consecutive latents ``(B, T, D)``, a 0-d tensor:

        L_sim = (1/(B (T-1) D)) sum_{b,t} ||z_{t+1} - z_t||^2
    """
    return (z[:, 1:] - z[:, :-1]).pow(2).mean()


def inverse_dynamics_loss(predict_actions: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
                          z: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """MSE between the actions predicted from consecutive latents and the true ones:

        L_idm = (1/(B (T-1) A)) sum_{b,t} ||g(z_t, z_{t+1}) - a_t||^2

    ``predict_actions(z_t (..., D), z_next (..., D)) -> (..., A)``; ``z``: ``(B, T, D)``;
    ``actions``: ``(B, T-1, A)``.
    """
    return F.mse_loss(predict_actions(z[:, :-1], z[:, 1:]), actions)


def encode_for_loss(model, frames: torch.Tensor) -> torch.Tensor:
    """The latents the loss is computed on: frames ``(B, T, 2, 65, 65)`` -> ``(B, T, D)``
    float32 (the encoder, the costly part, in bf16 on a GPU)."""
    if not bool(model.input_stats_fitted):
        raise RuntimeError(
            "the model's input statistics are not set: call model.fit_input_stats(frames) "
            "on a few hundred training trajectories first (without it the faint dot channel "
            "is drowned by the walls and the latent tends to ignore the agent)")
    with mixed_precision(frames.device):
        z = model.encode(frames)
    return at_least_float32(z)
