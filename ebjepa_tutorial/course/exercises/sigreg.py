"""Checker of chapter 02: the Epps-Pulley statistic of SIGReg."""

from __future__ import annotations

from collections.abc import Callable

import torch

from ...losses.sigreg import epps_pulley, sigreg_loss
from .common import Case, compare, exercise


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
                      symmetric=False) -> Callable:
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


_EPPS_PULLEY_HINTS = (
    "A sample looks Gaussian when its characteristic function, the average over the sample "
    "of exp(i t x), matches the Gaussian's, exp(-t^2/2), at every t. Measure the squared gap "
    "between the two at a handful of values of t, weight it so that small t counts most, "
    "and add it up over t (a numerical integral).",
    "Knots: K values of t equally spaced from 0 to t_max. Empirical characteristic "
    "function: Re = the mean over the N samples of cos(t x_n), Im = the mean of sin(t x_n), "
    "one value per knot. Integrand: exp(-t^2/2) * ((Re - exp(-t^2/2))^2 + Im^2). Integrate "
    "it over [0, t_max] with the trapezoid rule, double the result (the integrand is even in "
    "t), and multiply by N when scale_by_n is true. Shapes: x is (N,), the knots (K,), all "
    "the products t x_n form an (N, K) table, averaged over its N rows.",
    "t = <K equally spaced knots from 0 to t_max>\n"
    "xt = <the (N, K) table of products x_n * t_k>  # broadcast x as a column against t\n"
    "real, imag = <cos and sin of xt, each averaged over the sample (dim 0)>\n"
    "gaussian = torch.exp(-t**2 / 2)\n"
    "integrand = gaussian * ((real - gaussian)**2 + imag**2)\n"
    "statistic = 2 * <the trapezoid rule of integrand over t>\n"
    "return <statistic times N if scale_by_n, else statistic>",
)

_EPPS_PULLEY_SLIPS = [
    ("the weight w(t) = exp(-t^2/2) is missing from the integrand: integrate "
     "w(t) |phi_N(t) - phi(t)|^2.", _epps_pulley_slip(weight=False)),
    ("the imaginary part is missing: |phi_N - phi|^2 = (mean cos(tx) - exp(-t^2/2))^2 "
     "+ (mean sin(tx))^2.", _epps_pulley_slip(imag=False)),
    ("you integrated |phi_N - phi| unsquared; the statistic integrates its square.",
     _epps_pulley_slip(square=False)),
    ("you used a plain sum times the knot spacing (a rectangle rule); the course integrates "
     "with the trapezoid rule, which halves the two end knots.", _epps_pulley_slip(rule="sum")),
    ("you summed cos(tx) and sin(tx) over the sample; the empirical characteristic function "
     "averages them.", _epps_pulley_slip(average=False)),
    ("you spread the knots over [-t_max, t_max]; the course puts them on [0, t_max] and "
     "doubles the integral (the integrand is even): the same integral on a finer grid.",
     _epps_pulley_slip(symmetric=True)),
]


@exercise(_epps_pulley_reference, _EPPS_PULLEY_SLIPS, name="epps_pulley_1d",
          hints=_EPPS_PULLEY_HINTS, answers=(epps_pulley, sigreg_loss))
def check_epps_pulley(fn: Callable) -> bool:
    """Notebook 02: ``epps_pulley_1d(x, knots=17, t_max=3.0, scale_by_n=True)`` on one slice
    ``x`` ``(N,)`` -> a 0-d tensor, the course's :func:`~ebjepa_tutorial.losses.sigreg.epps_pulley`
    with ``sigma = 1``; value and gradient with respect to ``x``."""
    return compare(fn, _epps_pulley_reference, _epps_pulley_cases(), atol=1e-4,
                   diagnoses=_EPPS_PULLEY_SLIPS, grad=[(0, "the sample x")], dims={0: "N"},
                   factors={"N": "with scale_by_n=True the statistic is N times the integral, "
                                 "with scale_by_n=False the integral alone",
                            "2": "integrate over [0, t_max], then double once: the integrand "
                                 "is even in t"})
