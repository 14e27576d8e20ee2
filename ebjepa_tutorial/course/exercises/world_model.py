"""Checkers of chapter 05: the temporal-similarity and inverse-dynamics terms."""

from __future__ import annotations

from collections.abc import Callable

import torch

from ...losses import world as world_losses
from .common import Case, compare, exercise


def _trajectory_latents(seed: int = 3) -> list[Case]:
    """Latent sequences ``(B, T, D)`` of several kinds, for the chapter 05 checkers."""
    g = torch.Generator().manual_seed(seed)
    drift = torch.linspace(0, 1, 9)[None, :, None] * torch.tensor([[[1.0, -2.0, 0.5, 0.0]]])
    return [
        Case("random latents z of shape (4, 17, 8)", (torch.randn(4, 17, 8, generator=g),)),
        Case("latents that never change in time (5, 6, 3)",
             (torch.randn(5, 1, 3, generator=g).expand(5, 6, 3),)),
        Case("latents moving at a constant speed (1, 9, 4)", (drift,)),
        Case("the shortest sequences, 2 frames (3, 2, 5)", (torch.randn(3, 2, 5, generator=g),)),
        Case("latents with std about 4, shape (2, 10, 6)",
             (4 * torch.randn(2, 10, 6, generator=g),)),
    ]


@exercise(world_losses.temporal_similarity_loss)
def check_temporal_similarity(fn: Callable) -> bool:
    """Notebook 05: ``temporal_similarity(z)`` on latents ``(B, T, D)`` -> a 0-d tensor."""
    return compare(fn, world_losses.temporal_similarity_loss, _trajectory_latents())


def _linear_inverse_model(latent_dim: int, action_dim: int, seed: int) -> Callable:
    """A fixed random map ``g(z_t, z_next) = W [z_t, z_next] + b``: ``(..., D) x2 -> (..., A)``."""
    g = torch.Generator().manual_seed(seed)
    weight = torch.randn(2 * latent_dim, action_dim, generator=g) / latent_dim**0.5
    bias = torch.randn(action_dim, generator=g)

    def predict_actions(z, z_next):
        return torch.cat([z, z_next], dim=-1) @ weight + bias

    return predict_actions


def _difference_model(z, z_next):
    """``g(z_t, z_next) = (z_next - z_t)[..., :2]``: right only when frames are in order."""
    return (z_next - z)[..., :2]


@exercise(world_losses.inverse_dynamics_loss)
def check_inverse_dynamics(fn: Callable) -> bool:
    """Notebook 05: ``inverse_dynamics(predict_actions, z, actions)`` -> a 0-d tensor.

    ``z``: latents ``(B, T, D)``; ``actions``: ``(B, T-1, A)``; ``predict_actions``
    maps ``(z_t, z_next)``, each ``(..., D)``, to actions ``(..., A)``.
    """
    g = torch.Generator().manual_seed(4)
    cases = []
    for b, t, d, a, kind in [(4, 17, 8, 2, "random"), (3, 2, 5, 2, "random"),
                             (2, 9, 6, 3, "random"), (5, 7, 4, 2, "difference")]:
        model = _difference_model if kind == "difference" else _linear_inverse_model(d, a, b)
        what = ("g(z_t, z_next) = (z_next - z_t)[:2]" if kind == "difference"
                else f"a fixed linear g with {a}-d actions")
        cases.append(Case(
            f"{what}, latents ({b}, {t}, {d}) and actions ({b}, {t - 1}, {a})",
            (model, torch.randn(b, t, d, generator=g), torch.randn(b, t - 1, a, generator=g)),
        ))
    return compare(fn, world_losses.inverse_dynamics_loss, cases)
