"""Checker of chapter 02: the Epps-Pulley statistic of SIGReg on one slice ``x`` ``(N,)``, the
course's :func:`~ebjepa_tutorial.losses.sigreg.epps_pulley` with ``sigma = 1``."""

from __future__ import annotations

import torch

from ...losses.sigreg import epps_pulley
from .common import Case, Exercise, slips


def _epps_pulley_reference(x, knots=17, t_max=3.0, scale_by_n=True):
    return epps_pulley(x, knots=knots, t_max=t_max, sigma=1.0, scale_by_n=scale_by_n)


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
        area = torch.trapezoid(y, t) if rule == "trapezoid" else y.sum() * (t[1] - t[0])
        statistic = area if symmetric else 2 * area
        return statistic * len(x) if scale_by_n else statistic

    return epps_pulley_1d


check_epps_pulley = Exercise(
    "epps_pulley_1d", _epps_pulley_reference, slips(
        "epps_pulley_1d", unweighted=_epps_pulley_slip(weight=False),
        real_only=_epps_pulley_slip(imag=False), unsquared=_epps_pulley_slip(square=False),
        rectangle_rule=_epps_pulley_slip(rule="sum"), summed=_epps_pulley_slip(average=False),
        symmetric_knots=_epps_pulley_slip(symmetric=True)),
    _epps_pulley_cases, atol=1e-4, grad=[(0, "the sample x")], dims={0: "N"})
