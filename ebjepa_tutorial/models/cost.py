"""A learned cost-to-go on a world model's latents (notebook 07).

``d(z, g) = s ||f(z) - f(g)||`` estimates the length, in px of travel, of the shortest way from
the state encoded by ``z`` to the one encoded by ``g``; planned with it, a plan's cost is what is
left after it, ``S(a_1..a_H) = d(zhat_H, z_goal)``. A distance between embeddings, it is 0 from a
state to itself, symmetric and obeys the triangle inequality by construction.
"""

from __future__ import annotations

import torch
from torch import nn

COST_SCALE = 10.0  # px per unit of embedding distance: keeps f's outputs near 1 for 10-100 px


class CostToGo(nn.Module):
    """``d(z, g) = COST_SCALE ||f(z) - f(g)||``, ``f`` a GELU MLP ``D -> hidden -> hidden ->
    dims``: latents ``(..., D)`` and goals ``(..., D)`` (broadcast) -> ``(...)``."""

    def __init__(self, latent_dim: int, hidden: int = 256, dims: int = 32):
        super().__init__()
        self.latent_dim = latent_dim
        self.embed = nn.Sequential(nn.Linear(latent_dim, hidden), nn.GELU(),
                                   nn.Linear(hidden, hidden), nn.GELU(), nn.Linear(hidden, dims))

    def forward(self, z: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        return COST_SCALE * (self.embed(z) - self.embed(goal)).norm(dim=-1)


class WithLearnedCost(nn.Module):
    """A world model that plans with a cost-to-go head (``PlannerConfig(cost="learned")``): it
    encodes and imagines with ``world`` and scores with ``head``."""

    def __init__(self, world: nn.Module, head: CostToGo):
        super().__init__()
        if head.latent_dim != world.latent_dim:
            raise ValueError(f"the head reads latents of size {head.latent_dim}, the world "
                             f"model makes latents of size {world.latent_dim}")
        self.world, self.head = world, head

    @property
    def config(self):
        return self.world.config

    @property
    def latent_dim(self) -> int:
        return self.world.latent_dim

    def encode(self, frames: torch.Tensor) -> torch.Tensor:
        return self.world.encode(frames)

    def rollout(self, z0: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        return self.world.rollout(z0, actions)

    def cost_to_go(self, z: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        return self.head(z, goal)
