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


def _epps_pulley_slip(got: float, expected: float, n: int) -> str:
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


@exercise(_epps_pulley_reference)
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
            hint = _epps_pulley_slip(float(got), float(expected), len(case.args[0]))
            if hint and not torch.allclose(got.double().reshape(()), expected.double(),
                                           atol=1e-4, rtol=1e-4):
                raise ExerciseError(f"{name} gave {float(got):.6g} on {case.description}, but "
                                    f"the answer is {float(expected):.6g}.{hint}")
    return compare(fn, _epps_pulley_reference, cases, atol=1e-4)
