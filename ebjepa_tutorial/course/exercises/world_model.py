"""Checkers of chapter 05: the temporal-similarity and inverse-dynamics terms on latents ``z``
``(B, T, D)``, values and gradients with respect to the latents."""

from __future__ import annotations

import torch

from ...losses import world as world_losses
from .common import Case, Exercise, slips


def _trajectory_latents() -> list[Case]:
    g = torch.Generator().manual_seed(3)
    drift = torch.linspace(0, 1, 9)[None, :, None] * torch.tensor([[[1.0, -2.0, 0.5, 0.0]]])
    return [
        Case("random latents z of shape (4, 17, 8)", (torch.randn(4, 17, 8, generator=g),)),
        Case("latents that never change in time (5, 6, 3)",
             (torch.randn(5, 1, 3, generator=g).expand(5, 6, 3),)),
        Case("latents moving at a constant speed (1, 9, 4)", (drift,)),
        Case("the shortest sequences, 2 frames (3, 2, 5)", (torch.randn(3, 2, 5, generator=g),)),
        Case("latents with std about 4, shape (2, 10, 6)",
             (4 * torch.randn(2, 10, 6, generator=g),)),
        Case("float64 latents (3, 5, 7)", (torch.randn(3, 5, 7, generator=g,
                                                       dtype=torch.float64),)),
    ]


def _change(z: torch.Tensor) -> torch.Tensor:
    return z[:, 1:] - z[:, :-1]


check_temporal_similarity = Exercise(
    "temporal_similarity", world_losses.temporal_similarity_loss, slips(
        "temporal_similarity", unsquared=lambda z: _change(z).norm(dim=-1).mean(),
        absolute=lambda z: _change(z).abs().mean(), summed=lambda z: _change(z).pow(2).sum(),
        earlier_detached=lambda z: (z[:, 1:] - z[:, :-1].detach()).pow(2).mean(),
        later_detached=lambda z: (z[:, 1:].detach() - z[:, :-1]).pow(2).mean(),
        wrong_axis=lambda z: world_losses.temporal_similarity_loss(z.transpose(0, 1))),
    _trajectory_latents, grad=[(0, "the latents z")], dims={0: "BTD"})


def _linear_inverse_model(latent_dim: int, action_dim: int, seed: int, dtype=torch.float32):
    """A fixed random map ``g(z_t, z_next) = W [z_t, z_next] + b``: ``(..., D) x2 -> (..., A)``."""
    g = torch.Generator().manual_seed(seed)
    weight = torch.randn(2 * latent_dim, action_dim, generator=g, dtype=dtype) / latent_dim**0.5
    bias = torch.randn(action_dim, generator=g, dtype=dtype)

    def predict_actions(z, z_next):
        return torch.cat([z, z_next], dim=-1) @ weight + bias

    return predict_actions


def _difference_model(z, z_next):
    """``g(z_t, z_next) = (z_next - z_t)[..., :2]``: right only when frames are in order."""
    return (z_next - z)[..., :2]


def _inverse_cases() -> list[Case]:
    """``(predict_actions, z (B, T, D), actions (B, T - 1, A))``."""
    g, cases = torch.Generator().manual_seed(4), []
    for b, t, d, a, dtype in [(4, 17, 8, 2, torch.float32), (3, 2, 5, 2, torch.float32),
                              (2, 9, 6, 3, torch.float32), (5, 7, 4, 2, None),
                              (3, 6, 5, 3, torch.float64)]:
        model = _difference_model if dtype is None else _linear_inverse_model(d, a, b, dtype)
        what = ("g(z_t, z_next) = (z_next - z_t)[:2]" if dtype is None
                else f"a fixed linear g with {a}-d actions")
        what += " in float64" if dtype == torch.float64 else ""
        cases.append(Case(f"{what}, latents ({b}, {t}, {d}) and actions ({b}, {t - 1}, {a})",
                          (model, torch.randn(b, t, d, generator=g, dtype=dtype),
                           torch.randn(b, t - 1, a, generator=g, dtype=dtype))))
    return cases


def _pairs(g, z, a, earlier=lambda z: z, later=lambda z: z):
    return g(earlier(z[:, :-1]), later(z[:, 1:])) - a


check_inverse_dynamics = Exercise(
    "inverse_dynamics", world_losses.inverse_dynamics_loss, slips(
        "inverse_dynamics",
        wrong_order=lambda g, z, a: (g(z[:, 1:], z[:, :-1]) - a).pow(2).mean(),
        unsquared=lambda g, z, a: _pairs(g, z, a).norm(dim=-1).mean(),
        absolute=lambda g, z, a: _pairs(g, z, a).abs().mean(),
        summed=lambda g, z, a: _pairs(g, z, a).pow(2).sum(),
        later_detached=lambda g, z, a: _pairs(g, z, a, later=torch.detach).pow(2).mean(),
        earlier_detached=lambda g, z, a: _pairs(g, z, a, earlier=torch.detach).pow(2).mean()),
    _inverse_cases, grad=[(1, "the latents z")], dims={1: "BTD", 2: "__A"})
