"""SIGReg (LeJEPA, Balestriero & LeCun, 2025): push embeddings towards N(0, I) with 1-D tests.

Testing Gaussianity in D dimensions is hard, along one direction it is easy. So each step
draws ``num_slices`` random unit directions ``a``, projects the embeddings ``z`` ``(B, D)`` to
``x = z @ a`` (B numbers per direction), and scores each projection with the Epps-Pulley
statistic, which compares characteristic functions:

    phi_N(t) = (1/N) sum_n exp(i t x_n)        empirical characteristic function
    phi(t)   = exp(-t^2 / 2)                   that of N(0, 1)
    EP       = N * integral_{-T}^{T} |phi_N(t) - phi(t)|^2 w(t) dt,
    w(t)     = exp(-t^2 / (2 sigma^2))         Gaussian weight

By the Cramer-Wold theorem, a distribution whose every 1-D projection is N(0, 1) is N(0, I).
The projections are not standardised: the statistic must see the mean and the scale, or it
could not prevent collapse. The factor N (``scale_by_n=True``, LeJEPA's) makes EP about 1.05
for Gaussian samples at any batch size and about 0.4 N for a collapsed batch; without it the
statistic is N times smaller, and so must its coefficient ``lam`` be N times larger.
"""

from __future__ import annotations

import torch

from ..utils import at_least_float32
from .vicreg import _check_embeddings, invariance_term


def epps_pulley(x: torch.Tensor, knots: int = 17, t_max: float = 3.0, sigma: float = 1.0,
                scale_by_n: bool = True) -> torch.Tensor:
    """Epps-Pulley statistic of 1-D samples against N(0, 1): ``(N,) -> ()`` or ``(N, M) -> (M,)``.

    ``x``: N samples of one projection, or of M projections (one per column). The integrand is
    even in t, so we integrate over [0, t_max] with ``knots`` trapezoid knots and double it.
    Zero iff the empirical characteristic function matches exp(-t^2/2) at every knot.
    """
    if x.ndim not in (1, 2) or x.shape[0] < 2:
        raise ValueError(f"epps_pulley needs at least 2 samples along dimension 0 of a (N,) or "
                         f"(N, M) tensor, got shape {tuple(x.shape)}")
    x = at_least_float32(x)  # cos(t x) of large arguments loses every digit in half precision
    t = torch.linspace(0.0, t_max, knots, device=x.device, dtype=x.dtype)  # (K,)
    ecf_real, ecf_imag = EmpiricalCF.apply(x, t_max / (knots - 1), knots)  # (K,) or (M, K)
    gaussian_cf = torch.exp(-(t**2) / 2)  # phi(t) of N(0, 1): real
    weight = torch.exp(-(t**2) / (2 * sigma**2))  # w(t)

    squared_gap = (ecf_real - gaussian_cf) ** 2 + ecf_imag**2  # |phi_N(t) - phi(t)|^2
    half_integral = torch.trapezoid(weight * squared_gap, t, dim=-1)  # over [0, t_max]
    statistic = 2 * half_integral  # over [-t_max, t_max], by symmetry
    return statistic * x.shape[0] if scale_by_n else statistic


_ANCHOR_EVERY = 8  # knots between exact cos/sin: bounds the angle-addition drift to ~8 ulp


def _cos_sin_at_knots(x: torch.Tensor, dt: float, knots: int):
    """Yield ``(cos(k dt x), sin(k dt x))`` for k = 0 .. knots - 1, each shaped like ``x``.

    By angle addition, e^{i (k+1) dt x} = e^{i k dt x} e^{i dt x}: six multiply-adds per knot
    instead of a cos and a sin, recomputed exactly every ``_ANCHOR_EVERY`` knots.
    """
    cos_step, sin_step = torch.cos(x * dt), torch.sin(x * dt)
    cos_k, sin_k = torch.ones_like(x), torch.zeros_like(x)
    for k in range(knots):
        if k == 1:
            cos_k, sin_k = cos_step, sin_step
        elif k % _ANCHOR_EVERY == 1:  # exact again, so that rounding errors do not pile up
            cos_k, sin_k = torch.cos(x * (k * dt)), torch.sin(x * (k * dt))
        elif k:
            cos_k, sin_k = cos_k * cos_step - sin_k * sin_step, sin_k * cos_step + cos_k * sin_step
        yield cos_k, sin_k


class EmpiricalCF(torch.autograd.Function):
    """Re and Im of phi_N(t_k) = (1/N) sum_n exp(i t_k x_n) at t_k = k dt, k < knots:
    ``apply(x (N, ...), dt, knots) -> two (..., knots)``.

    Autograd would store cos and sin of every knot (2 K copies of x); the gradient has a
    closed form instead,
        d Re phi_N(t_k) / d x_n = -t_k sin(t_k x_n) / N,
        d Im phi_N(t_k) / d x_n =  t_k cos(t_k x_n) / N,
    so the backward pass rebuilds the cosines and sines, knot by knot, from x alone.
    """

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


def random_directions(dim: int, num_slices: int, generator: torch.Generator | None = None,
                      device: torch.device | str | None = None) -> torch.Tensor:
    """``num_slices`` random unit vectors in R^dim, the columns of a ``(dim, num_slices)``
    matrix, drawn on the generator's device (CPU by default: the same on every machine)."""
    gen_device = generator.device if generator is not None else "cpu"
    directions = torch.randn(dim, num_slices, generator=generator, device=gen_device)
    directions = directions / directions.norm(dim=0, keepdim=True)
    return directions.to(device) if device is not None else directions


def sigreg(z: torch.Tensor, num_slices: int = 256, generator: torch.Generator | None = None,
           directions: torch.Tensor | None = None, scale_by_n: bool = True) -> torch.Tensor:
    """Sliced Epps-Pulley statistic of embeddings ``z`` ``(B, D)``, averaged over slices: ``()``.

    Fresh directions are drawn from ``generator`` on every call (a training loop tests new
    ones each step), unless ``directions`` ``(D, M)`` are given. Cost: O(B num_slices knots).
    """
    _check_embeddings(z, "z", min_batch=2)
    if directions is None:
        directions = random_directions(z.shape[1], num_slices, generator, z.device)
    z = at_least_float32(z)
    projected = z @ directions.to(z.device, z.dtype)  # (B, M)
    return epps_pulley(projected, scale_by_n=scale_by_n).mean()


def sigreg_loss(z_a: torch.Tensor, z_b: torch.Tensor, lam: float = 0.1, num_slices: int = 256,
                generator: torch.Generator | None = None,
                scale_by_n: bool = True) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Invariance + ``lam`` * SIGReg on two views ``(B, D)``: returns ``(total, terms)``.

    SIGReg is applied to each view with the same random directions and averaged; ``terms``
    holds the unweighted terms, detached 0-d tensors. ``lam = 0.1`` is the EB-JEPA CIFAR-10
    setting for ``scale_by_n=True``.
    """
    inv = invariance_term(z_a, z_b)
    directions = random_directions(z_a.shape[1], num_slices, generator, z_a.device)
    reg = (sigreg(z_a, directions=directions, scale_by_n=scale_by_n)
           + sigreg(z_b, directions=directions, scale_by_n=scale_by_n)) / 2
    total = inv + lam * reg
    return total, {"invariance": inv.detach(), "sigreg": reg.detach()}
