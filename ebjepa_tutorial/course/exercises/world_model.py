"""Checkers of chapter 05: the temporal-similarity and inverse-dynamics terms, values and
gradients with respect to the latents."""

from __future__ import annotations

from collections.abc import Callable

import torch

from ...losses import world as world_losses
from .common import Case, compare, exercise


def _trajectory_latents() -> list[Case]:
    """Latent sequences ``(B, T, D)`` of several kinds."""
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


_TEMPORAL_HINTS = (
    "An encoder watching a trajectory should move its latent only a little from one frame to "
    "the next. Measure each step's change of latent and penalise its size, on average.",
    "The T - 1 changes z_(t+1) - z_t run along axis 1, time; each is (B, D). Square every "
    "element and average over all B (T - 1) D of them: L = (1 / (B (T - 1) D)) * sum over "
    "b, t of ||z_(b,t+1) - z_(b,t)||^2, a 0-d tensor.",
    "changes = <z at times 1 .. T-1 minus z at times 0 .. T-2, slicing axis 1>\n"
    "return <the mean of changes squared, over every element>",
)

_TEMPORAL_SLIPS = [
    ("an unsquared distance ||z_t+1 - z_t||: the term is the mean *squared* change.",
     lambda z: _change(z).norm(dim=-1).mean()),
    ("you used the absolute change; the term squares it.",
     lambda z: _change(z).abs().mean()),
    ("you summed instead of averaging: the term is the mean over every element.",
     lambda z: _change(z).pow(2).sum()),
    ("the gradient reaches z_t+1 but not z_t: you detached the earlier latent of each pair; "
     "both latents of a pair must be pulled toward each other.",
     lambda z: (z[:, 1:] - z[:, :-1].detach()).pow(2).mean()),
    ("the gradient reaches z_t but not z_t+1: you detached the later latent of each pair; "
     "both latents of a pair must be pulled toward each other.",
     lambda z: (z[:, 1:].detach() - z[:, :-1]).pow(2).mean()),
]


@exercise(world_losses.temporal_similarity_loss, _TEMPORAL_SLIPS, name="temporal_similarity",
          hints=_TEMPORAL_HINTS)
def check_temporal_similarity(fn: Callable) -> bool:
    """Notebook 05: ``temporal_similarity(z)`` on latents ``(B, T, D)`` -> a 0-d tensor."""
    return compare(fn, world_losses.temporal_similarity_loss, _trajectory_latents(),
                   diagnoses=_TEMPORAL_SLIPS, grad=[(0, "the latents z")], dims={0: "BTD"},
                   swap=(0, 0, 1, "the batch and the time axes of z exchanged",
                         "Here z is (B, T, D): consecutive latents of one trajectory are "
                         "neighbours along axis 1, time, not along axis 0"),
                   factors={"D": "the change is averaged over the D dimensions too, not "
                                 "summed over them",
                            "T/(T - 1)": "T latents make T - 1 changes: average over those"})


def _linear_inverse_model(latent_dim: int, action_dim: int, seed: int,
                          dtype=torch.float32) -> Callable:
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


_INVERSE_HINTS = (
    "If the latent keeps what the agent did, a small head can read the action back from two "
    "consecutive latents. The loss scores that reading against the actions that were really "
    "taken, so that training makes the latent keep them.",
    "The pairs are (z_t, z_(t+1)) for t = 0 .. T - 2: the first T - 1 latents and the last "
    "T - 1 latents, each (B, T - 1, D). predict_actions takes all pairs in one call, the "
    "earlier latent first, and gives (B, T - 1, A), one action per pair, like actions. "
    "L = the mean over all B (T - 1) A elements of (predicted - a)^2.",
    "predicted = predict_actions(<latents 0 .. T-2>, <latents 1 .. T-1>)  # (B, T-1, A)\n"
    "return <the mean of (predicted - actions) squared>",
)

_INVERSE_SLIPS = [
    ("you gave g the pair in the wrong order: the action is read as g(z_t, z_t+1), the "
     "earlier latent first.",
     lambda g, z, a: (g(z[:, 1:], z[:, :-1]) - a).pow(2).mean()),
    ("an unsquared distance ||g - a||: the loss is the mean *squared* error.",
     lambda g, z, a: (g(z[:, :-1], z[:, 1:]) - a).norm(dim=-1).mean()),
    ("you used the absolute error; the loss is the mean squared error.",
     lambda g, z, a: (g(z[:, :-1], z[:, 1:]) - a).abs().mean()),
    ("you summed instead of averaging: the loss is the mean over every element.",
     lambda g, z, a: (g(z[:, :-1], z[:, 1:]) - a).pow(2).sum()),
    ("the gradient reaches z_t but not z_t+1: you detached the later latent of each pair; "
     "both latents must receive it.",
     lambda g, z, a: (g(z[:, :-1], z[:, 1:].detach()) - a).pow(2).mean()),
    ("the gradient reaches z_t+1 but not z_t: you detached the earlier latent of each pair; "
     "both latents must receive it.",
     lambda g, z, a: (g(z[:, :-1].detach(), z[:, 1:]) - a).pow(2).mean()),
]


@exercise(world_losses.inverse_dynamics_loss, _INVERSE_SLIPS, name="inverse_dynamics",
          hints=_INVERSE_HINTS)
def check_inverse_dynamics(fn: Callable) -> bool:
    """Notebook 05: ``inverse_dynamics(predict_actions, z, actions)`` -> a 0-d tensor.

    ``z``: latents ``(B, T, D)``; ``actions``: ``(B, T-1, A)``; ``predict_actions``
    maps ``(z_t, z_next)``, each ``(..., D)``, to actions ``(..., A)``. The gradient
    with respect to ``z`` is what makes the encoder keep the dot in the latent (only
    the dot explains the action).
    """
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
    return compare(fn, world_losses.inverse_dynamics_loss, cases, diagnoses=_INVERSE_SLIPS,
                   grad=[(1, "the latents z")], dims={1: "BTD", 2: "__A"},
                   factors={"A": "the error is averaged over the A action dimensions too, "
                                 "not summed over them"})
