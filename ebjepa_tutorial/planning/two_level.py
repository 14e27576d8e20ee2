"""A two-level planner: a coarse model picks subgoals for the flat planner (notebook 07).

At every re-plan the coarse level (MPPI over macro-actions of ``coarse.stride`` steps,
warm-started like the flat plan) plans from the current latent to the goal; the latent it
imagines ``lookahead`` coarse steps ahead is the subgoal that the flat planner of
:func:`~ebjepa_tutorial.planning.mpc.mpc_loop` plans towards over its short horizon.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch

from .mpc import arrival_distance
from .mppi import PlannerConfig, plan, shift_plan


@dataclass(frozen=True)
class TwoLevel:
    """The coarse level of a two-level planner.

    The final approach: once the coarse plan comes within ``reach_px`` of the goal
    (as the model sees it, :func:`~ebjepa_tutorial.planning.mpc.arrival_distance`)
    by its subgoal, the subgoal is the goal itself. Without it an agent at the goal
    keeps chasing the coarse model's imprecise latents, and can walk off the goal again.
    """

    coarse: torch.nn.Module  # models.hierarchy.CoarseModel: rollout(z0, macro) -> latents
    config: PlannerConfig
    lookahead: int = 1
    reach_px: float = 0.0  # 0: no final approach, always the coarse plan's latent
    reach: float | None = None  # reach_px in latent units, set by calibrate()

    def __post_init__(self):
        if not 1 <= self.lookahead <= self.config.horizon:
            raise ValueError(f"lookahead must be in 1..{self.config.horizon} coarse steps (the "
                             f"coarse plan's horizon), got {self.lookahead}")
        if self.reach_px < 0:
            raise ValueError(f"reach_px must be >= 0 px (0: no final approach), got "
                             f"{self.reach_px}")

    def calibrate(self, model, walls: int = 1) -> TwoLevel:
        """The same planner with ``reach`` measured on ``model``'s latents of ``walls``' world
        (once: a calibrated planner is returned as it is)."""
        if not self.reach_px or self.reach is not None:
            return self
        return replace(self, reach=arrival_distance(model, self.reach_px, walls=walls))

    def subgoals(self, z0: torch.Tensor, z_goal: torch.Tensor, config: PlannerConfig,
                 generators: Sequence[torch.Generator], mean: torch.Tensor):
        """``(subgoal latents (B, D), the coarse mean plan (B, H', 2))``."""
        if self.reach_px and self.reach is None:
            raise ValueError("a final approach needs its latent distance: two_level.calibrate("
                             "model, walls) first (run_episodes does it)")
        coarse = plan(self.coarse, z0, z_goal, config, generators, mean).mean
        ahead = self.coarse.rollout(z0, coarse[:, : self.lookahead])  # (B, lookahead, D)
        subgoal = ahead[:, -1]
        if self.reach is not None:  # the goal, where the plan reaches it by the subgoal
            there = (ahead - z_goal[:, None]).norm(dim=-1).amin(dim=1) < self.reach  # (B,)
            subgoal = torch.where(there[:, None], z_goal, subgoal)
        return subgoal, coarse

    def aim(self, generators: Sequence[torch.Generator]) -> _Aim:
        """The ``aim`` of :func:`~ebjepa_tutorial.planning.mpc.mpc_loop` for one batch."""
        return _Aim(self, list(generators))


class _Aim:
    """The subgoals of one batch of episodes: the coarse plan carried from re-plan to
    re-plan, shifted by one coarse step each time, its first plan cold (J iterations)."""

    def __init__(self, two_level: TwoLevel, generators: list[torch.Generator]):
        self.two_level, self.generators = two_level, generators
        self.config, self.coarse = two_level.config, None

    def __call__(self, z: torch.Tensor, z_goal: torch.Tensor,
                 moving: torch.Tensor) -> torch.Tensor:
        """Targets ``(B, D)``: the subgoal of each episode under way (``moving (B,)``)."""
        if self.coarse is None:
            self.coarse = z.new_zeros(len(z), self.config.horizon, 2)  # (B, H', 2)
        target, rows = z_goal.clone(), moving.nonzero()[:, 0]
        if len(rows):
            mine = [self.generators[i] for i in rows.tolist()]
            target[rows], self.coarse[rows] = self.two_level.subgoals(
                z[rows], z_goal[rows], self.config, mine, self.coarse[rows])
        self.config, self.coarse = self.config.warm(), shift_plan(self.coarse, 1)
        return target
