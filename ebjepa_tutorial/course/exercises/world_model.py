"""Checkers of chapter 05: the temporal-similarity and inverse-dynamics terms, their values
and their gradients with respect to the latents."""

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


def _change(z: torch.Tensor) -> torch.Tensor:
    return z[:, 1:] - z[:, :-1]


_TEMPORAL_SLIPS = [
    ("you summed the squared change over the D dimensions (||z_t+1 - z_t||^2); the course "
     "averages over dimensions too: .pow(2).mean() over every element.",
     lambda z: _change(z).pow(2).sum(-1).mean()),
    ("an unsquared distance ||z_t+1 - z_t||: the term is the mean *squared* change.",
     lambda z: _change(z).norm(dim=-1).mean()),
    ("you used the absolute change; square it: .pow(2).mean().",
     lambda z: _change(z).abs().mean()),
    ("you took differences along the batch axis (z[1:] - z[:-1]); time is axis 1: "
     "z[:, 1:] - z[:, :-1].", lambda z: (z[1:] - z[:-1]).pow(2).mean()),
    ("you summed instead of averaging: .mean() over every element.",
     lambda z: _change(z).pow(2).sum()),
    ("your loss has the right value, but no gradient reaches the latents z: did you "
     ".detach() them? The term must pull the encoder's consecutive latents together.",
     lambda z: _change(z.detach()).pow(2).mean()),
    ("the gradient reaches z_t+1 but not z_t: you detached z[:, :-1]; both latents of a pair "
     "must be pulled toward each other.", lambda z: (z[:, 1:] - z[:, :-1].detach()).pow(2).mean()),
    ("the gradient reaches z_t but not z_t+1: you detached z[:, 1:]; both latents of a pair "
     "must be pulled toward each other.", lambda z: (z[:, 1:].detach() - z[:, :-1]).pow(2).mean()),
]


@exercise(world_losses.temporal_similarity_loss, _TEMPORAL_SLIPS)
def check_temporal_similarity(fn: Callable) -> bool:
    """Notebook 05: ``temporal_similarity(z)`` on latents ``(B, T, D)`` -> a 0-d tensor.

    Compares the value and the gradient with respect to ``z``.
    """
    return compare(fn, world_losses.temporal_similarity_loss, _trajectory_latents(),
                   diagnoses=_TEMPORAL_SLIPS, grad=(0, "the latents z"))


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


_INVERSE_SLIPS = [
    ("you gave g the pair in the wrong order: the action is read as g(z_t, z_t+1), that is "
     "predict_actions(z[:, :-1], z[:, 1:]).",
     lambda g, z, a: (g(z[:, 1:], z[:, :-1]) - a).pow(2).mean()),
    ("you summed the squared error over the A action dimensions; average over them too "
     "(.pow(2).mean() over every element).",
     lambda g, z, a: (g(z[:, :-1], z[:, 1:]) - a).pow(2).sum(-1).mean()),
    ("an unsquared distance ||g - a||: the loss is the mean *squared* error.",
     lambda g, z, a: (g(z[:, :-1], z[:, 1:]) - a).norm(dim=-1).mean()),
    ("you used the absolute error; the loss is the mean squared error.",
     lambda g, z, a: (g(z[:, :-1], z[:, 1:]) - a).abs().mean()),
    ("you summed instead of averaging: .mean() over every element.",
     lambda g, z, a: (g(z[:, :-1], z[:, 1:]) - a).pow(2).sum()),
    ("your loss has the right value, but no gradient reaches the latents z: did you "
     ".detach() them? Chapter 05: this gradient is what makes the encoder keep the dot in "
     "the latent (only the dot explains the action); without it only the head learns.",
     lambda g, z, a: (g(z[:, :-1].detach(), z[:, 1:].detach()) - a).pow(2).mean()),
    ("the gradient reaches z_t but not z_t+1: you detached z[:, 1:]; both latents must "
     "receive it.", lambda g, z, a: (g(z[:, :-1], z[:, 1:].detach()) - a).pow(2).mean()),
    ("the gradient reaches z_t+1 but not z_t: you detached z[:, :-1]; both latents must "
     "receive it.", lambda g, z, a: (g(z[:, :-1].detach(), z[:, 1:]) - a).pow(2).mean()),
]


@exercise(world_losses.inverse_dynamics_loss, _INVERSE_SLIPS)
def check_inverse_dynamics(fn: Callable) -> bool:
    """Notebook 05: ``inverse_dynamics(predict_actions, z, actions)`` -> a 0-d tensor.

    ``z``: latents ``(B, T, D)``; ``actions``: ``(B, T-1, A)``; ``predict_actions``
    maps ``(z_t, z_next)``, each ``(..., D)``, to actions ``(..., A)``. Compares the
    value and the gradient with respect to ``z``.
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
    return compare(fn, world_losses.inverse_dynamics_loss, cases, diagnoses=_INVERSE_SLIPS,
                   grad=(1, "the latents z"))
