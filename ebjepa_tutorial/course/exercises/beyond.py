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


def _violation(hinge=F.relu, power=2, reduce=torch.mean, swapped=False):
    def step_violation(step_distance, step_length):
        over = step_length - step_distance if swapped else step_distance - step_length
        return reduce(hinge(over).abs().pow(power))
    return step_violation


check_step_violation = Exercise(
    "step_violation", step_violation, dict(
        no_hinge=_violation(hinge=lambda x: x), swapped=_violation(swapped=True),
        unsquared=_violation(power=1), summed=_violation(reduce=torch.sum)),
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


def _spread(sign=1.0, hinge=F.softplus, reduce=torch.mean, cap=True):
    def spread_loss(distance, cap_):
        return reduce(hinge(sign * ((cap_ if cap else 0.0) - distance)))
    return spread_loss


check_spread_loss = Exercise(
    "spread_loss", spread_loss, dict(
        sign_flipped=_spread(sign=-1.0), relu=_spread(hinge=F.relu), no_cap=_spread(cap=False),
        summed=_spread(reduce=torch.sum)),
    _spread_cases, grad=[(0, "the distances")], dims={0: "B"})
