"""SIGReg (LeJEPA, Balestriero & LeCun, 2025): push embeddings ``z (B, D)`` towards N(0, I) by
scoring random unit projections ``x = z @ a`` against N(0, 1) with the Epps-Pulley statistic (by
Cramer-Wold, ``z`` is N(0, I) if every 1-D projection is N(0, 1))."""

from __future__ import annotations

import torch

from ..utils import at_least_float32
from .vicreg import _check_embeddings, invariance_term


def epps_pulley(x: torch.Tensor, knots: int = 17, t_max: float = 3.0, sigma: float = 1.0,
                scale_by_n: bool = True) -> torch.Tensor:
    """Epps-Pulley statistic of N samples of one projection ``(N,) -> ()``, or of M projections
    ``(N, M) -> (M,)``; the integrand is even, so trapezoids on [0, T = t_max], doubled:

        EP = N integral_{-T}^{T} |phi_N(t) - exp(-t^2 / 2)|^2 exp(-t^2 / (2 sigma^2)) dt

    with phi_N(t) = (1/N) sum_n exp(i t x_n). The factor N (LeJEPA's) makes EP about 1.05 for
    Gaussian samples; ``scale_by_n=False`` drops it, as EB-JEPA's code does (``lam`` N-fold
    larger)."""
    if x.ndim not in (1, 2) or x.shape[0] < 2:
        raise ValueError(f"epps_pulley needs at least 2 samples along dimension 0 of a (N,) or "
                         f"(N, M) tensor, got shape {tuple(x.shape)}")
    x = at_least_float32(x)  # cos(t x) of large arguments loses every digit in half precision
    t = torch.linspace(0.0, t_max, knots, device=x.device, dtype=x.dtype)  # (K,)
    ecf_real, ecf_imag = EmpiricalCF.apply(x, t_max / (knots - 1), knots)  # (K,) or (M, K)
    gaussian_cf = torch.exp(-(t**2) / 2)  # phi(t) of N(0, 1): real
    weight = torch.exp(-(t**2) / (2 * sigma**2))  # w(t)
    squared_gap = (ecf_real - gaussian_cf) ** 2 + ecf_imag**2  # |phi_N(t) - phi(t)|^2
    statistic = 2 * torch.trapezoid(weight * squared_gap, t, dim=-1)  # twice [0, t_max]'s
    return statistic * x.shape[0] if scale_by_n else statistic


def _cos_sin_at_knots(x: torch.Tensor, dt: float, knots: int):
    """Yield ``(cos(k dt x), sin(k dt x))`` for k < knots, shaped like ``x``, by angle addition
    (e^{i (k+1) dt x} = e^{i k dt x} e^{i dt x}), exact again every 8 knots."""
    cos_step, sin_step = torch.cos(x * dt), torch.sin(x * dt)
    cos_k, sin_k = torch.ones_like(x), torch.zeros_like(x)
    for k in range(knots):
        if k % 8 == 1:  # k = 1, 9, 17, ...: exact, so that the drift stays within ~8 ulp
            cos_k, sin_k = torch.cos(x * (k * dt)), torch.sin(x * (k * dt))
        elif k:
            cos_k, sin_k = cos_k * cos_step - sin_k * sin_step, sin_k * cos_step + cos_k * sin_step
        yield cos_k, sin_k


class EmpiricalCF(torch.autograd.Function):
    """Re and Im of phi_N(k dt), k < knots: ``apply(x (N, ...), dt, knots) -> two (..., knots)``;
    backward rebuilds cos and sin from x: ``d Re phi_N(t) / d x_n = -t sin(t x_n) / N``, etc."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, dt: float, knots: int):
        pairs = [(c.mean(dim=0), s.mean(dim=0)) for c, s in _cos_sin_at_knots(x, dt, knots)]
        ctx.save_for_backward(x)
        ctx.dt, ctx.knots = dt, knots
        return torch.stack([c for c, _ in pairs], -1), torch.stack([s for _, s in pairs], -1)

    @staticmethod
    def backward(ctx, grad_real: torch.Tensor, grad_imag: torch.Tensor):
        (x,) = ctx.saved_tensors
        grad_x = torch.zeros_like(x)
        for k, (cos_k, sin_k) in enumerate(_cos_sin_at_knots(x, ctx.dt, ctx.knots)):
            t_k = k * ctx.dt / x.shape[0]  # t_k / N
            grad_x += t_k * (cos_k * grad_imag[..., k] - sin_k * grad_real[..., k])
        return grad_x, None, None


def random_directions(dim: int, num_slices: int,
                      generator: torch.Generator | None = None) -> torch.Tensor:
    """``num_slices`` random unit vectors, the columns of a ``(dim, num_slices)`` matrix, on the
    generator's device (CPU by default: the same on every machine)."""
    device = generator.device if generator is not None else "cpu"
    directions = torch.randn(dim, num_slices, generator=generator, device=device)
    return directions / directions.norm(dim=0, keepdim=True)


def sigreg(z: torch.Tensor, num_slices: int = 256, generator: torch.Generator | None = None,
           directions: torch.Tensor | None = None, scale_by_n: bool = True) -> torch.Tensor:
    """Epps-Pulley statistic of embeddings ``z`` ``(B, D)`` averaged over slices, ``()``: fresh
    directions from ``generator`` on every call, unless ``directions`` ``(D, M)`` are given."""
    _check_embeddings(z)
    if directions is None:
        directions = random_directions(z.shape[1], num_slices, generator)
    z = at_least_float32(z)
    projected = z @ directions.to(z.device, z.dtype)  # (B, M)
    return epps_pulley(projected, scale_by_n=scale_by_n).mean()


def sigreg_loss(z_a: torch.Tensor, z_b: torch.Tensor, lam: float = 0.1, num_slices: int = 256,
                generator: torch.Generator | None = None,
                scale_by_n: bool = True) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """``(L, terms)`` of two views ``(B, D)``: ``L = invariance + lam * SIGReg``, SIGReg averaged
    over the views (same directions); ``terms``: unweighted, detached 0-d tensors."""
    inv = invariance_term(z_a, z_b)
    directions = random_directions(z_a.shape[1], num_slices, generator)
    reg = (sigreg(z_a, directions=directions, scale_by_n=scale_by_n)
           + sigreg(z_b, directions=directions, scale_by_n=scale_by_n)) / 2
    total = inv + lam * reg
    return total, {"invariance": inv.detach(), "sigreg": reg.detach()}
