"""The projector (or "expander"): features ``(B, in_dim)`` -> projections ``(B, out_dim)``.
VICReg and SIGReg shape the projections, so that the features, which we keep, stay general."""

from __future__ import annotations

from torch import nn


class Projector(nn.Sequential):
    """``depth - 1`` Linear-BN-ReLU layers (Linears without bias: the BN removes it), then a
    Linear. ``depth=3`` is the VICReg / EB-JEPA projector."""

    def __init__(self, in_dim: int, hidden_dim: int, out_dim: int, depth: int):
        layers, width = [], in_dim
        for _ in range(depth - 1):
            layers += [nn.Linear(width, hidden_dim, bias=False), nn.BatchNorm1d(hidden_dim),
                       nn.ReLU(inplace=True)]
            width = hidden_dim
        super().__init__(*layers, nn.Linear(width, out_dim))
        self.in_dim, self.out_dim = in_dim, out_dim


def build_projector(in_dim: int, hidden_dim: int, out_dim: int, depth: int) -> nn.Module:
    """A :class:`Projector`, or ``nn.Identity()`` when ``depth == 0`` (the regulariser then sees
    the features); both have ``in_dim`` and ``out_dim``."""
    if depth:
        return Projector(in_dim, hidden_dim, out_dim, depth)
    identity = nn.Identity()
    identity.in_dim = identity.out_dim = in_dim
    return identity
