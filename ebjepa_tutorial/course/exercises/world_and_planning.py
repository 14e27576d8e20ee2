"""Checkers of chapters 05-06: the temporal-similarity and inverse-dynamics terms on latents
``z`` ``(B, T, D)``; one MPPI update, ``actions (B, N, H, A)``, ``costs (B, N)`` -> mean, std."""

from functools import partial

import torch

from ...losses import world as world_losses
from ...planning import mppi_update, mppi_weights, weighted_mean_std
from .common import Case, Exercise


def _trajectory_latents() -> list[Case]:
    randn = partial(torch.randn, generator=torch.Generator().manual_seed(3))
    drift = torch.linspace(0, 1, 9)[None, :, None] * torch.tensor([[[1.0, -2.0, 0.5, 0.0]]])
    return [
        Case("random latents z of shape (4, 17, 8)", (randn(4, 17, 8),)),
        Case("latents that never change in time (5, 6, 3)", (randn(5, 1, 3).expand(5, 6, 3),)),
        Case("latents moving at a constant speed (1, 9, 4)", (drift,)),
        Case("the shortest sequences, 2 frames (3, 2, 5)", (randn(3, 2, 5),)),
        Case("latents with std about 4, shape (2, 10, 6)", (4 * randn(2, 10, 6),)),
        Case("float64 latents (3, 5, 7)", (randn(3, 5, 7, dtype=torch.float64),)),
    ]


check_temporal_similarity = Exercise(
    "temporal_similarity", world_losses.temporal_similarity_loss, dict(
        unsquared=lambda z: (z[:, 1:] - z[:, :-1]).norm(dim=-1).mean(),
        absolute=lambda z: (z[:, 1:] - z[:, :-1]).abs().mean(),
        summed=lambda z: (z[:, 1:] - z[:, :-1]).pow(2).sum(),
        earlier_detached=lambda z: (z[:, 1:] - z[:, :-1].detach()).pow(2).mean(),
        later_detached=lambda z: (z[:, 1:].detach() - z[:, :-1]).pow(2).mean(),
        wrong_axis=lambda z: world_losses.temporal_similarity_loss(z.transpose(0, 1)),
        feature_axis=lambda z: z.diff(dim=-1).pow(2).mean(),
        wrapped=lambda z: (z.roll(-1, dims=1) - z).pow(2).mean()),
    _trajectory_latents, grad=[(0, "the latents z")], dims={0: "BTD"})


def _linear_inverse_model(latent_dim: int, action_dim: int, seed: int, dtype=torch.float32):
    """A fixed random map ``g(z_t, z_next) = W [z_t, z_next] + b``: ``(..., D) x2 -> (..., A)``."""
    g = torch.Generator().manual_seed(seed)
    weight = torch.randn(2 * latent_dim, action_dim, generator=g, dtype=dtype) / latent_dim**0.5
    bias = torch.randn(action_dim, generator=g, dtype=dtype)
    return lambda z, z_next: torch.cat([z, z_next], dim=-1) @ weight + bias


def _inverse_cases() -> list[Case]:
    """``(predict_actions, z (B, T, D), actions (B, T - 1, A))``."""
    g, cases = torch.Generator().manual_seed(4), []
    # first no size n with n or n - 1 = 2: a factor 2 (a 1/2 convention) is then no size's
    for b, t, d, a, dtype in [(5, 9, 6, 4, torch.float32), (4, 17, 8, 2, torch.float32),
                              (3, 2, 5, 2, torch.float32), (5, 7, 4, 2, None),
                              (3, 6, 5, 3, torch.float64)]:
        model = (_linear_inverse_model(d, a, b, dtype) if dtype is not None  # or a difference,
                 else lambda z, z_next: (z_next - z)[..., :2])  # right only in time order
        what = ("g(z_t, z_next) = (z_next - z_t)[:2]" if dtype is None
                else f"a fixed linear g with {a}-d actions")
        what += " in float64" if dtype == torch.float64 else ""
        cases.append(Case(f"{what}, latents ({b}, {t}, {d}) and actions ({b}, {t - 1}, {a})",
                          (model, torch.randn(b, t, d, generator=g, dtype=dtype),
                           torch.randn(b, t - 1, a, generator=g, dtype=dtype))))
    return cases


def _pairs(g, z, a, earlier=lambda z: z, later=lambda z: z):
    return g(earlier(z[:, :-1]), later(z[:, 1:])) - a


check_inverse_dynamics = Exercise(
    "inverse_dynamics", world_losses.inverse_dynamics_loss, dict(
        wrong_order=lambda g, z, a: (g(z[:, 1:], z[:, :-1]) - a).pow(2).mean(),
        unsquared=lambda g, z, a: _pairs(g, z, a).norm(dim=-1).mean(),
        absolute=lambda g, z, a: _pairs(g, z, a).abs().mean(),
        summed=lambda g, z, a: _pairs(g, z, a).pow(2).sum(),
        later_detached=lambda g, z, a: _pairs(g, z, a, later=torch.detach).pow(2).mean(),
        earlier_detached=lambda g, z, a: _pairs(g, z, a, earlier=torch.detach).pow(2).mean()),
    _inverse_cases, grad=[(1, "the latents z")], dims={1: "BTD", 2: "__A"})


def _mppi_cases() -> list[Case]:
    g = torch.Generator().manual_seed(7)
    actions = torch.randn(2, 10, 4, 2, generator=g)
    costs = 5 * torch.rand(2, 10, generator=g)
    large, tau = costs + 1e4, 0.1
    # Unshifted, float32 rounds each -S/tau (about -100,000) to within S/tau 2^-24, so a weight
    # moves by twice that, relatively, and the mean and std by that much of the largest action.
    honest = 4 * 2.0**-24 * float(large.max()) / tau * float(actions.abs().max())
    apart = costs + torch.tensor([[0.0], [1000.0]])  # one shift for the batch leaves 0/0
    return [
        Case("2 episodes x 10 plans of 4 steps, Q=3, tau=0.5", (actions, costs, 3, 0.5)),
        Case("the same plans with tau=5 (softer weights)", (actions, costs, 3, 5.0)),
        Case("costs near 10,000 (exp(-S/tau) alone would underflow to 0/0)",
             (actions, large, 4, tau), atol=honest),
        Case("episodes whose costs lie 1,000 apart (each has its own cheapest plan)",
             (actions, apart, 3, tau), atol=honest * float(apart.max() / large.max())),
        Case("Q=1 (only the best plan: std 0)", (actions, costs, 1, 1.0)),
        Case("Q=N=10 (every plan is an elite)", (actions, costs, 10, 1.0)),
        Case("one episode, 6 plans of 1 step", (torch.randn(1, 6, 1, 2, generator=g),
                                                torch.rand(1, 6, generator=g), 2, 0.3)),
        Case("float64 plans and costs", (actions[:1].double(), costs[:1].double(), 3, 0.5)),
    ]


def _mppi_slip(weights=mppi_weights, std=None, elites_of=None, largest=False):
    """An MPPI update with one mistake: ``weights(elite_costs, tau)``, ``std(elites, w, mean)``,
    the number of elites ``elites_of(N, Q)``, or the ``largest`` costs taken as elites."""
    def mppi_update(actions, costs, elites, temperature):
        q = elites_of(actions.shape[1], elites) if elites_of else elites
        elite_costs, index = costs.topk(q, dim=1, largest=largest)
        elite = actions.gather(1, index[:, :, None, None].expand(-1, -1, *actions.shape[2:]))
        w = weights(elite_costs, temperature)
        mean, spread = weighted_mean_std(elite, w)
        return mean, spread if std is None else std(elite, w[:, :, None, None], mean)
    return mppi_update


def _batch_shifted(costs: torch.Tensor, tau: float) -> torch.Tensor:
    """Weights shifted by the whole batch's cheapest cost: another episode's may underflow."""
    weights = torch.exp(-(costs - costs.min()) / tau)
    return weights / weights.sum(1, keepdim=True)


def _shifted(costs: torch.Tensor) -> torch.Tensor:
    return costs - costs.min(dim=1, keepdim=True).values


check_mppi_update = Exercise(
    "mppi_update", mppi_update, dict(
        no_min_shift=_mppi_slip(weights=lambda s, tau: torch.exp(-s / tau) / torch.exp(
            -s / tau).sum(1, keepdim=True)),
        all_samples=_mppi_slip(elites_of=lambda n, q: n), most_expensive=_mppi_slip(largest=True),
        times_tau=_mppi_slip(weights=lambda s, tau: torch.softmax(-_shifted(s) * tau, dim=1)),
        batch_min_shift=_mppi_slip(weights=_batch_shifted),
        growing_weights=_mppi_slip(weights=lambda s, tau: torch.softmax(_shifted(s) / tau, 1)),
        equal_weights=_mppi_slip(weights=lambda s, tau: torch.full_like(s, 1 / s.shape[1])),
        unnormalised=_mppi_slip(weights=lambda s, tau: torch.exp(-_shifted(s) / tau)),
        variance=_mppi_slip(std=lambda a, w, m: (w * (a - m[:, None]).pow(2)).sum(1)),
        unweighted_std=(_mppi_slip(std=lambda a, w, m: a.std(1)),
                        _mppi_slip(std=lambda a, w, m: a.std(1, unbiased=False))),
        uncentred_std=_mppi_slip(std=lambda a, w, m: (w * a.pow(2)).sum(1).sqrt())),
    _mppi_cases, parts=("mean", "std"))
