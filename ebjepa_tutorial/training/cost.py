"""Fit a cost-to-go head on a frozen world model's latents (notebook 07).

The world model is not changed: its encoder turns fresh data-policy
trajectories into latents once, its predictor imagines short rollouts of them
once, and the head (``models.cost.CostToGo``) is fitted on those by the rule of
``losses.cost``: pairs of frames of one layout pushed apart, each observed step
held within its action's length by a Lagrange multiplier. The trajectories come
in groups that share a layout (a distance between two layouts means nothing),
long enough to cross a room, and a quarter start at a wall heading in.

A planner scores the head on the predictor's IMAGINED latents, and MPPI seeks
out any plan whose imagined latents the head reads as progress. Pushed into a
wall the predictor drifts a little; so the fit also asks the head to read each
imagined latent as the true one it stands for (``consistency``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from ..envs import generate_trajectories, random_layouts
from ..losses.cost import imagination_gap, spread_loss, step_violation
from ..models.cost import COST_SCALE, CostToGo
from ..models.world import WorldModel, trajectory_latents
from ..utils import check_fields, is_int_at_least
from .checkpoints import run_identity
from .loop import History, fit, load_or_fit, step_generator

# The fit's constants (every run of the course uses these):
CAP = 150.0  # C, px: pairs farther apart are hardly pushed (the softplus's hinge)
TOLERANCE = 0.1  # epsilon, px: the root mean square by which steps may exceed their action
LR, MULTIPLIER_LR = 1e-3, 1e-2  # Adam's rate for the head; gradient ascent on the multiplier
WALL_FRACTION = 0.25  # trajectories that start in front of a wall, heading in
IMAGINED_STEPS = 16  # steps of each imagined rollout (a trajectory's steps are a multiple)


@dataclass(frozen=True)
class CostConfig:
    """How a cost-to-go head is fitted. The defaults are notebook 07's class run."""

    n_trajectories: int = 5_000  # fresh data-policy trajectories, encoded once
    trajectory_steps: int = 64  # long enough for a random walk to cross a room
    layouts: int = 500  # distinct layouts, each shared by n_trajectories / layouts of them
    steps: int = 4000  # Adam steps
    batch_size: int = 1024  # pairs, steps and imagined latents, each
    hidden: int = 256
    dims: int = 32  # the embedding whose distance is the cost
    consistency: float = 10.0  # weight of the imagined latents' gap (0: none)
    walls: int = 1  # 1: Two Rooms; 2: Three Rooms
    seed: int = 7

    def __post_init__(self):
        check_fields(self, {name: (is_int_at_least(1), "an int >= 1") for name in
                            ("n_trajectories", "trajectory_steps", "layouts", "steps",
                             "batch_size", "hidden", "dims")})
        if self.n_trajectories % self.layouts:
            raise ValueError(f"n_trajectories ({self.n_trajectories}) must be a multiple of "
                             f"layouts ({self.layouts}): each layout has as many trajectories")
        if self.trajectory_steps % IMAGINED_STEPS:
            raise ValueError(f"trajectory_steps ({self.trajectory_steps}) must be a multiple of "
                             f"{IMAGINED_STEPS}: each trajectory is imagined in pieces of as "
                             "many steps (IMAGINED_STEPS)")
        if not self.consistency >= 0:
            raise ValueError(f"consistency must be >= 0 (0: none), got {self.consistency}")


@dataclass
class CostData:
    """What the head is fitted on, in groups of ``group`` trajectories that share a layout.

    ``latents (N, T+1, D)``, ``lengths (N, T)`` (px each action asks for) and
    ``imagined (N, T // k, k, D)``: the predictor's rollout of each piece of ``k`` steps
    from its first true latent, so ``imagined[n, p, j]`` stands for ``latents[n, p*k + j + 1]``.
    """

    latents: torch.Tensor
    lengths: torch.Tensor
    imagined: torch.Tensor
    group: int


@torch.no_grad()
def cost_data(model: WorldModel, config: CostConfig) -> CostData:
    """Fresh trajectories of ``config``, encoded and imagined by ``model`` (frozen)."""
    generator = torch.Generator().manual_seed(config.seed)
    group = config.n_trajectories // config.layouts
    layouts = random_layouts(config.layouts, generator, config.walls)
    data = generate_trajectories(config.n_trajectories, config.trajectory_steps, generator,
                                 wall_fraction=WALL_FRACTION,
                                 layouts=layouts.repeat_interleave(group, dim=0))
    latents, k = trajectory_latents(model, data), IMAGINED_STEPS
    imagined = torch.stack([model.rollout(latents[:, s], data.actions[:, s: s + k])
                            for s in range(0, config.trajectory_steps, k)], dim=1)
    return CostData(latents, data.actions.norm(dim=-1), imagined, group)


def sample_batch(data: CostData, batch: int, generator: torch.Generator):
    """One batch: ``z (B, D)``, ``z_next (B, D)``, ``length (B,)`` (a step of the data);
    ``other (B, D)``, a frame of a trajectory in ``z``'s layout group; ``imagined (B, D)`` and
    ``true (B, D)``, an imagined latent of the same trajectory and the one it stands for."""
    latents = data.latents
    n, frames, _ = latents.shape
    i = torch.randint(0, n, (batch,), generator=generator)
    t = torch.randint(0, frames - 1, (batch,), generator=generator)
    j = i // data.group * data.group + torch.randint(0, data.group, (batch,), generator=generator)
    u = torch.randint(0, frames, (batch,), generator=generator)
    pieces, k = data.imagined.shape[1:3]
    p = torch.randint(0, pieces, (batch,), generator=generator)
    s = torch.randint(0, k, (batch,), generator=generator)
    return (latents[i, t], latents[i, t + 1], data.lengths[i, t], latents[j, u],
            data.imagined[i, p, s], latents[i, p * k + s + 1])


class Multiplier(nn.Module):
    """The Lagrange multiplier ``lambda = 100 softplus(raw) > 0`` of the steps' constraint."""

    def __init__(self):
        super().__init__()
        self.raw = nn.Parameter(torch.zeros(()))

    def forward(self) -> torch.Tensor:
        return 100 * F.softplus(self.raw)


def cost_objective(head: CostToGo, multiplier: Multiplier, batch, config: CostConfig):
    """``(loss, terms)`` of one batch. Descending the loss fits the head and, through
    ``-lambda (violation - eps)``, raises lambda while the steps are too long (gradient
    ascent on the multiplier) and lowers it once they hold."""
    z, z_next, length, other, imagined, true = batch
    lam, eps = multiplier(), (TOLERANCE / COST_SCALE) ** 2
    violation = step_violation(head(z, z_next) / COST_SCALE, length / COST_SCALE)
    loss = (spread_loss(head(z, other) / COST_SCALE, CAP / COST_SCALE)
            + lam.detach() * violation - lam * (violation.detach() - eps))
    if config.consistency:
        loss = loss + config.consistency * imagination_gap(head.embed(imagined), head.embed(true))
    return loss, {"violation_px": violation.detach().sqrt() * COST_SCALE,
                  "multiplier": lam.detach()}


def fit_cost_head(model: WorldModel, config: CostConfig) -> tuple[CostToGo, History]:
    """A :class:`CostToGo` fitted on ``model``'s frozen latents; returns ``(head, history)``."""
    return fit_cost_to_go(cost_data(model, config), config)


def fit_cost_to_go(data: CostData, config: CostConfig) -> tuple[CostToGo, History]:
    """Fit a head on ``data`` (:func:`cost_data`) by :func:`cost_objective`."""
    torch.manual_seed(config.seed)
    head, multiplier = CostToGo(data.latents.shape[-1], config.hidden, config.dims), Multiplier()
    optimizer = torch.optim.Adam([{"params": head.parameters()},
                                  {"params": multiplier.parameters(), "lr": MULTIPLIER_LR}],
                                 lr=LR)
    history = fit(head, optimizer,
                  lambda batch: cost_objective(head, multiplier, batch, config),
                  lambda step: sample_batch(data, config.batch_size,
                                            step_generator(config.seed, step)),
                  config.steps, log_every=50, desc="cost-to-go")
    return head.eval(), history


def cost_head_or_load(model: WorldModel, base: dict, config: CostConfig,
                      name: str) -> CostToGo:
    """The head of ``config`` on ``model`` (trained by the run whose identity is ``base``):
    loaded from ``checkpoints/<name>.pt`` or the cache if it was saved, else fitted and
    saved to the cache. In eval mode, on the CPU."""
    return load_or_fit(name, CostToGo(model.latent_dim, config.hidden, config.dims),
                       lambda: fit_cost_head(model, config), run_identity(config, base=base))
