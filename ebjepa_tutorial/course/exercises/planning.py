"""Checker of chapter 06: one MPPI update of the plan's mean and spread."""

from __future__ import annotations

from collections.abc import Callable

import torch

from ... import planning
from ...planning import mppi_update
from .common import Case, _describe, compare, exercise


def _mppi_cases() -> list[Case]:
    g = torch.Generator().manual_seed(7)
    actions = torch.randn(2, 10, 4, 2, generator=g)
    costs = 5 * torch.rand(2, 10, generator=g)
    return [
        Case("2 episodes x 10 plans of 4 steps, Q=3, tau=0.5", (actions, costs, 3, 0.5)),
        Case("the same plans with tau=5 (softer weights)", (actions, costs, 3, 5.0)),
        Case("costs near 10,000 (exp(-S/tau) alone would underflow to 0/0)",
             (actions, costs + 1e4, 4, 0.1)),
        Case("Q=1 (only the best plan: std 0)", (actions, costs, 1, 1.0)),
        Case("Q=N=10 (every plan is an elite)", (actions, costs, 10, 1.0)),
        Case("one episode, 6 plans of 1 step", (torch.randn(1, 6, 1, 2, generator=g),
                                                torch.rand(1, 6, generator=g), 2, 0.3)),
    ]


def _stacked(fn: Callable) -> Callable:
    """``fn(...) -> (mean, std)`` as one tensor ``stack([mean, std])``, so ``compare`` sees both."""
    def run(*args, **kwargs):
        out = fn(*args, **kwargs)
        if not isinstance(out, tuple) or len(out) != 2:
            raise TypeError(f"it must return a pair (mean, std), got {_describe(out)}")
        return torch.stack(out)

    run.__name__ = getattr(fn, "__name__", "your function")
    return run


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


_MPPI_SLIPS = [(words, _mppi_slip(**slip)) for words, slip in [
    ("your weights do not subtract the minimum cost: exp(-S / tau) underflows to 0 when the "
     "costs are large, and 0 / 0 gives NaN. Use exp(-(S - S_min) / tau), e.g. "
     "torch.softmax(-(S - S_min) / tau, dim=1).",
     {"weights": lambda s, tau: torch.exp(-s / tau) / torch.exp(-s / tau).sum(1, keepdim=True)}),
    ("you weighted all N sampled plans; MPPI weighs only the Q elites "
     "(costs.topk(Q, dim=1, largest=False)).", {"elites_of": lambda n, q: n}),
    ("you kept the Q most expensive plans: the elites are the cheapest, topk(..., "
     "largest=False).", {"largest": True}),
    ("you multiplied by the temperature; divide: exp(-(S - S_min) / tau), so that a larger "
     "tau gives softer weights.",
     {"weights": lambda s, tau: torch.softmax(-_shifted(s) * tau, dim=1)}),
    ("your weights grow with the cost: the exponent is -(S - S_min) / tau.",
     {"weights": lambda s, tau: torch.softmax(_shifted(s) / tau, dim=1)}),
    ("you gave every elite the same weight (the CEM update); MPPI weighs each by "
     "exp(-(S - S_min) / tau), normalised.",
     {"weights": lambda s, tau: torch.full_like(s, 1 / s.shape[1])}),
    ("your weights do not sum to 1: divide exp(-(S - S_min) / tau) by its sum over the "
     "elites (torch.softmax does).", {"weights": lambda s, tau: torch.exp(-_shifted(s) / tau)}),
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


@exercise(mppi_update, _MPPI_SLIPS)
def check_mppi_update(fn: Callable) -> bool:
    """Notebook 06: ``mppi_update(actions, costs, elites, temperature) -> (mean, std)``.

    ``actions (B, N, H, A)``, ``costs (B, N)`` -> two ``(B, H, A)`` tensors, compared
    (stacked: mean first, then std) with :func:`ebjepa_tutorial.planning.mppi_update`.
    """
    slips = [(words, _stacked(variant)) for words, variant in _MPPI_SLIPS]
    return compare(_stacked(fn), _stacked(mppi_update), _mppi_cases(), diagnoses=slips,
                   parts=("mean", "std"))
