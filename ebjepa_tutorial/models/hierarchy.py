"""A coarse world model for a two-level planner (notebook 07).

The flat planner imagines every one of 64 steps to see round the wall. A
coarse model steps ``stride`` environment steps at a time, so a plan of 16
coarse steps covers the same 64 steps for a quarter of the predictor calls:

    z_{t+S} = z_t + W MLP([z_t, u_t / (S * MAX_STEP)])

where the macro-action ``u_t`` (px, ``(2,)``) is the displacement the next ``S``
actions ask for (their sum). It reads and writes the world model's latents, so
its predictions are subgoals that the flat planner can aim at over a few steps.
"""

from __future__ import annotations

from types import SimpleNamespace

import torch
from torch import nn

from ..envs import MAX_STEP


class CoarseModel(nn.Module):
    """Latents ``stride`` steps apart: ``rollout(z0 (R, D), macro (R, H, 2)) -> (R, H, D)``."""

    def __init__(self, latent_dim: int, stride: int, hidden: int):
        super().__init__()  # stride >= 1: CoarseConfig checks it
        self.latent_dim, self.stride = latent_dim, stride
        self.config = SimpleNamespace(action_dim=2)  # what the planner reads
        self.body = nn.Sequential(nn.Linear(latent_dim + 2, hidden), nn.GELU(),
                                  nn.Linear(hidden, hidden), nn.GELU())
        self.out = nn.Linear(hidden, latent_dim)
        nn.init.zeros_(self.out.weight)  # an untrained step stands still
        nn.init.zeros_(self.out.bias)

    def predict(self, z: torch.Tensor, macro: torch.Tensor) -> torch.Tensor:
        """One coarse step: ``(R, D), (R, 2) -> (R, D)``."""
        scaled = macro / (self.stride * MAX_STEP)
        return z + self.out(self.body(torch.cat([z, scaled], dim=-1)))

    def rollout(self, z0: torch.Tensor, macro: torch.Tensor) -> torch.Tensor:
        z, out = z0, []
        for step in macro.unbind(1):
            z = self.predict(z, step)
            out.append(z)
        return torch.stack(out, dim=1)


def macro_actions(actions: torch.Tensor, stride: int) -> torch.Tensor:
    """Sum each ``stride`` consecutive actions: ``(N, T, 2) -> (N, T // stride, 2)``."""
    n, t, a = actions.shape
    return actions[:, : t - t % stride].reshape(n, t // stride, stride, a).sum(dim=2)
