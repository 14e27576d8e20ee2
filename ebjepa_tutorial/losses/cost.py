"""The cost-to-go head's loss: the largest distance that no observed step exceeds (notebook 07).

The head ``d(z, g) = s ||f(z) - f(g)||`` is a distance between embeddings, so it
obeys the triangle inequality ``d(a, c) <= d(a, b) + d(b, c)`` whatever ``f`` is,
and a chain of short steps bounds a long way. The length of the shortest way
between two states is the LARGEST such distance under which no step of the data
is longer than the px its action asked for: squeeze every observed step, push
everything else apart (quasimetric RL, Wang et al., 2023):

    maximise    - mean softplus(C - d(z, g))              over pairs of frames of one layout
    subject to    mean relu(d(z_t, z_t+1) - |a_t|)^2 <= eps   over the data's steps

The softplus is a smooth hinge: pairs nearer than ``C`` are pushed apart,
farther ones hardly at all, so the push ends where the steps' constraint holds
it. A Lagrange multiplier holds the constraint (``training.cost``). Distances
here are in the head's units (``models.cost.COST_SCALE`` px), which sets how
soft the hinge is.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F


def _check_same_shape(a: torch.Tensor, b: torch.Tensor, names: str) -> None:
    if a.shape != b.shape:
        raise ValueError(f"{names} must have the same shape, got {tuple(a.shape)} and "
                         f"{tuple(b.shape)}")


def spread_loss(distance: torch.Tensor, cap: float) -> torch.Tensor:
    """``mean(softplus(cap - distance))``: lower as pairs ``(...)`` move apart, flat far past
    ``cap``."""
    return F.softplus(cap - distance).mean()


def step_violation(step_distance: torch.Tensor, step_length: torch.Tensor) -> torch.Tensor:
    """``mean(relu(step_distance - step_length)^2)``: how far the head stretches the data's
    steps beyond what their actions asked for (0 when none is longer). Same shapes."""
    _check_same_shape(step_distance, step_length, "step_distance and step_length")
    return F.relu(step_distance - step_length).square().mean()


def imagination_gap(imagined: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    """``mean ||imagined - true||^2`` over embeddings ``(B, k)``: how differently the head reads
    the predictor's imagined latents and the true ones they stand for."""
    _check_same_shape(imagined, true, "imagined and true")
    return (imagined - true).square().sum(dim=-1).mean()
