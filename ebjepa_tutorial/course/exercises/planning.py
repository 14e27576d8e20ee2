"""Checker of chapter 06: one MPPI update of the plan's mean and spread."""

from __future__ import annotations

from collections.abc import Callable

import torch

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


@exercise(mppi_update)
def check_mppi_update(fn: Callable) -> bool:
    """Notebook 06: ``mppi_update(actions, costs, elites, temperature) -> (mean, std)``.

    ``actions (B, N, H, A)``, ``costs (B, N)`` -> two ``(B, H, A)`` tensors, compared
    (stacked: mean first, then std) with :func:`ebjepa_tutorial.planning.mppi_update`.
    """
    return compare(_stacked(fn), _stacked(mppi_update), _mppi_cases())
