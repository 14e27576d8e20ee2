"""Checkers of chapter 07: the two terms that fit the cost-to-go head, on ``(B,)`` distances."""

import torch
import torch.nn.functional as F

from .common import Case, Exercise


def step_violation(step_distance, step_length):
    """The course's answer: ``mean(relu(step_distance - step_length)^2)``, a 0-d tensor."""
    return F.relu(step_distance - step_length).square().mean()


def spread_loss(distance, cap):
    """The course's answer: ``mean(softplus(cap - distance))``, a 0-d tensor."""
    return F.softplus(cap - distance).mean()


def _violation_cases() -> list[Case]:
    g = torch.Generator().manual_seed(5)
    length = 0.02 + 0.16 * torch.rand(32, generator=g)  # head units: 0.2-1.8 px
    stretch = length * (0.5 + torch.rand(32, generator=g))  # some within, some beyond
    return [
        Case("32 steps, some stretched beyond their action, some not", (stretch, length)),
        Case("4 steps, every one within its action (no violation)",
             (length[:4] * 0.9, length[:4])),
        Case("4 steps, every one 0.1 beyond its action", (length[:4] + 0.1, length[:4])),
        Case("8 float64 steps", (stretch[:8].double(), length[:8].double())),
    ]


check_step_violation = Exercise(  # each slip: the answer with one mistake
    "step_violation", step_violation, dict(
        no_hinge=lambda d, length: (d - length).square().mean(),
        swapped=lambda d, length: F.relu(length - d).square().mean(),
        unsquared=lambda d, length: F.relu(d - length).mean(),
        summed=lambda d, length: F.relu(d - length).square().sum()),
    _violation_cases, grad=[(0, "the step distances")], dims={0: "B"})


def _spread_cases() -> list[Case]:
    g = torch.Generator().manual_seed(6)
    distance = 20 * torch.rand(64, generator=g)  # head units: 0-200 px
    return [
        Case("64 pair distances, cap 15", (distance, 15.0)),
        Case("the same, cap 5", (distance, 5.0)),
        Case("8 pairs all beyond the cap", (distance[:8] + 20, 15.0)),
        Case("16 float64 pair distances, cap 10", (distance[:16].double(), 10.0)),
    ]


check_spread_loss = Exercise(
    "spread_loss", spread_loss, dict(
        sign_flipped=lambda d, cap: F.softplus(d - cap).mean(),
        relu=lambda d, cap: F.relu(cap - d).mean(), no_cap=lambda d, cap: F.softplus(-d).mean(),
        summed=lambda d, cap: F.softplus(cap - d).sum()),
    _spread_cases, grad=[(0, "the distances")], dims={0: "B"})
