"""Checkers of chapter 07: the two terms that fit the cost-to-go head."""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F

from ...losses.cost import spread_loss, step_violation
from .common import Case, compare, exercise


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


_VIOLATION_HINTS = (
    "A step of the head may come out shorter than the action that made it (the shortest "
    "way can be shorter than the walk), never longer. Only the excess counts, and it should "
    "count smoothly where the constraint starts to bite.",
    "The violation is the mean over the B steps of relu(d_step - l)^2: zero when the head's "
    "distance d_step is at most the action's length l, the squared excess otherwise. Both "
    "inputs are (B,); the result is a 0-d tensor.",
    "excess = <the part of step_distance - step_length above 0>\n"
    "return <the mean of excess squared>",
)

_VIOLATION_SLIPS = [
    ("a step SHORTER than its action breaks nothing (the shortest way may be shorter than "
     "the walk): keep only the excess, the part of step_distance - step_length above 0.",
     _violation(hinge=lambda x: x)),
    ("the excess is step_distance - step_length (the head's length beyond the action's), "
     "not the other way round.", _violation(swapped=True)),
    ("square the excess: a squared penalty is smooth where the constraint starts to bite.",
     _violation(power=1)),
    ("average over the steps, do not sum.", _violation(reduce=torch.sum)),
]


@exercise(step_violation, _VIOLATION_SLIPS, name="step_violation", hints=_VIOLATION_HINTS)
def check_step_violation(fn: Callable) -> bool:
    """Notebook 07: ``step_violation(step_distance, step_length)`` -> a 0-d tensor; value and
    gradient with respect to the step distances."""
    return compare(fn, step_violation, _violation_cases(), diagnoses=_VIOLATION_SLIPS,
                   grad=[(0, "the step distances")], dims={0: "B"})


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


_SPREAD_HINTS = (
    "Pairs of states should be pushed apart until they are about the cap apart, then hardly "
    "at all: a smooth hinge, large for close pairs, fading for far ones. Lower must be "
    "better, so the term falls as the distances grow.",
    "The spread is the mean over the pairs of softplus(C - d), where softplus(u) = "
    "log(1 + e^u): about C - d for pairs much closer than the cap C, near 0 for pairs far "
    "beyond it. distance is (B,), cap a float; the result is a 0-d tensor.",
    "return <the mean of softplus(cap - distance)>  # softplus is in torch.nn.functional",
)

_SPREAD_SLIPS = [
    ("the sign is flipped: softplus(distance - cap) grows as pairs move apart, so descending "
     "it pulls them together. The argument is cap - distance.", _spread(sign=-1.0)),
    ("use the smooth hinge softplus, not relu: with relu a pair past the cap gets no push at "
     "all, and one just inside it a full one.", _spread(hinge=F.relu)),
    ("the cap is missing: softplus(cap - distance), so the push fades for pairs already far "
     "apart.", _spread(cap=False)),
    ("average over the pairs, do not sum.", _spread(reduce=torch.sum)),
]


@exercise(spread_loss, _SPREAD_SLIPS, name="spread_loss", hints=_SPREAD_HINTS)
def check_spread_loss(fn: Callable) -> bool:
    """Notebook 07: ``spread_loss(distance, cap)`` -> a 0-d tensor; value and gradient with
    respect to the distances."""
    return compare(fn, spread_loss, _spread_cases(), diagnoses=_SPREAD_SLIPS,
                   grad=[(0, "the distances")], dims={0: "B"})
