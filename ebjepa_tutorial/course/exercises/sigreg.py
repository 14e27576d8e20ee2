"""Checker of chapter 02: the Epps-Pulley statistic of SIGReg."""

from __future__ import annotations

from collections.abc import Callable

import torch

from ...losses.sigreg import epps_pulley
from .common import Case, ExerciseError, _call, compare, exercise


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
    ]


def _epps_pulley_factor(got: float, expected: float, n: int) -> str:
    """A likely cause when the learner's statistic is off by a telling factor, else ''."""
    ratio = got / expected if expected != 0 else float("nan")
    for factor, why in [
        (1 / n, "it is N times too small: with scale_by_n=True, multiply the integral by N"),
        (n, "it is N times too large: multiply by N only when scale_by_n is True"),
        (0.5, "it is half the answer: the trapezoid rule on [0, t_max] gives half the "
              "integral over [-t_max, t_max]; double it (the integrand is even)"),
        (2.0, "it is twice the answer: integrate over [0, t_max] and double once, no more"),
    ]:
        if abs(ratio - factor) < 1e-3 * factor:
            return f" Hint: {why}."
    return ""


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


_EPPS_PULLEY_SLIPS = [
    ("the weight w(t) = exp(-t^2/2) is missing from the integrand: integrate "
     "w(t) |phi_N(t) - phi(t)|^2.", _epps_pulley_slip(weight=False)),
    ("the imaginary part is missing: |phi_N - phi|^2 = (mean cos(tx) - exp(-t^2/2))^2 "
     "+ (mean sin(tx))^2.", _epps_pulley_slip(imag=False)),
    ("you integrated |phi_N - phi| unsquared; the statistic integrates its square.",
     _epps_pulley_slip(square=False)),
    ("you used a plain sum times the knot spacing (a rectangle rule); integrate with "
     "torch.trapezoid(y, t).", _epps_pulley_slip(rule="sum")),
    ("you summed cos(tx) and sin(tx) over the sample; the empirical characteristic function "
     "averages them (.mean(dim=0)).", _epps_pulley_slip(average=False)),
    ("you spread the knots over [-t_max, t_max]; the course puts them on [0, t_max] and "
     "doubles the integral (the integrand is even): the same integral on a finer grid.",
     _epps_pulley_slip(symmetric=True)),
]


@exercise(_epps_pulley_reference, _EPPS_PULLEY_SLIPS)
def check_epps_pulley(fn: Callable) -> bool:
    """Notebook 02: ``epps_pulley_1d(x, knots=17, t_max=3.0, scale_by_n=True)`` -> a 0-d tensor.

    ``x``: one slice, ``(N,)``. Compared with :func:`ebjepa_tutorial.losses.sigreg.epps_pulley`
    (weight width ``sigma = 1``) on Gaussian, collapsed and uniform samples,
    with and without the factor N, and with other knots.
    """
    name = getattr(fn, "__name__", "your function")
    cases = _epps_pulley_cases()
    for case in cases:  # first, name the usual slips (a missing factor N, a missing doubling)
        expected = _epps_pulley_reference(*case.args, **case.kwargs)
        got = _call(fn, name, case)
        if isinstance(got, torch.Tensor) and got.numel() == 1:
            hint = _epps_pulley_factor(float(got), float(expected), len(case.args[0]))
            if hint and not torch.allclose(got.double().reshape(()), expected.double(),
                                           atol=1e-4, rtol=1e-4):
                raise ExerciseError(f"{name} gave {float(got):.6g} on {case.description}, but "
                                    f"the answer is {float(expected):.6g}.{hint}")
    return compare(fn, _epps_pulley_reference, cases, atol=1e-4, diagnoses=_EPPS_PULLEY_SLIPS)
