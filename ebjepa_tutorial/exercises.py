"""Checkers for the notebooks' exercises: is the learner's function right?

Each ``check_*`` runs the learner's function and the package's reference
implementation on the same small inputs, prints a one-line verdict when they
agree, and otherwise raises :class:`ExerciseError` saying in plain words which
input went wrong and how. Chapters add their checkers here.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch

from . import losses, world_losses


class ExerciseError(AssertionError):
    """The learner's function disagrees with the reference; the message says where."""


@dataclass
class Case:
    """One test input: a description for the learner and the arguments to call with."""

    description: str
    args: tuple
    kwargs: dict = field(default_factory=dict)


def _describe(value) -> str:
    if isinstance(value, torch.Tensor):
        return f"a tensor of shape {tuple(value.shape)}"
    return f"a {type(value).__name__}"


def _call(fn: Callable, name: str, case: Case):
    try:
        return fn(*case.args, **case.kwargs)
    except NotImplementedError:
        raise ExerciseError(
            f"{name} is not implemented yet: replace the `raise NotImplementedError` "
            "line with your code, run that cell, then run this check again."
        ) from None
    except Exception as err:
        message = f"{name} raised {type(err).__name__}: {err} on {case.description}."
        raise ExerciseError(message) from err


def compare(fn: Callable, reference: Callable, cases: list[Case], atol: float = 1e-5) -> bool:
    """Check ``fn`` against ``reference`` on every case; print a verdict or raise ExerciseError."""
    name = getattr(fn, "__name__", "your function")
    for case in cases:
        expected = reference(*case.args, **case.kwargs)
        got = _call(fn, name, case)
        if not isinstance(got, torch.Tensor):
            raise ExerciseError(f"{name} returned {_describe(got)}; expected a torch tensor.")
        if got.shape != expected.shape:
            single = " (a single number)" if expected.ndim == 0 else ""
            raise ExerciseError(
                f"{name} returned shape {tuple(got.shape)} on {case.description}; "
                f"expected shape {tuple(expected.shape)}{single}."
            )
        if not torch.allclose(got.double(), expected.double(), atol=atol, rtol=1e-4):
            raise ExerciseError(
                f"{name} gave {got.detach().flatten()[:4].tolist()} on {case.description}, "
                f"but the answer is {expected.detach().flatten()[:4].tolist()}."
            )
    print(f"Correct: {name} matches the reference on {len(cases)} test inputs.")
    return True


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


def check_variance_term(fn: Callable) -> bool:
    """Notebook 00 and 01: ``variance_term(z, gamma=1.0, eps=1e-4)`` on ``(B, D)``."""
    cases = _embedding_cases() + [
        Case("gamma=2.0", (torch.randn(32, 4, generator=torch.Generator().manual_seed(1)),),
             {"gamma": 2.0}),
    ]
    return compare(fn, losses.variance_term, cases)


def check_covariance_term(fn: Callable) -> bool:
    """Notebook 00 and 01: ``covariance_term(z)`` on ``(B, D)``."""
    return compare(fn, losses.covariance_term, _embedding_cases(seed=2))


def _trajectory_latents(seed: int = 3) -> list[Case]:
    """Latent sequences ``(B, T, D)`` of several kinds, for the chapter 05 checkers."""
    g = torch.Generator().manual_seed(seed)
    drift = torch.linspace(0, 1, 9)[None, :, None] * torch.tensor([[[1.0, -2.0, 0.5, 0.0]]])
    return [
        Case("random latents z of shape (4, 17, 8)", (torch.randn(4, 17, 8, generator=g),)),
        Case("latents that never change in time (5, 6, 3)",
             (torch.randn(5, 1, 3, generator=g).expand(5, 6, 3),)),
        Case("latents moving at a constant speed (1, 9, 4)", (drift,)),
        Case("the shortest sequences, 2 frames (3, 2, 5)", (torch.randn(3, 2, 5, generator=g),)),
        Case("latents with std about 4, shape (2, 10, 6)",
             (4 * torch.randn(2, 10, 6, generator=g),)),
    ]


def check_temporal_similarity(fn: Callable) -> bool:
    """Notebook 05: ``temporal_similarity(z)`` on latents ``(B, T, D)`` -> a 0-d tensor."""
    return compare(fn, world_losses.temporal_similarity_loss, _trajectory_latents())


def _linear_inverse_model(latent_dim: int, action_dim: int, seed: int) -> Callable:
    """A fixed random map ``g(z_t, z_next) = W [z_t, z_next] + b``: ``(..., D) x2 -> (..., A)``."""
    g = torch.Generator().manual_seed(seed)
    weight = torch.randn(2 * latent_dim, action_dim, generator=g) / latent_dim**0.5
    bias = torch.randn(action_dim, generator=g)

    def predict_actions(z, z_next):
        return torch.cat([z, z_next], dim=-1) @ weight + bias

    return predict_actions


def _difference_model(z, z_next):
    """``g(z_t, z_next) = (z_next - z_t)[..., :2]``: right only when frames are in order."""
    return (z_next - z)[..., :2]


def check_inverse_dynamics(fn: Callable) -> bool:
    """Notebook 05: ``inverse_dynamics(predict_actions, z, actions)`` -> a 0-d tensor.

    ``z``: latents ``(B, T, D)``; ``actions``: ``(B, T-1, A)``; ``predict_actions``
    maps ``(z_t, z_next)``, each ``(..., D)``, to actions ``(..., A)``.
    """
    g = torch.Generator().manual_seed(4)
    cases = []
    for b, t, d, a, kind in [(4, 17, 8, 2, "random"), (3, 2, 5, 2, "random"),
                             (2, 9, 6, 3, "random"), (5, 7, 4, 2, "difference")]:
        model = _difference_model if kind == "difference" else _linear_inverse_model(d, a, b)
        what = ("g(z_t, z_next) = (z_next - z_t)[:2]" if kind == "difference"
                else f"a fixed linear g with {a}-d actions")
        cases.append(Case(
            f"{what}, latents ({b}, {t}, {d}) and actions ({b}, {t - 1}, {a})",
            (model, torch.randn(b, t, d, generator=g), torch.randn(b, t - 1, a, generator=g)),
        ))
    return compare(fn, world_losses.inverse_dynamics_loss, cases)


def _vicreg_total(z_a, z_b, inv_coeff, std_coeff, cov_coeff):
    return losses.vicreg_loss(z_a, z_b, inv_coeff, std_coeff, cov_coeff)[0]


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


def _epps_pulley_reference(x, knots=17, t_max=3.0, scale_by_n=True):
    from .sigreg import epps_pulley

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


def check_epps_pulley(fn: Callable) -> bool:
    """Notebook 02: ``epps_pulley_1d(x, knots=17, t_max=3.0, scale_by_n=True)`` -> a 0-d tensor.

    ``x``: one slice, ``(N,)``. Compared with :func:`ebjepa_tutorial.sigreg.epps_pulley`
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


def check_mppi_update(fn: Callable) -> bool:
    """Notebook 06: ``mppi_update(actions, costs, elites, temperature) -> (mean, std)``.

    ``actions (B, N, H, A)``, ``costs (B, N)`` -> two ``(B, H, A)`` tensors, compared
    (stacked: mean first, then std) with :func:`ebjepa_tutorial.planning.mppi_update`.
    """
    from .planning import mppi_update

    return compare(_stacked(fn), _stacked(mppi_update), _mppi_cases())
