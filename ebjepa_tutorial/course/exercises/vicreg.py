"""Checkers of chapters 00-01: the variance and covariance terms on ``z`` ``(B, D)``, the VICReg
loss, and the conversion of the VICReg paper's coefficients to EB-JEPA's."""

from __future__ import annotations

import torch

from ... import losses
from .common import Case, Exercise, slips


def _embedding_cases(seed: int = 0) -> list[Case]:
    g = torch.Generator().manual_seed(seed)
    return [
        Case("a random batch z of shape (32, 8)", (torch.randn(32, 8, generator=g),)),
        Case("a collapsed batch (every row the same)", (torch.ones(16, 4),)),
        Case("a batch with std about 3", (3 * torch.randn(64, 5, generator=g),)),
        Case("a batch of 2 rows", (torch.randn(2, 3, generator=g),)),
        Case("a batch with correlated dimensions",
             (torch.randn(40, 1, generator=g) * torch.tensor([[1.0, -2.0, 0.5]]),)),
        Case("a float64 batch (12, 6)", (torch.randn(12, 6, generator=g, dtype=torch.float64),)),
    ]


def _hinge(std: torch.Tensor, gamma: float) -> torch.Tensor:
    return torch.relu(gamma - std).mean()


check_variance_term = Exercise(
    "variance_term", losses.variance_term, slips(
        "variance_term",
        biased_variance=lambda z, gamma=1.0: _hinge((z.var(0, unbiased=False) + 1e-4).sqrt(),
                                                    gamma),
        eps_missing=lambda z, gamma=1.0: _hinge(z.var(0).sqrt(), gamma),
        eps_outside=lambda z, gamma=1.0: _hinge(z.var(0).sqrt() + 1e-4, gamma),
        variance_not_std=lambda z, gamma=1.0: _hinge(z.var(0) + 1e-4, gamma),
        no_hinge=lambda z, gamma=1.0: (gamma - (z.var(0) + 1e-4).sqrt()).mean(),
        gamma_ignored=lambda z, gamma=1.0: _hinge((z.var(0) + 1e-4).sqrt(), 1.0),
        per_dimension=lambda z, gamma=1.0: torch.relu(gamma - (z.var(0) + 1e-4).sqrt()),
        wrong_axis=lambda z, gamma=1.0: losses.variance_term(z.T.contiguous(), gamma)),
    lambda: _embedding_cases() + [Case("gamma=2.0", (
        torch.randn(32, 4, generator=torch.Generator().manual_seed(1)),), {"gamma": 2.0})],
    grad=[(0, "z")], dims={0: "BD"})


def _covariance(z: torch.Tensor, centre: bool = True) -> torch.Tensor:
    centred = z - z.mean(dim=0) if centre else z
    return centred.T @ centred / (len(z) - 1)


def _off_diagonal(cov: torch.Tensor) -> torch.Tensor:
    return cov - torch.diag(torch.diagonal(cov))


def _per_pair(total: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    return total / (z.shape[1] * (z.shape[1] - 1))


check_covariance_term = Exercise(
    "covariance_term", losses.covariance_term, slips(
        "covariance_term",
        not_centred=lambda z: _per_pair(_off_diagonal(_covariance(z, False)).pow(2).sum(), z),
        diagonal_kept=lambda z: _per_pair(_covariance(z).pow(2).sum(), z),
        mean_of_all=lambda z: _covariance(z).pow(2).mean(),
        not_squared=lambda z: _per_pair(_off_diagonal(_covariance(z)).sum(), z),
        absolute=lambda z: _per_pair(_off_diagonal(_covariance(z)).abs().sum(), z),
        cov_of_rows=lambda z: _per_pair(_off_diagonal(torch.cov(z)).pow(2).sum(), z),
        wrong_axis=lambda z: losses.covariance_term(z.T.contiguous())),
    lambda: _embedding_cases(seed=2),
    grad=[(0, "z")], dims={0: "BD"})


def _vicreg_slip(views=lambda term, a, b: (term(a) + term(b)) / 2,
                 invariance=losses.invariance_term, swap=False):
    """A VICReg loss with one mistake: another rule ``views(term, z_a, z_b)`` for applying
    the variance and covariance terms, another ``invariance``, or ``swap``ped weights."""
    def vicreg(z_a, z_b, inv_coeff, std_coeff, cov_coeff):
        std_coeff, cov_coeff = (cov_coeff, std_coeff) if swap else (std_coeff, cov_coeff)
        return (inv_coeff * invariance(z_a, z_b)
                + std_coeff * views(losses.variance_term, z_a, z_b)
                + cov_coeff * views(losses.covariance_term, z_a, z_b))

    return vicreg


def _vicreg_cases() -> list[Case]:
    g = torch.Generator().manual_seed(5)
    z = torch.randn(32, 8, generator=g)
    mixed = torch.randn(48, 1, generator=g) * torch.tensor([[1.0, -0.5, 2.0, 0.1]])
    return [
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
        Case("two float64 views (16, 4), coefficients 1, 2, 3",
             (torch.randn(16, 4, generator=g, dtype=torch.float64),
              torch.randn(16, 4, generator=g, dtype=torch.float64), 1.0, 2.0, 3.0)),
    ]


# the weighted sum alone: what the learner writes, and what notebook 01's training step calls
check_vicreg = Exercise(
    "vicreg", losses.vicreg.vicreg, slips(
        "vicreg", views_added=_vicreg_slip(lambda term, a, b: term(a) + term(b)),
        one_view=(_vicreg_slip(lambda term, a, b: term(a)),
                  _vicreg_slip(lambda term, a, b: term(b))),
        views_stacked=_vicreg_slip(lambda term, a, b: term(torch.cat([a, b]))),
        weights_swapped=_vicreg_slip(swap=True),
        invariance_summed=_vicreg_slip(invariance=lambda a, b: (a - b).pow(2).sum(1).mean()),
        invariance_unsquared=_vicreg_slip(invariance=lambda a, b: (a - b).norm(dim=1).mean())),
    _vicreg_cases,
    grad=[(0, "the first view z_a"), (1, "the second view z_b")], dims={0: "BD"})


def _vicreg_paper_to_ebjepa(inv: float, std: float, cov: float, dim: int) -> tuple:
    """VICReg-paper coefficients -> EB-JEPA's: the paper divides the covariance sum by ``D``,
    EB-JEPA by ``D (D - 1)``, so its weight grows by ``D - 1``; all three are then divided by
    the invariance weight, which leaves the loss's shape unchanged (only its scale)."""
    return 1.0, std / inv, cov * (dim - 1) / inv


check_vicreg_paper_to_ebjepa = Exercise(
    "vicreg_paper_to_ebjepa", _vicreg_paper_to_ebjepa, slips(
        "vicreg_paper_to_ebjepa",
        factor_missing=lambda inv, std, cov, dim: (1.0, std / inv, cov / inv),
        times_d=lambda inv, std, cov, dim: (1.0, std / inv, cov * dim / inv),
        divided_by_factor=lambda inv, std, cov, dim: (1.0, std / inv, cov / (dim - 1) / inv),
        variance_not_divided=lambda inv, std, cov, dim: (1.0, std, cov * (dim - 1) / inv),
        not_divided=lambda inv, std, cov, dim: (inv, std, cov * (dim - 1)),
        divided_by_std=lambda inv, std, cov, dim: (inv / std, 1.0, cov * (dim - 1) / std)),
    lambda: [Case("inv={:g}, std={:g}, cov={:g}, dim={}".format(*args), args) for args in [
        (25.0, 25.0, 1.0, 2048), (25.0, 25.0, 1.0, 8192), (10.0, 25.0, 1.0, 1024),
        (5.0, 5.0, 1.0, 128), (2.0, 1.0, 0.5, 3)]],
    parts=("invariance weight", "variance weight", "covariance weight"), atol=1e-6)
