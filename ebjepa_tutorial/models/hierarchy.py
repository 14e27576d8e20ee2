"""A coarse world model for a two-level planner (notebook 07): ``stride`` steps at a time,

    z_{t+S} = z_t + W MLP([z_t, u_t / (S * MAX_STEP)])

where the macro-action ``u_t`` (px, ``(2,)``) is the sum of the next ``S`` actions. It reads and
writes the world model's latents, so its predictions are subgoals the flat planner can aim at.
"""

from __future__ import annotations

from types import SimpleNamespace

import torch
from torch import nn

from ..envs import MAX_STEP


class CoarseModel(nn.Module):
    """Latents ``stride`` steps apart: ``rollout(z0 (R, D), macro (R, H, 2)) -> (R, H, D)``."""

    def __init__(self, latent_dim: int, stride: int = 4, hidden: int = 256):
        super().__init__()
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
