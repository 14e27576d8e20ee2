"""Checker of chapter 06: one MPPI update of the plan's mean and spread, ``actions (B, N, H, A)``,
``costs (B, N)`` -> two ``(B, H, A)`` tensors."""

from __future__ import annotations

import torch

from ... import planning
from ...planning import mppi_update
from .common import TEXTS, Case, Exercise, slips

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
             (actions, large, 4, tau), atol=honest, why_loose=TEXTS["mppi_update"]["float32"]),
        Case("Q=1 (only the best plan: std 0)", (actions, costs, 1, 1.0)),
        Case("Q=N=10 (every plan is an elite)", (actions, costs, 10, 1.0)),
        Case("one episode, 6 plans of 1 step", (torch.randn(1, 6, 1, 2, generator=g),
                                                torch.rand(1, 6, generator=g), 2, 0.3)),
        Case("float64 plans and costs", (actions[:1].double(), costs[:1].double(), 3, 0.5)),
    ]


def _mppi_slip(weights=planning.mppi_weights, std=None, elites_of=None, largest=False):
    """An MPPI update with one mistake: ``weights(elite_costs, tau)``, ``std(elites, w, mean)``,
    the number of elites ``elites_of(N, Q)``, or the ``largest`` costs taken as elites."""
    def mppi_update(actions, costs, elites, temperature):
        q = elites_of(actions.shape[1], elites) if elites_of else elites
        elite_costs, index = costs.topk(q, dim=1, largest=largest)
        elite = actions.gather(1, index[:, :, None, None].expand(-1, -1, *actions.shape[2:]))
        w = weights(elite_costs, temperature)
        mean, spread = planning.weighted_mean_std(elite, w)
        return mean, spread if std is None else std(elite, w[:, :, None, None], mean)

    return mppi_update


def _shifted(costs: torch.Tensor) -> torch.Tensor:
    return costs - costs.min(dim=1, keepdim=True).values


check_mppi_update = Exercise(
    "mppi_update", mppi_update, slips(
        "mppi_update",
        no_min_shift=_mppi_slip(weights=lambda s, tau: torch.exp(-s / tau) / torch.exp(
            -s / tau).sum(1, keepdim=True)),
        all_samples=_mppi_slip(elites_of=lambda n, q: n), most_expensive=_mppi_slip(largest=True),
        times_tau=_mppi_slip(weights=lambda s, tau: torch.softmax(-_shifted(s) * tau, dim=1)),
        growing_weights=_mppi_slip(weights=lambda s, tau: torch.softmax(_shifted(s) / tau, 1)),
        equal_weights=_mppi_slip(weights=lambda s, tau: torch.full_like(s, 1 / s.shape[1])),
        unnormalised=_mppi_slip(weights=lambda s, tau: torch.exp(-_shifted(s) / tau)),
        variance=_mppi_slip(std=lambda a, w, m: (w * (a - m[:, None]).pow(2)).sum(1)),
        unweighted_std=(_mppi_slip(std=lambda a, w, m: a.std(1)),
                        _mppi_slip(std=lambda a, w, m: a.std(1, unbiased=False))),
        uncentred_std=_mppi_slip(std=lambda a, w, m: (w * a.pow(2)).sum(1).sqrt())),
    _mppi_cases, parts=("mean", "std"))
