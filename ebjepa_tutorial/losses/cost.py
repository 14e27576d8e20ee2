"""The cost-to-go head's two terms (notebook 07): the largest distance no observed step exceeds.

    maximise    - mean softplus(C - d(z, g))              over pairs of frames of one layout
    subject to    mean relu(d(z_t, z_t+1) - |a_t|)^2 <= eps   over the data's steps

Distances here are in the head's units (``models.cost.COST_SCALE`` px).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def spread_loss(distance: torch.Tensor, cap: float) -> torch.Tensor:
    """``mean(softplus(cap - distance))``: lower as pairs ``(...)`` move apart, flat far past
    ``cap``."""
    return F.softplus(cap - distance).mean()


def step_violation(step_distance: torch.Tensor, step_length: torch.Tensor) -> torch.Tensor:
    """``mean(relu(step_distance - step_length)^2)``: how far the head stretches the data's
    steps beyond what their actions asked for (0 when none is longer). Same shapes."""
    return F.relu(step_distance - step_length).square().mean()
