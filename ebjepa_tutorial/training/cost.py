"""Fit a cost-to-go head on a frozen world model's latents (notebook 07).

The world model is not changed: its encoder turns fresh data-policy
trajectories into latents once, and the head (``models.cost.CostToGo``) is
fitted on them by temporal differences with hindsight goals
(``losses.cost``). Half the goals (``hindsight``) are frames later in the same
trajectory, whose distance the data itself bounds; the rest are frames of
other trajectories in the same layout (a distance between two layouts means
nothing), which the head can only learn by chaining estimates: the long way
round the wall is learned from short pieces. So the trajectories come in
groups that share a layout.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch

from ..envs import generate_trajectories, random_layouts
from ..losses.cost import cost_to_go_targets, expectile_loss
from ..models.cost import CostToGo
from ..models.world import WorldModel, trajectory_latents
from ..utils import check_fields, is_int_at_least, is_positive
from .checkpoints import run_identity
from .loop import History, fit, load_or_fit, step_generator
from .world import upgrade_base


@dataclass(frozen=True)
class CostConfig:
    """How a cost-to-go head is fitted. The defaults are notebook 07's class run."""

    n_trajectories: int = 20_000  # fresh data-policy trajectories, encoded once
    layouts: int = 500  # distinct layouts, each shared by n_trajectories / layouts of them
    steps: int = 4000  # Adam steps
    batch_size: int = 1024
    lr: float = 1e-3
    hidden: int = 256
    tau: float = 0.1  # the expectile: small = the shortest of the data's ways on
    target_momentum: float = 0.99  # dbar <- m * dbar + (1 - m) * d after every step
    hindsight: float = 0.5  # share of goals later in the same trajectory
    walls: int = 1  # 1: Two Rooms; 2: Three Rooms
    seed: int = 7

    def __post_init__(self):
        check_fields(self, {name: (is_int_at_least(1), "an int >= 1") for name in
                            ("n_trajectories", "layouts", "steps", "batch_size",
                             "hidden")})
        if self.n_trajectories % self.layouts:
            raise ValueError(f"n_trajectories ({self.n_trajectories}) must be a multiple of "
                             f"layouts ({self.layouts}): each layout has as many trajectories")
        check_fields(self, {"lr": (is_positive, "a number > 0")})
        for name in ("tau", "target_momentum", "hindsight"):
            if not 0 < getattr(self, name) < 1:
                raise ValueError(f"{name} must be in (0, 1), got {getattr(self, name)}")


def sample_goals(latents: torch.Tensor, actions: torch.Tensor, batch: int, hindsight: float,
                 generator: torch.Generator, group: int = 1):
    """One batch of transitions with goals, from latents ``(N, T+1, D)`` and actions ``(N, T, A)``.

    Trajectories ``k * group .. (k + 1) * group - 1`` share a layout; a goal that is not
    later on its own trajectory is a frame of one of its group's.

    Returns ``z (B, D)``, ``z_next (B, D)``, ``goal (B, D)``, ``step_cost (B,)`` (the
    action's length, px), ``offset (B,)`` and ``spent (B,)`` (see
    :func:`~ebjepa_tutorial.losses.cost.cost_to_go_targets`).
    """
    n, frames, _ = latents.shape
    i = torch.randint(0, n, (batch,), generator=generator)
    t = torch.randint(0, frames - 1, (batch,), generator=generator)
    later = (torch.rand(batch, generator=generator) * (frames - t)).long()  # 0..T-t
    own = torch.rand(batch, generator=generator) < hindsight
    other_i = i // group * group + torch.randint(0, group, (batch,), generator=generator)
    other_t = torch.randint(0, frames, (batch,), generator=generator)
    goal = torch.where(own[:, None], latents[i, t + later],
                       latents[other_i, other_t])
    offset = torch.where(own, later, -1)
    lengths = actions.norm(dim=-1)  # (N, T)
    spent = torch.cat([lengths.new_zeros(n, 1), lengths.cumsum(dim=1)], dim=1)  # (N, T+1)
    spent = spent[i, t + later] - spent[i, t]
    return latents[i, t], latents[i, t + 1], goal, lengths[i, t], offset, spent


class TargetCopy:
    """The slowly moving copy ``dbar`` of a head, updated after every optimiser step."""

    def __init__(self, head: CostToGo, momentum: float):
        self.head, self.momentum = head, momentum
        self.copy = copy.deepcopy(head).requires_grad_(False)

    @torch.no_grad()
    def __call__(self, step: int) -> None:
        for mine, theirs in zip(self.copy.parameters(), self.head.parameters()):
            mine.lerp_(theirs, 1 - self.momentum)


def fit_cost_head(model: WorldModel, config: CostConfig = CostConfig(),
                  progress: bool = True) -> tuple[CostToGo, History]:
    """A :class:`CostToGo` fitted on ``model``'s frozen latents; returns ``(head, history)``."""
    generator = torch.Generator().manual_seed(config.seed)
    group = config.n_trajectories // config.layouts
    layouts = random_layouts(config.layouts, generator, config.walls)
    data = generate_trajectories(config.n_trajectories, seed=generator,
                                 layouts=layouts.repeat_interleave(group, dim=0))
    return fit_cost_to_go(trajectory_latents(model, data), data.actions, config, progress,
                          group)


def fit_cost_to_go(latents: torch.Tensor, actions: torch.Tensor, config: CostConfig,
                   progress: bool = True, group: int = 1) -> tuple[CostToGo, History]:
    """Fit a head on trajectories of latents ``(N, T+1, D)`` and their actions ``(N, T, A)``,
    in groups of ``group`` consecutive trajectories that share a layout (:func:`sample_goals`).
    """
    torch.manual_seed(config.seed)
    head = CostToGo(latents.shape[-1], config.hidden)
    target = TargetCopy(head, config.target_momentum)
    optimizer = torch.optim.Adam(head.parameters(), lr=config.lr)

    def batch(step: int):
        generator = step_generator(config.seed, step)
        return sample_goals(latents, actions, config.batch_size, config.hindsight, generator,
                            group)

    def loss(pairs):
        z, z_next, goal, step_cost, offset, spent = pairs
        with torch.no_grad():
            y = cost_to_go_targets(step_cost, target.copy(z_next, goal), offset, spent)
        return expectile_loss(head(z, goal), y, config.tau), {}

    history = fit(head, optimizer, loss, batch, config.steps, log_every=50,
                  desc="cost-to-go", progress=progress, after_step=target)
    return head.eval(), history


def cost_head_or_load(model: WorldModel, base: dict, config: CostConfig,
                      name: str) -> CostToGo:
    """The head of ``config`` on ``model`` (trained by the run whose identity is ``base``):
    loaded from ``checkpoints/<name>.pt`` or the cache if it was saved, else fitted and
    saved to the cache. In eval mode, on the CPU."""
    return load_or_fit(name, CostToGo(model.latent_dim, config.hidden),
                       lambda: fit_cost_head(model, config), run_identity(config, base=base),
                       upgrade=upgrade_base)
