"""Checker of chapter 06: one MPPI update of the plan's mean and spread."""

from __future__ import annotations

from collections.abc import Callable

import torch

from ... import planning
from ...planning import mppi_update
from .common import Case, compare, exercise

_FLOAT32_STEP = 2.0**-24  # float32 keeps a number to within about this fraction of itself


def _mppi_cases() -> list[Case]:
    g = torch.Generator().manual_seed(7)
    actions = torch.randn(2, 10, 4, 2, generator=g)
    costs = 5 * torch.rand(2, 10, generator=g)
    large, tau = costs + 1e4, 0.1
    # Without subtracting the minimum, -S/tau is about -100,000 here; float32 rounds it to
    # within S/tau * 2^-24 each, so each weight may move by twice that, relatively, and the
    # mean and std by that much of the largest action. A valid softmax(-S/tau) stays inside.
    honest = 4 * _FLOAT32_STEP * float(large.max()) / tau * float(actions.abs().max())
    return [
        Case("2 episodes x 10 plans of 4 steps, Q=3, tau=0.5", (actions, costs, 3, 0.5)),
        Case("the same plans with tau=5 (softer weights)", (actions, costs, 3, 5.0)),
        Case("costs near 10,000 (exp(-S/tau) alone would underflow to 0/0)",
             (actions, large, 4, tau), atol=honest,
             why_loose="Note: on the costs near 10,000 your mean and std differ from the "
                       "course's by up to {diff:.1e}, which float32 explains and the check "
                       "accepts. Your weights do not subtract the minimum cost first: -S/tau "
                       "is then about -100,000, where float32 keeps only about three decimals "
                       "of the costs. Subtracting the minimum keeps the exponents small and "
                       "exact."),
        Case("Q=1 (only the best plan: std 0)", (actions, costs, 1, 1.0)),
        Case("Q=N=10 (every plan is an elite)", (actions, costs, 10, 1.0)),
        Case("one episode, 6 plans of 1 step", (torch.randn(1, 6, 1, 2, generator=g),
                                                torch.rand(1, 6, generator=g), 2, 0.3)),
        Case("float64 plans and costs", (actions[:1].double(), costs[:1].double(), 3, 0.5)),
    ]


def _mppi_slip(weights=None, std=None, elites_of=None, largest=False) -> Callable:
    """An MPPI update with one mistake: ``weights(elite_costs, tau)``, ``std(elites, w, mean)``,
    the number of elites ``elites_of(N, Q)``, or the ``largest`` costs taken as elites."""
    def mppi_update(actions, costs, elites, temperature):
        q = elites_of(actions.shape[1], elites) if elites_of else elites
        elite_costs, index = costs.topk(q, dim=1, largest=largest)
        elite = actions.gather(1, index[:, :, None, None].expand(-1, -1, *actions.shape[2:]))
        w = (weights or planning.mppi_weights)(elite_costs, temperature)[:, :, None, None]
        mean = (w * elite).sum(dim=1)
        if std is None:
            return mean, (w * (elite - mean[:, None]).pow(2)).sum(dim=1).sqrt()
        return mean, std(elite, w, mean)

    return mppi_update


def _shifted(costs: torch.Tensor) -> torch.Tensor:
    return costs - costs.min(dim=1, keepdim=True).values


_MPPI_HINTS = (
    "Keep the cheapest plans. Each pulls the new plan toward itself with a weight that "
    "falls exponentially with its cost, the temperature setting how fast; the new spread is "
    "how far the kept plans lie from the new mean, with the same weights.",
    "Per episode, the elites are the Q = elites plans of lowest cost (along axis 1 of costs, "
    "which is (B, N)); gathering them from actions (B, N, H, A) gives (B, Q, H, A). Weights: "
    "w_i = exp(-(S_i - S_min) / tau) divided by their sum over the Q elites (the same "
    "formula as a softmax of -(S - S_min) / tau over the elites; subtracting S_min keeps "
    "the exponentials from underflowing). Then mean = sum_i w_i a_i and std = "
    "sqrt(sum_i w_i (a_i - mean)^2), both sums over the elites: two (B, H, A) tensors.",
    "elite_costs, index = <the `elites` smallest costs of each episode and where they are: "
    "topk with largest=False, along dim 1>\n"
    "elite = <the plans at those indices, (B, Q, H, A): gather along dim 1, or index with a "
    "batch arange>\n"
    "w = <softmax over the elites of -(elite_costs - their minimum) / temperature>, shaped "
    "(B, Q, 1, 1)\n"
    "mean = <the sum over the elites (dim 1) of w * elite>\n"
    "std = <the square root of the sum over the elites of w * (elite - mean)^2>\n"
    "return mean, std",
)

_MPPI_SLIPS = [(words, _mppi_slip(**slip)) for words, slip in [
    ("your weights do not subtract the minimum cost: exp(-S / tau) underflows to 0 when the "
     "costs are large, and 0 / 0 gives NaN. Subtract the elites' minimum cost inside the "
     "exponential: it cancels in the ratio and keeps the exponents near 0.",
     {"weights": lambda s, tau: torch.exp(-s / tau) / torch.exp(-s / tau).sum(1, keepdim=True)}),
    ("you weighted all N sampled plans; MPPI weighs only the Q elites, the cheapest.",
     {"elites_of": lambda n, q: n}),
    ("you kept the Q most expensive plans: the elites are the cheapest.", {"largest": True}),
    ("you multiplied by the temperature; divide: exp(-(S - S_min) / tau), so that a larger "
     "tau gives softer weights.",
     {"weights": lambda s, tau: torch.softmax(-_shifted(s) * tau, dim=1)}),
    ("your weights grow with the cost: the exponent is -(S - S_min) / tau.",
     {"weights": lambda s, tau: torch.softmax(_shifted(s) / tau, dim=1)}),
    ("you gave every elite the same weight (the CEM update); MPPI weighs each by "
     "exp(-(S - S_min) / tau), normalised.",
     {"weights": lambda s, tau: torch.full_like(s, 1 / s.shape[1])}),
    ("your weights do not sum to 1: divide exp(-(S - S_min) / tau) by its sum over the "
     "elites.", {"weights": lambda s, tau: torch.exp(-_shifted(s) / tau)}),
    ("your std is the weighted variance: take its square root.",
     {"std": lambda a, w, m: (w * (a - m[:, None]).pow(2)).sum(1)}),
    ("your std ignores the weights (the plain std of the elites); use "
     "sqrt(sum_i w_i (a_i - mean)^2) with the new mean.", {"std": lambda a, w, m: a.std(1)}),
    ("your std ignores the weights (the plain std of the elites); use "
     "sqrt(sum_i w_i (a_i - mean)^2) with the new mean.",
     {"std": lambda a, w, m: a.std(1, unbiased=False)}),
    ("your std does not subtract the mean: sqrt(sum_i w_i (a_i - mean)^2).",
     {"std": lambda a, w, m: (w * a.pow(2)).sum(1).sqrt()}),
]]


@exercise(mppi_update, _MPPI_SLIPS, name="mppi_update", hints=_MPPI_HINTS,
          answers=(planning.mppi_weights, planning.weighted_mean_std, planning.select_elites))
def check_mppi_update(fn: Callable) -> bool:
    """Notebook 06: ``mppi_update(actions, costs, elites, temperature) -> (mean, std)``:
    ``actions (B, N, H, A)``, ``costs (B, N)`` -> two ``(B, H, A)`` tensors."""
    return compare(fn, mppi_update, _mppi_cases(), diagnoses=_MPPI_SLIPS,
                   parts=("mean", "std"))
