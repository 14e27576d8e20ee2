"""How well a distance between latents knows the way round the walls (notebook 07)."""

from __future__ import annotations

import torch

from ..envs import random_layouts, render, sample_positions
from ..envs.two_rooms import shortest_path_length


@torch.no_grad()
def cost_calibration(model, head, n: int = 512, walls: int = 1, seed: int = 0,
                     rooms=None) -> dict[str, torch.Tensor]:
    """``n`` pairs of dot positions in fresh layouts, from the rooms ``rooms = (a_room,
    b_room)`` (0 the leftmost; None: anywhere), each measured three ways: ``{"shortest": px
    of the shortest way, "head": head(z_a, z_b) in px, "latent": ||z_a - z_b||}``, ``(n,)``
    each on the CPU."""
    generator = torch.Generator().manual_seed(seed)
    layouts = random_layouts(n, generator, walls)
    picks = (None, None) if rooms is None else (torch.full((n,), r) for r in rooms)
    a, b = (sample_positions(layouts, generator, room) for room in picks)
    device = next(model.parameters()).device
    z_a, z_b = (model.encode(render(p, layouts).to(device)) for p in (a, b))
    return {"shortest": shortest_path_length(a, b, layouts),
            "head": head(z_a, z_b).cpu(), "latent": (z_a - z_b).norm(dim=-1).cpu()}


def correlation(x: torch.Tensor, y: torch.Tensor) -> float:
    """Pearson's correlation of two ``(n,)`` tensors."""
    return torch.corrcoef(torch.stack([x.float(), y.float()]))[0, 1].item()
