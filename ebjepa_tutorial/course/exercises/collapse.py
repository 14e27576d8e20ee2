"""Checkers of chapters 00-02, the terms that keep embeddings ``z`` ``(B, D)`` from collapsing:
VICReg's variance and covariance terms, its loss and the paper's coefficients in EB-JEPA's, and
SIGReg's Epps-Pulley statistic of one slice ``x`` ``(N,)``."""

from functools import partial

import torch

from ... import losses
from ...losses.sigreg import epps_pulley
from .common import Case, Exercise


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


check_variance_term = Exercise(
    "variance_term", losses.variance_term, dict(
        biased_variance=lambda z, gamma=1.0: torch.relu(
            gamma - (z.var(0, unbiased=False) + 1e-4).sqrt()).mean(),
        eps_missing=lambda z, gamma=1.0: torch.relu(gamma - z.var(0).sqrt()).mean(),
        eps_outside=lambda z, gamma=1.0: torch.relu(gamma - (z.var(0).sqrt() + 1e-4)).mean(),
        variance_not_std=lambda z, gamma=1.0: torch.relu(gamma - (z.var(0) + 1e-4)).mean(),
        no_hinge=lambda z, gamma=1.0: (gamma - (z.var(0) + 1e-4).sqrt()).mean(),
        gamma_ignored=lambda z, gamma=1.0: torch.relu(1.0 - (z.var(0) + 1e-4).sqrt()).mean(),
        eps_ignored=lambda z, gamma=1.0, eps=1e-4: torch.relu(
            gamma - (z.var(0) + 1e-4).sqrt()).mean(),
        per_dimension=lambda z, gamma=1.0: torch.relu(gamma - (z.var(0) + 1e-4).sqrt()),
        wrong_axis=lambda z, gamma=1.0: losses.variance_term(z.T.contiguous(), gamma)),
    lambda: _embedding_cases() + [Case("gamma=2.0", (
        torch.randn(32, 4, generator=torch.Generator().manual_seed(1)),), {"gamma": 2.0}),
        Case("eps=0.01 on a collapsed batch", (torch.ones(8, 3),), {"eps": 1e-2})],
    grad=[(0, "z")], dims={0: "BD"})


def _pair_mean(z, cov=losses.covariance_matrix, f=torch.square, diagonal=False):
    """``sum_{i != j} f(C_ij) / (D (D - 1))`` of ``C = cov(z)`` (``diagonal``: all i, j)."""
    c, d = cov(z), z.shape[1]
    return f(c if diagonal else c - torch.diag(torch.diagonal(c))).sum() / (d * (d - 1))


check_covariance_term = Exercise(
    "covariance_term", losses.covariance_term, dict(
        not_centred=lambda z: _pair_mean(z, cov=lambda z: z.T @ z / (len(z) - 1)),
        diagonal_kept=lambda z: _pair_mean(z, diagonal=True),
        mean_of_all=lambda z: losses.covariance_matrix(z).pow(2).mean(),
        not_squared=lambda z: _pair_mean(z, f=lambda c: c),
        absolute=lambda z: _pair_mean(z, f=torch.abs),
        cov_of_rows=lambda z: _pair_mean(z, cov=torch.cov),
        batch_by_batch=lambda z: _pair_mean(z, cov=lambda z: (z - z.mean(0)) @ (z - z.mean(0)).T
                                            / (len(z) - 1)),
        correlations=lambda z: _pair_mean(z, cov=lambda z: torch.corrcoef(z.T)),
        global_mean=lambda z: _pair_mean(z, cov=lambda z: (z - z.mean()).T @ (z - z.mean())
                                         / (len(z) - 1)),
        wrong_axis=lambda z: losses.covariance_term(z.T.contiguous())),
    lambda: _embedding_cases(seed=2),
    grad=[(0, "z")], dims={0: "BD"})


def _vicreg_slip(views=lambda term, a, b: (term(a) + term(b)) / 2,
                 invariance=losses.invariance_term, swap=False):
    """A VICReg loss with one mistake: another rule ``views(term, z_a, z_b)`` for the variance
    and covariance terms, another ``invariance``, or ``swap``ped weights."""
    def vicreg(z_a, z_b, inv_coeff, std_coeff, cov_coeff):
        std_coeff, cov_coeff = (cov_coeff, std_coeff) if swap else (std_coeff, cov_coeff)
        return (inv_coeff * invariance(z_a, z_b)
                + std_coeff * views(losses.variance_term, z_a, z_b)
                + cov_coeff * views(losses.covariance_term, z_a, z_b))
    return vicreg


def _vicreg_cases() -> list[Case]:
    g = torch.Generator().manual_seed(5)
    randn = partial(torch.randn, generator=g)
    z = randn(32, 8)
    mixed = randn(48, 1) * torch.tensor([[1.0, -0.5, 2.0, 0.1]])
    return [
        Case("two random views (32, 8), coefficients 1, 1, 80",
             (z, z + 0.3 * randn(32, 8), 1.0, 1.0, 80.0)),
        Case("views with different spreads (std 0.5 and 3), coefficients 25, 25, 1",
             (0.5 * randn(64, 6), 3 * randn(64, 6), 25.0, 25.0, 1.0)),
        Case("only the variance weight set (0, 1, 0), views of std 0.2 and 0.8",
             (0.2 * randn(16, 5), 0.8 * randn(16, 5), 0.0, 1.0, 0.0)),
        Case("only the covariance weight set (0, 0, 1), one view correlated",
             (mixed + 0.1 * randn(48, 4), randn(48, 4), 0.0, 0.0, 1.0)),
        Case("two identical collapsed views (every row the same), coefficients 2, 3, 4",
             (torch.ones(8, 3), torch.ones(8, 3), 2.0, 3.0, 4.0)),
        Case("two float64 views (16, 4), coefficients 1, 2, 3",
             (randn(16, 4, dtype=torch.float64), randn(16, 4, dtype=torch.float64),
              1.0, 2.0, 3.0)),
    ]


check_vicreg = Exercise(
    "vicreg", losses.vicreg.vicreg, dict(
        views_added=_vicreg_slip(lambda term, a, b: term(a) + term(b)),
        one_view=(_vicreg_slip(lambda term, a, b: term(a)),
                  _vicreg_slip(lambda term, a, b: term(b))),
        views_stacked=_vicreg_slip(lambda term, a, b: term(torch.cat([a, b]))),
        weights_swapped=_vicreg_slip(swap=True),
        invariance_summed=_vicreg_slip(invariance=lambda a, b: (a - b).pow(2).sum(1).mean()),
        invariance_unsquared=_vicreg_slip(invariance=lambda a, b: (a - b).norm(dim=1).mean())),
    _vicreg_cases,
    grad=[(0, "the first view z_a"), (1, "the second view z_b")], dims={0: "BD"})


def _vicreg_paper_to_ebjepa(inv: float, std: float, cov: float, dim: int) -> tuple:
    """VICReg-paper coefficients -> EB-JEPA's: the covariance sum is divided by ``D (D - 1)``,
    not ``D``, so its weight grows by ``D - 1``; then all three by the invariance weight."""
    return 1.0, std / inv, cov * (dim - 1) / inv


check_vicreg_paper_to_ebjepa = Exercise(
    "vicreg_paper_to_ebjepa", _vicreg_paper_to_ebjepa, dict(
        factor_missing=lambda inv, std, cov, dim: (1.0, std / inv, cov / inv),
        times_d=lambda inv, std, cov, dim: (1.0, std / inv, cov * dim / inv),
        divided_by_factor=lambda inv, std, cov, dim: (1.0, std / inv, cov / (dim - 1) / inv),
        variance_not_divided=lambda inv, std, cov, dim: (1.0, std, cov * (dim - 1) / inv),
        not_divided=lambda inv, std, cov, dim: (inv, std, cov * (dim - 1)),
        divided_by_std=lambda inv, std, cov, dim: (inv / std, 1.0, cov * (dim - 1) / std)),
    lambda: [Case("inv={:g}, std={:g}, cov={:g}, dim={}".format(*args), args) for args in [
        (25.0, 25.0, 1.0, 2048), (25.0, 25.0, 1.0, 8192), (10.0, 25.0, 1.0, 1024),
        (5.0, 5.0, 1.0, 128), (2.0, 1.0, 0.3, 3)]],
    parts=("invariance weight", "variance weight", "covariance weight"), atol=1e-6)


def _epps_pulley_cases() -> list[Case]:
    g = torch.Generator().manual_seed(6)
    uniform = (torch.rand(256, generator=g) * 2 - 1) * 3**0.5  # mean 0, variance 1
    return [
        Case("a Gaussian sample of 256 numbers", (torch.randn(256, generator=g),)),
        Case("a collapsed sample (64 copies of 0.5)", (torch.full((64,), 0.5),)),
        Case("a uniform sample with mean 0 and variance 1", (uniform,)),
        Case("a Gaussian sample with mean 1 and std 3", (1 + 3 * torch.randn(128, generator=g),)),
        Case("a Gaussian sample of 100 numbers with scale_by_n=False",
             (torch.randn(100, generator=g),), {"scale_by_n": False}),
        Case("a collapsed sample (32 zeros) with scale_by_n=False", (torch.zeros(32),),
             {"scale_by_n": False}),
        Case("knots=5 and t_max=2.0", (torch.randn(50, generator=g),), {"knots": 5, "t_max": 2.0}),
        Case("a sample of 2 numbers", (torch.tensor([-0.3, 1.2]),)),
        Case("a float64 Gaussian sample of 40 numbers",
             (torch.randn(40, generator=g, dtype=torch.float64),)),
    ]


def _epps_pulley_slip(weight=True, imag=True, square=True, rule="trapezoid", average=True,
                      symmetric=False):
    """The notebook's statistic with one mistake (each keyword undoes one step)."""
    def epps_pulley_1d(x, knots=17, t_max=3.0, scale_by_n=True):
        t = torch.linspace(-t_max if symmetric else 0.0, t_max, knots)
        xt = x[:, None] * t
        real = torch.cos(xt).mean(0) if average else torch.cos(xt).sum(0)
        im = (torch.sin(xt).mean(0) if average else torch.sin(xt).sum(0)) if imag else 0.0
        gaussian = torch.exp(-(t**2) / 2)
        gap = (real - gaussian) ** 2 + im**2
        y = (gaussian if weight else 1.0) * (gap if square else gap.sqrt())
        area = (torch.trapezoid(y, t) if rule == "trapezoid" else torch.trapezoid(y)
                if rule == "unit" else y.mean() * t_max if rule == "mean"
                else y.sum() * (t[1] - t[0]))
        statistic = area if symmetric else 2 * area
        return statistic * len(x) if scale_by_n else statistic
    return epps_pulley_1d


check_epps_pulley = Exercise(
    "epps_pulley_1d", epps_pulley, dict(  # sigma = 1: the cases pass the rest by keyword
        unweighted=_epps_pulley_slip(weight=False), real_only=_epps_pulley_slip(imag=False),
        unsquared=_epps_pulley_slip(square=False), rectangle_rule=_epps_pulley_slip(rule="sum"),
        unit_spacing=_epps_pulley_slip(rule="unit"), knot_mean=_epps_pulley_slip(rule="mean"),
        summed=_epps_pulley_slip(average=False),
        symmetric_knots=_epps_pulley_slip(symmetric=True)),
    _epps_pulley_cases, atol=1e-4, grad=[(0, "the sample x")], dims={0: "N"})
