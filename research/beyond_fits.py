"""Chapter 07's fits on a frozen world model's latents: the cost-to-go head and the coarse model.

What made ``checkpoints/cost_head_*_class.pt`` and ``coarse_*_class.pt`` (run by
``research.fit_beyond``); notebook 07 loads those files (its ``load_fit``). The head, its two
loss terms, the coarse model and the two-level planner are notebook 07's own definitions
(:data:`NOTEBOOK`, read from its cells by ``research.from_notebook``).

The cost head (``CostToGo``) is fitted by the rule of the notebook's ``spread_loss`` and
``step_violation``: pairs of frames of one layout pushed apart, each observed step held within
its action's length by a Lagrange multiplier. The world model's encoder turns fresh data-policy
trajectories into latents once, its predictor imagines short rollouts of them once. The
trajectories come in groups that share a layout (a distance between two layouts means nothing),
long enough to cross a room, and a quarter start at a wall heading in. A planner scores the
head on the predictor's IMAGINED latents, and MPPI seeks out any plan whose imagined latents
the head reads as progress; pushed into a wall the predictor drifts a little, so the fit also
asks the head to read each imagined latent as the true one it stands for (``consistency``).

The coarse model (``CoarseModel``) is fitted on the data policy's random
walks, then again with its own two-level planner's episodes added (DAgger, Ross et al., 2011).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from ebjepa_tutorial.envs import Trajectories, generate_trajectories, random_layouts
from ebjepa_tutorial.losses.world import multistep_prediction_loss
from ebjepa_tutorial.models.world import WorldModel
from ebjepa_tutorial.planning import EpisodeResults, PlannerConfig, run_episodes
from ebjepa_tutorial.training.loop import History, step_generator
from ebjepa_tutorial.utils import check_fields, is_int_at_least

from .fitting import fit, trajectory_latents
from .from_notebook import definitions

# Notebook 07's definitions, run from its cells: what the fits train and the commands load.
NOTEBOOK = definitions("07_beyond_the_paper.ipynb", "COST_SCALE", "CostToGo", "WithLearnedCost",
                       "step_violation", "spread_loss", "load_fit", "CoarseModel", "TwoLevel",
                       "cost_calibration", "correlation")
COST_SCALE, CostToGo, CoarseModel = NOTEBOOK.COST_SCALE, NOTEBOOK.CostToGo, NOTEBOOK.CoarseModel
spread_loss, step_violation = NOTEBOOK.spread_loss, NOTEBOOK.step_violation

# ---- the cost-to-go head ----------------------------------------------------------------------

# The fit's constants (every run of the course uses these):
CAP = 150.0  # C, px: pairs farther apart are hardly pushed (the softplus's hinge)
TOLERANCE = 0.1  # epsilon, px: the root mean square by which steps may exceed their action
LR, MULTIPLIER_LR = 1e-3, 1e-2  # Adam's rate for the head; gradient ascent on the multiplier
WALL_FRACTION = 0.25  # trajectories that start in front of a wall, heading in
IMAGINED_STEPS = 16  # steps of each imagined rollout (a trajectory's steps are a multiple)


@dataclass(frozen=True)
class CostConfig:
    """How a cost-to-go head is fitted. The defaults are the shipped class fits'."""

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


def imagination_gap(imagined: torch.Tensor, true: torch.Tensor) -> torch.Tensor:
    """``mean ||imagined - true||^2`` over embeddings ``(B, k)``: how differently the head reads
    the predictor's imagined latents and the true ones they stand for."""
    if imagined.shape != true.shape:
        raise ValueError(f"imagined and true must have the same shape, got "
                         f"{tuple(imagined.shape)} and {tuple(true.shape)}")
    return (imagined - true).square().sum(dim=-1).mean()


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


# ---- the coarse model -------------------------------------------------------------------------

# The data policy for the fit (every run of the course). The coarse planner asks for
# macro-actions up to stride x 1.8 px, and MPPI seeks out whatever the model gets wrong: at
# the world model's 1 px mean step the data's 4-step moves stop at about 4.7 px (90th
# percentile), and longer ones pass through walls in imagination. Faster steps and starts
# heading into a wall show the model what it is asked about.
STEP_MEAN = 1.5  # px per step (the data policy clips steps to 0.2-1.8)
COARSE_LR = 1e-3  # Adam's rate
VISIT_EVERY = 8  # the planner's episodes are cut into windows starting every 8 steps
VISIT_SEED = 40_000  # the planner's episodes play seeds from here: a range no evaluation uses


@dataclass(frozen=True)
class CoarseConfig:
    """How the coarse model is fitted. The defaults are the shipped class fits'."""

    stride: int = 4  # S, environment steps per coarse step
    n_trajectories: int = 20_000  # fresh data-policy trajectories of 16 steps: 4 coarse steps
    steps: int = 3000
    batch_size: int = 1024
    hidden: int = 256
    walls: int = 1
    seed: int = 11

    def __post_init__(self):
        check_fields(self, {name: (is_int_at_least(1), "an int >= 1") for name in
                            ("stride", "n_trajectories", "steps", "batch_size", "hidden")})


def macro_actions(actions: torch.Tensor, stride: int) -> torch.Tensor:
    """Sum each ``stride`` consecutive actions: ``(N, T, 2) -> (N, T // stride, 2)``."""
    n, t, a = actions.shape
    return actions[:, : t - t % stride].reshape(n, t // stride, stride, a).sum(dim=2)


def coarse_data(model: WorldModel, config: CoarseConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """Fresh random walks of ``config`` on ``model``'s frozen latents: ``(latents (N, T+1, D),
    actions (N, T, 2))``."""
    data = generate_trajectories(config.n_trajectories, seed=config.seed, walls=config.walls,
                                 step_mean=STEP_MEAN, wall_fraction=WALL_FRACTION)
    return trajectory_latents(model, data), data.actions


def fit_coarse_model(model: WorldModel, config: CoarseConfig) -> tuple[CoarseModel, History]:
    """A :class:`CoarseModel` fitted on ``model``'s frozen latents; ``(coarse, history)``."""
    return fit_coarse_on(*coarse_data(model, config), config)


def fit_coarse_on(latents: torch.Tensor, actions: torch.Tensor,
                  config: CoarseConfig) -> tuple[CoarseModel, History]:
    """Fit on trajectories of latents ``(N, T+1, D)`` and actions ``(N, T, 2)``: the rollout
    error of every coarse step, from the first frame, under the summed actions."""
    coarse_z = latents[:, :: config.stride]  # (N, T // S + 1, D)
    macro = macro_actions(actions, config.stride)  # (N, T // S, 2)
    if macro.shape[1] < 1:
        raise ValueError(f"trajectories of {actions.shape[1]} steps hold no coarse step of "
                         f"{config.stride}")
    torch.manual_seed(config.seed)
    coarse = CoarseModel(latents.shape[-1], config.stride, config.hidden)
    optimizer = torch.optim.Adam(coarse.parameters(), lr=COARSE_LR)

    def batch(step: int):
        index = torch.randint(0, len(latents), (config.batch_size,),
                              generator=step_generator(config.seed, step))
        return coarse_z[index], macro[index]

    def loss(pair):
        z, u = pair
        return multistep_prediction_loss(coarse.predict, z, u, u.shape[1]), {}

    history = fit(coarse, optimizer, loss, batch, config.steps, log_every=50,
                  desc="coarse model")
    return coarse.eval(), history


@dataclass(frozen=True)
class CoarseFit:
    """The coarse model's fit on ``coarse``'s random walks, then again with the episodes of
    the two-level planner built on the first fit added (DAgger, Ross et al., 2011).

    A planner seeks out what its model gets wrong, a long macro-action into a wall beside
    a door, and random walks rarely go there; the planner's own episodes show the model
    what really happens where it is asked. The planner: ``low`` and, over the coarse model,
    ``high``, ``lookahead`` and ``reach_px`` (notebook 07's ``TwoLevel``). It plays ``episodes``
    episodes of ``steps`` steps (:func:`two_level_episodes`), cut into windows as long as the
    walks, one starting every ``VISIT_EVERY`` steps.
    """

    coarse: CoarseConfig
    low: PlannerConfig  # the flat level
    high: PlannerConfig  # the coarse level
    lookahead: int
    reach_px: float
    episodes: int = 300
    steps: int = 200

    def __post_init__(self):
        check_fields(self, {name: (is_int_at_least(1), "an int >= 1") for name in
                            ("lookahead", "episodes", "steps")})


def two_level_episodes(model: WorldModel, coarse: CoarseModel, fit: CoarseFit) -> Trajectories:
    """The episodes of ``fit``'s two-level planner on ``coarse``, as offline data: ``episodes``
    episodes of ``steps`` steps from seed ``VISIT_SEED``, 10 at a time, in
    ``fit.coarse.walls``' world."""
    seeds = range(VISIT_SEED, VISIT_SEED + fit.episodes)
    coarse = copy.deepcopy(coarse).to(next(model.parameters()).device)  # plans beside model
    two_level = NOTEBOOK.TwoLevel(coarse, fit.high, fit.lookahead, fit.reach_px)
    return as_trajectories(run_episodes(model, seeds, fit.low, fit.steps, batch=10,
                                        walls=fit.coarse.walls, two_level=two_level))


def as_trajectories(played: EpisodeResults) -> Trajectories:
    """Played episodes as offline data, as ``envs.generate_trajectories`` stores a random
    walk: positions ``(N, T + 1, 2)``, actions ``(N, T, 2)``, no wall starts."""
    return Trajectories(played.paths, played.actions, played.episodes.layouts,
                        torch.zeros(len(played.seeds), dtype=torch.bool))


def windows(x: torch.Tensor, length: int, every: int) -> torch.Tensor:
    """Windows of ``length`` along the time axis, one starting every ``every`` steps:
    ``(N, T, F) -> (N * W, length, F)`` with ``W = (T - length) // every + 1``."""
    if x.shape[1] < length:
        raise ValueError(f"sequences of {x.shape[1]} steps hold no window of {length}")
    return x.unfold(1, length, every).transpose(-1, -2).flatten(0, 1)


def fit_coarse_with_visits(model: WorldModel, config: CoarseFit) -> tuple[CoarseModel, History]:
    """A coarse model fitted on ``model``'s frozen latents of random walks and of its own
    planner's episodes (:func:`two_level_episodes` on a first fit): ``(coarse, history of the
    second fit)``."""
    latents, actions = coarse_data(model, config.coarse)
    first, _ = fit_coarse_on(latents, actions, config.coarse)
    played = two_level_episodes(model, first, config)
    length = actions.shape[1]  # windows as long as the random walks
    z = windows(trajectory_latents(model, played), length + 1, VISIT_EVERY)
    a = windows(played.actions, length, VISIT_EVERY)
    return fit_coarse_on(torch.cat([latents, z]), torch.cat([actions, a]), config.coarse)
