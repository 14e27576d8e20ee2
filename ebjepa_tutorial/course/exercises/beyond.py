"""Checkers of chapter 07: the cost-to-go head's TD targets and its expectile loss."""

from __future__ import annotations

from collections.abc import Callable

import torch

from ...losses.cost import cost_to_go_targets, expectile_loss
from .common import Case, compare, exercise


def _target_cases() -> list[Case]:
    g = torch.Generator().manual_seed(5)
    n = 12
    step_cost = 0.2 + 1.6 * torch.rand(n, generator=g)
    next_to_go = 40 * torch.rand(n, generator=g)
    offset = torch.tensor([0, 1, 2, 5, -1, -1, 3, 0, 16, -1, 1, 4])
    spent = torch.where(offset > 0, offset * 1.0 + 5 * torch.rand(n, generator=g), 0.0)
    tight = torch.tensor([0.5, 1.0, 2.0])
    return [
        Case("12 transitions: goals that are the state itself, the next frame, later frames "
             "of the same trajectory and other trajectories' frames",
             (step_cost, next_to_go, offset, spent)),
        Case("3 transitions whose data path is longer than the bootstrap (min picks dbar)",
             (torch.ones(3), tight, torch.tensor([2, 3, 4]), torch.tensor([9.0, 9.0, 9.0]))),
        Case("3 goals from elsewhere (offset -1; spent is meaningless there)",
             (torch.ones(3), tight, torch.full((3,), -1), torch.zeros(3))),
    ]


def _targets(reached=True, bound=torch.minimum, cost=True, bound_elsewhere=False):
    """A TD target with one mistake: no zero at the goal (``reached``), another ``bound``
    than the minimum with the data path, no step cost, or the data path used for goals
    from elsewhere too."""
    def cost_to_go_targets(step_cost, next_to_go, offset, spent):
        bootstrap = (step_cost if cost else 0.0) + next_to_go
        own = offset != 0 if bound_elsewhere else offset > 0
        target = torch.where(own, bound(bootstrap, spent), bootstrap)
        return torch.where(offset == 0, 0.0, target) if reached else target

    return cost_to_go_targets


_TARGET_SLIPS = [
    ("where the goal is the state itself (offset 0) the target must be 0: no step is needed "
     "to reach it. torch.where(offset == 0, 0.0, target).", _targets(reached=False)),
    ("you took the larger of the bootstrap and the data path; the trajectory shows a way "
     "of length `spent` exists, so the shortest way is at most that: torch.minimum.",
     _targets(bound=torch.maximum)),
    ("you ignored the data path: where the goal lies later on the same trajectory "
     "(offset > 0) the target is min(c + dbar, spent).", _targets(bound=lambda b, s: b)),
    ("you used the data path alone for goals on the same trajectory; the bootstrap "
     "c + dbar(s', g) can be shorter than the way the random walk took: take the minimum.",
     _targets(bound=lambda b, s: s)),
    ("the step's own cost is missing: the target is c(s, a) + dbar(s', g), the px spent "
     "on this step plus what is left after it.", _targets(cost=False)),
    ("offset -1 marks a goal from another trajectory: `spent` means nothing there, so use "
     "the bootstrap alone (torch.where(offset > 0, ...)).", _targets(bound_elsewhere=True)),
]


@exercise(cost_to_go_targets, _TARGET_SLIPS)
def check_cost_to_go_targets(fn: Callable) -> bool:
    """Notebook 07: ``cost_to_go_targets(step_cost, next_to_go, offset, spent) -> (B,)``."""
    return compare(fn, cost_to_go_targets, _target_cases(), diagnoses=_TARGET_SLIPS)


def _expectile_cases() -> list[Case]:
    g = torch.Generator().manual_seed(6)
    estimate, target = 30 * torch.rand(64, generator=g), 30 * torch.rand(64, generator=g)
    return [
        Case("64 estimates and targets, tau = 0.1", (estimate, target, 0.1)),
        Case("the same, tau = 0.5 (half the mean squared error)", (estimate, target, 0.5)),
        Case("every target above its estimate, tau = 0.2",
             (estimate[:8], estimate[:8] + 1 + torch.rand(8, generator=g), 0.2)),
    ]


def _expectile(weight_below=lambda tau: 1 - tau, power=2, reduce=torch.mean):
    def expectile_loss(estimate, target, tau):
        error = target - estimate
        weight = torch.where(error < 0, weight_below(tau), 1 - weight_below(tau))
        return reduce(weight * error.abs().pow(power))

    return expectile_loss


_EXPECTILE_SLIPS = [
    ("your weights are swapped: a target BELOW the estimate (error < 0) weighs 1 - tau, one "
     "above weighs tau, so that a small tau pulls the estimate down towards the shortest "
     "ways.", _expectile(weight_below=lambda tau: tau)),
    ("square the error: the expectile loss is weight * (target - estimate)^2 (with |error| "
     "you fit a quantile instead).", _expectile(power=1)),
    ("average over the batch (.mean()), do not sum.", _expectile(reduce=torch.sum)),
]


@exercise(expectile_loss, _EXPECTILE_SLIPS)
def check_expectile_loss(fn: Callable) -> bool:
    """Notebook 07: ``expectile_loss(estimate, target, tau)`` -> a 0-d tensor; value and
    gradient with respect to the estimate."""
    return compare(fn, expectile_loss, _expectile_cases(), diagnoses=_EXPECTILE_SLIPS,
                   grad=(0, "the estimates"))
