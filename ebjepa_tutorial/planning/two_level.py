"""A two-level planner (notebook 07): at every re-plan a coarse level (MPPI over macro-actions
of ``coarse.stride`` steps) plans to the goal, and the latent it imagines ``lookahead``
coarse steps ahead is the subgoal the flat planner of :func:`~.mpc.mpc_loop` plans towards."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch

from .mpc import arrival_distance
from .mppi import PlannerConfig, plan, shift_plan


@dataclass(frozen=True)
class TwoLevel:
    """The coarse level of a two-level planner.

    The final approach: once the coarse plan comes within ``reach_px`` of the goal (as the
    model sees it, :func:`~.mpc.arrival_distance`) by its subgoal, the subgoal is the goal
    itself; otherwise an agent at the goal keeps chasing the coarse model's imprecise latents.
    """

    coarse: torch.nn.Module  # models.hierarchy.CoarseModel: rollout(z0, macro) -> latents
    config: PlannerConfig
    lookahead: int = 1  # coarse steps ahead, at most config.horizon
    reach_px: float = 0.0  # 0: no final approach, always the coarse plan's latent
    reach: float | None = None  # reach_px in latent units, set by calibrate()

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

    def aim(self, generators: Sequence[torch.Generator]):
        """The ``aim(z, z_goal, moving)`` of :func:`~.mpc.mpc_loop` for one batch: the
        subgoals ``(B, D)`` of the episodes under way (``moving (B,)``), from a coarse plan
        carried from re-plan to re-plan, shifted by one coarse step each time, its first plan
        cold (J iterations)."""
        state = {"config": self.config, "coarse": None}

        def aim(z: torch.Tensor, z_goal: torch.Tensor, moving: torch.Tensor) -> torch.Tensor:
            config, coarse = state["config"], state["coarse"]
            if coarse is None:
                coarse = z.new_zeros(len(z), config.horizon, 2)  # (B, H', 2)
            target, rows = z_goal.clone(), moving.nonzero()[:, 0]
            if len(rows):
                mine = [generators[i] for i in rows.tolist()]
                target[rows], coarse[rows] = self.subgoals(z[rows], z_goal[rows], config, mine,
                                                           coarse[rows])
            state.update(config=config.warm(), coarse=shift_plan(coarse, 1))
            return target

        return aim
