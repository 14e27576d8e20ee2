"""Checkers of chapters 00-01: the variance and covariance terms, the VICReg loss, the
conversion of the VICReg paper's coefficients to EB-JEPA's."""

from __future__ import annotations

from collections.abc import Callable

import torch

from ... import losses
from .common import Case, ExerciseError, _call, _describe, compare, exercise


def _embedding_cases(seed: int = 0) -> list[Case]:
    g = torch.Generator().manual_seed(seed)
    return [
        Case("a random batch z of shape (32, 8)", (torch.randn(32, 8, generator=g),)),
        Case("a collapsed batch (every row the same)", (torch.ones(16, 4),)),
        Case("a batch with std about 3", (3 * torch.randn(64, 5, generator=g),)),
        Case("a batch of 2 rows", (torch.randn(2, 3, generator=g),)),
        Case("a batch with correlated dimensions",
             (torch.randn(40, 1, generator=g) * torch.tensor([[1.0, -2.0, 0.5]]),)),
    ]


@exercise(losses.variance_term)
def check_variance_term(fn: Callable) -> bool:
    """Notebook 00 and 01: ``variance_term(z, gamma=1.0, eps=1e-4)`` on ``(B, D)``."""
    cases = _embedding_cases() + [
        Case("gamma=2.0", (torch.randn(32, 4, generator=torch.Generator().manual_seed(1)),),
             {"gamma": 2.0}),
    ]
    return compare(fn, losses.variance_term, cases)


@exercise(losses.covariance_term)
def check_covariance_term(fn: Callable) -> bool:
    """Notebook 00 and 01: ``covariance_term(z)`` on ``(B, D)``."""
    return compare(fn, losses.covariance_term, _embedding_cases(seed=2))


def _vicreg_total(z_a, z_b, inv_coeff, std_coeff, cov_coeff):
    return losses.vicreg_loss(z_a, z_b, inv_coeff, std_coeff, cov_coeff)[0]


@exercise(_vicreg_total)
def check_vicreg(fn: Callable) -> bool:
    """Notebook 01: ``vicreg(z_a, z_b, inv_coeff, std_coeff, cov_coeff)`` -> a 0-d tensor.

    Two views ``(B, D)``; the variance and covariance terms are computed on each
    view and averaged, as :func:`losses.vicreg_loss` does.
    """
    g = torch.Generator().manual_seed(5)
    z = torch.randn(32, 8, generator=g)
    mixed = torch.randn(48, 1, generator=g) * torch.tensor([[1.0, -0.5, 2.0, 0.1]])
    cases = [
        Case("two random views (32, 8), coefficients 1, 1, 80",
             (z, z + 0.3 * torch.randn(32, 8, generator=g), 1.0, 1.0, 80.0)),
        Case("views with different spreads (std 0.5 and 3), coefficients 25, 25, 1",
             (0.5 * torch.randn(64, 6, generator=g), 3 * torch.randn(64, 6, generator=g),
              25.0, 25.0, 1.0)),
        Case("only the variance weight set (0, 1, 0), views of std 0.2 and 0.8",
             (0.2 * torch.randn(16, 5, generator=g), 0.8 * torch.randn(16, 5, generator=g),
              0.0, 1.0, 0.0)),
        Case("only the covariance weight set (0, 0, 1), one view correlated",
             (mixed + 0.1 * torch.randn(48, 4, generator=g), torch.randn(48, 4, generator=g),
              0.0, 0.0, 1.0)),
        Case("two identical collapsed views (every row the same), coefficients 2, 3, 4",
             (torch.ones(8, 3), torch.ones(8, 3), 2.0, 3.0, 4.0)),
    ]
    return compare(fn, _vicreg_total, cases)


def _vicreg_paper_to_ebjepa(inv: float, std: float, cov: float, dim: int) -> tuple:
    """Reference: VICReg-paper coefficients -> EB-JEPA coefficients (invariance weight 1).

    The covariance sum is divided by ``D`` in one and by ``D (D - 1)`` in the
    other, so its weight grows by ``D - 1``; dividing every weight by the
    invariance weight leaves the loss's shape unchanged (only its scale).
    """
    return 1.0, std / inv, cov * (dim - 1) / inv


@exercise(_vicreg_paper_to_ebjepa)
def check_vicreg_paper_to_ebjepa(fn: Callable) -> bool:
    """Notebook 01: ``vicreg_paper_to_ebjepa(inv, std, cov, dim)`` -> three floats."""
    name = getattr(fn, "__name__", "your function")
    labels = ("invariance", "variance", "covariance")
    cases = [(25.0, 25.0, 1.0, 2048), (25.0, 25.0, 1.0, 8192), (10.0, 25.0, 1.0, 1024),
             (5.0, 5.0, 1.0, 128), (2.0, 1.0, 0.5, 3)]
    for inv, std, cov, dim in cases:
        where = f"inv={inv:g}, std={std:g}, cov={cov:g}, dim={dim}"
        got = _call(fn, name, Case(where, (inv, std, cov, dim)))
        if isinstance(got, torch.Tensor) or not hasattr(got, "__len__") or len(got) != 3:
            raise ExerciseError(
                f"{name} returned {_describe(got)} on {where}; expected a tuple of three "
                "numbers (invariance, variance, covariance weights)."
            )
        try:
            values = [float(v) for v in got]
        except (TypeError, ValueError):
            raise ExerciseError(f"{name} returned {got!r} on {where}; expected numbers.") from None
        expected = _vicreg_paper_to_ebjepa(inv, std, cov, dim)
        for label, value, answer in zip(labels, values, expected):
            if abs(value - answer) > 1e-6 * max(1.0, abs(answer)):
                raise ExerciseError(
                    f"{name} gave {label} weight {value:.6g} on {where}, but the answer is "
                    f"{answer:.6g} (all three: {tuple(round(a, 6) for a in expected)})."
                )
    print(f"Correct: {name} matches the reference on {len(cases)} test inputs.")
    return True
