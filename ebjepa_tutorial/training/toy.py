"""Notebook 00's joint embedding small enough to watch: 2-D points around ``k`` centres, their
noisy views (two views of a point are a compatible pair), an MLP encoder."""

import torch
from torch import nn

from ..losses import covariance_matrix


def make_blobs(n: int, k: int = 6, radius: float = 2.0, spread: float = 0.3,
               seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` points around ``k`` centres on a circle: points ``(n, 2)`` and labels ``(n,)``."""
    generator = torch.Generator().manual_seed(seed)
    labels = torch.randint(0, k, (n,), generator=generator)
    angle = 2 * torch.pi * labels / k
    centres = radius * torch.stack([angle.cos(), angle.sin()], dim=1)
    return centres + spread * torch.randn(n, 2, generator=generator), labels


def two_views(x: torch.Tensor, noise: float,
              generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Two noisy copies of ``x`` ``(N, 2)``: the compatible pairs of the energy."""
    noise_a = torch.randn(x.shape, generator=generator)
    noise_b = torch.randn(x.shape, generator=generator)
    return x + noise * noise_a, x + noise * noise_b


def mlp_encoder(embed_dim: int = 8, hidden: int = 64, in_dim: int = 2) -> nn.Sequential:
    """A 3-layer MLP ``(N, in_dim) -> (N, embed_dim)``."""
    return nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(),
                         nn.Linear(hidden, hidden), nn.ReLU(),
                         nn.Linear(hidden, embed_dim))


@torch.no_grad()
def spectrum(z: torch.Tensor) -> torch.Tensor:
    """Eigenvalues of the covariance of ``z`` ``(N, D)``, largest first: ``(D,)``."""
    return torch.linalg.eigvalsh(covariance_matrix(z)).flip(0).clamp_min(0)


@torch.no_grad()
def energy_map(encoder: nn.Module, anchor: torch.Tensor, extent: float = 3.5,
               resolution: int = 80) -> tuple[torch.Tensor, torch.Tensor]:
    """``E(anchor, y) = ||enc(anchor) - enc(y)||^2`` for ``anchor (2,)`` and ``y`` on a grid
    over ``[-extent, extent]^2``: the grid's coordinates ``(R,)`` and the energies ``(R, R)``
    (rows: y)."""
    coords = torch.linspace(-extent, extent, resolution)
    grid_y, grid_x = torch.meshgrid(coords, coords, indexing="ij")
    points = torch.stack([grid_x.flatten(), grid_y.flatten()], dim=1)
    z_anchor = encoder(anchor[None])
    energy = (encoder(points) - z_anchor).pow(2).sum(dim=1)
    return coords, energy.reshape(resolution, resolution)
