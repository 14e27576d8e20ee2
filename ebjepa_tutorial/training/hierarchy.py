"""Fit a coarse model (``models.hierarchy``) on a frozen world model's latents (notebook 07).

Fitted on the data policy's random walks (:func:`fit_coarse_model`), or fitted
again with its own two-level planner's episodes added (:func:`fit_coarse_with_visits`,
handed the function that plays them, ``planning.two_level_episodes``: a layer up).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from ..envs import Trajectories, generate_trajectories
from ..losses.world import multistep_prediction_loss, windows
from ..models.hierarchy import CoarseModel, macro_actions
from ..models.world import WorldModel, trajectory_latents
from ..utils import check_fields, is_int_at_least
from .checkpoints import run_identity
from .loop import History, fit, load_or_fit, step_generator

# The data policy for the fit (every run of the course). The coarse planner asks for
# macro-actions up to stride x 1.8 px, and MPPI seeks out whatever the model gets wrong: at
# the world model's 1 px mean step the data's 4-step moves stop at about 4.7 px (90th
# percentile), and longer ones pass through walls in imagination. Faster steps and starts
# heading into a wall show the model what it is asked about.
STEP_MEAN = 1.5  # px per step (the data policy clips steps to 0.2-1.8)
WALL_FRACTION = 0.25  # trajectories that start in front of a wall, heading in
LR = 1e-3  # Adam's rate
VISIT_EVERY = 8  # the planner's episodes are cut into windows starting every 8 steps


@dataclass(frozen=True)
class CoarseConfig:
    """How the coarse model is fitted. The defaults are notebook 07's class run."""

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
    optimizer = torch.optim.Adam(coarse.parameters(), lr=LR)

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
    ``high``, ``lookahead`` and ``reach_px`` (``planning.TwoLevel``). It plays ``episodes``
    episodes of ``steps`` steps (``planning.two_level_episodes``: seeds from 40,000, a range
    no evaluation uses), cut into windows as long as the walks, one starting every
    ``VISIT_EVERY`` steps.
    """

    coarse: CoarseConfig
    low: object  # planning.PlannerConfig of the flat level
    high: object  # planning.PlannerConfig of the coarse level
    lookahead: int
    reach_px: float
    episodes: int = 300
    steps: int = 200

    def __post_init__(self):
        check_fields(self, {name: (is_int_at_least(1), "an int >= 1") for name in
                            ("lookahead", "episodes", "steps")})


def fit_coarse_with_visits(model: WorldModel, config: CoarseFit,
                           play: Callable[[WorldModel, CoarseModel, CoarseFit], Trajectories]
                           ) -> tuple[CoarseModel, History]:
    """A coarse model fitted on ``model``'s frozen latents of random walks and of its own
    planner's episodes: ``(coarse, history of the second fit)``. ``play(model, coarse,
    config)``: the two-level planner's episodes on a first fit (``planning.two_level_episodes``)."""
    latents, actions = coarse_data(model, config.coarse)
    first, _ = fit_coarse_on(latents, actions, config.coarse)
    played = play(model, first, config)
    length = actions.shape[1]  # windows as long as the random walks
    z = windows(trajectory_latents(model, played), length + 1, VISIT_EVERY)
    a = windows(played.actions, length, VISIT_EVERY)
    return fit_coarse_on(torch.cat([latents, z]), torch.cat([actions, a]), config.coarse)


def coarse_or_load(model: WorldModel, base: dict, config, name: str,
                   play: Callable | None = None) -> CoarseModel:
    """The coarse model of ``config`` on ``model`` (trained by the run whose identity is
    ``base``): loaded from ``checkpoints/<name>.pt`` or the cache if it was saved, else
    fitted and saved to the cache. In eval mode, on the CPU.

    ``config``: a :class:`CoarseConfig` (:func:`fit_coarse_model`), or a :class:`CoarseFit`
    (:func:`fit_coarse_with_visits`, whose planner ``play`` plays: ``planning.two_level_episodes``).
    """
    if isinstance(config, CoarseFit):
        if play is None:
            raise TypeError("a CoarseFit plays its planner: coarse_or_load(..., "
                            "play=planning.two_level_episodes)")
        fit = lambda: fit_coarse_with_visits(model, config, play)  # noqa: E731
    else:
        fit = lambda: fit_coarse_model(model, config)  # noqa: E731
    shape = getattr(config, "coarse", config)
    return load_or_fit(name, CoarseModel(model.latent_dim, shape.stride, shape.hidden),
                       fit, run_identity(config, base=base))
