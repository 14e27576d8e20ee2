"""Heads that sit on top of an encoder: the projector (or "expander") of joint-embedding SSL.

VICReg and SIGReg are applied to the projector's output ``z``, not to the
encoder's features ``y``: the regularisers can then reshape ``z`` freely
while ``y``, the representation we keep, stays more general. Features:
``(B, in_dim)`` -> projections ``(B, out_dim)``.
"""

from __future__ import annotations

from torch import nn


class Projector(nn.Sequential):
    """MLP ``(B, in_dim) -> (B, out_dim)``: ``depth - 1`` Linear-BN-ReLU layers, then a Linear.

    ``depth=3`` is the VICReg / EB-JEPA projector (notebooks 01-02; the video's has 2):
    Linear-BN-ReLU, Linear-BN-ReLU, Linear. The hidden Linears have no bias
    because the BatchNorm that follows removes it anyway.
    """

    def __init__(self, in_dim: int, hidden_dim: int, out_dim: int, depth: int):
        layers: list[nn.Module] = []
        width = in_dim
        for _ in range(depth - 1):
            layers += [nn.Linear(width, hidden_dim, bias=False), nn.BatchNorm1d(hidden_dim)]
            layers.append(nn.ReLU(inplace=True))
            width = hidden_dim
        layers.append(nn.Linear(width, out_dim))
        super().__init__(*layers)
        self.in_dim, self.out_dim = in_dim, out_dim


def build_projector(in_dim: int, hidden_dim: int, out_dim: int, depth: int) -> nn.Module:
    """A :class:`Projector`, or ``nn.Identity()`` when ``depth == 0`` (no projector).

    The identity keeps the regulariser on the encoder's features directly
    (then ``out_dim`` is ``in_dim``). Both have ``in_dim`` and ``out_dim`` attributes.
    """
    if depth == 0:
        identity = nn.Identity()
        identity.in_dim = identity.out_dim = in_dim
        return identity
    return Projector(in_dim, hidden_dim, out_dim, depth)
