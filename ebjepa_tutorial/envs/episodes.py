"""Evaluation episodes in Two Rooms (start in one outer room, goal in the other, success within
``SUCCESS_RADIUS`` px), and :class:`TwoRoomsEnv`, the batched environment a planner acts in."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..utils import as_generator
from .two_rooms import check_world, random_layouts, render, room_of, sample_positions, transition

SUCCESS_RADIUS = 4.5
# step budgets: a path through each door's centre row takes 30.1 steps at the median and 69.9
# at worst in Two Rooms, 42.4 and 94.8 in Three Rooms, whose budget is too short for sliding
# along walls to find a door
EPISODE_STEPS = 200
THREE_ROOMS_EPISODE_STEPS = 120


@dataclass
class Episodes:
    """B evaluation tasks: layouts (B, 2W) long, starts (B, 2) and goals (B, 2) float32."""

    layouts: torch.Tensor
    starts: torch.Tensor
    goals: torch.Tensor

    def __len__(self) -> int:
        return len(self.layouts)

    def goal_images(self) -> torch.Tensor:
        """The goals as the planner sees them: (B, 2, 65, 65) float32."""
        return render(self.goals, self.layouts)

    def to(self, device) -> Episodes:
        return Episodes(self.layouts.to(device), self.starts.to(device), self.goals.to(device))

    def __getitem__(self, index) -> Episodes:
        return Episodes(self.layouts[index], self.starts[index], self.goals[index])

    @staticmethod
    def concat(parts: list[Episodes]) -> Episodes:
        return Episodes(*(torch.cat([getattr(p, name) for p in parts])
                          for name in ("layouts", "starts", "goals")))


def make_episodes(n: int, seed=0, walls: int = 1) -> Episodes:
    """``n`` tasks of ``walls`` walls, start and goal uniform over the floors of the two outer
    rooms (which holds the start is drawn per task); ``seed``: an int or a torch.Generator."""
    generator = as_generator(seed)
    layouts = random_layouts(n, generator, walls)
    start_rooms = torch.randint(0, 2, (n,), generator=generator) * walls  # 0 or the last room
    starts = sample_positions(layouts, generator, start_rooms)
    goals = sample_positions(layouts, generator, walls - start_rooms)
    return Episodes(layouts, starts, goals)


def step_budget(layouts: torch.Tensor) -> int:
    """The steps an episode of these layouts (B, 2W) may take: 200 with one wall, 120 with two."""
    return EPISODE_STEPS if layouts.shape[1] == 2 else THREE_ROOMS_EPISODE_STEPS


class TwoRoomsEnv:
    """B worlds stepped at once: ``reset(n, seed)`` or ``reset(episodes=...)``, then ``step(actions
    (B, 2))``, each returning images (B, 2, 65, 65). State: ``positions``, ``goals`` (B, 2),
    ``layouts`` (B, 2W), ``steps_taken``, ``path`` (positions, start first) and ``actions``."""

    def __init__(self, device: str | torch.device = "cpu"):
        self.device = torch.device(device)
        self.positions: torch.Tensor | None = None

    def reset(self, n: int = 1, seed=0, episodes: Episodes | None = None) -> torch.Tensor:
        """Start ``n`` new Two Rooms episodes from ``seed`` (or the given ones); observe them."""
        episodes = make_episodes(n, seed) if episodes is None else episodes
        check_world(episodes.layouts, episodes.starts)
        self.episodes = episodes.to(self.device)
        self.layouts, self.goals = self.episodes.layouts, self.episodes.goals
        self.step_budget = step_budget(self.layouts)
        self.positions = self.episodes.starts.clone()
        self.steps_taken, self.path, self.actions = 0, [self.positions], []
        return self.observe()

    def _check_started(self) -> None:
        if self.positions is None:
            raise RuntimeError("call env.reset(n, seed) before using the environment")

    def observe(self) -> torch.Tensor:
        """Current images: (B, 2, 65, 65) float32."""
        self._check_started()
        return render(self.positions, self.layouts)

    def goal_images(self) -> torch.Tensor:
        """Goal images: (B, 2, 65, 65) float32."""
        self._check_started()
        return self.episodes.goal_images()

    def step(self, actions: torch.Tensor) -> torch.Tensor:
        """Move every world by its action (B, 2) with ``transition``; observe them."""
        self._check_started()
        dtype = self.positions.dtype
        if actions.shape != (len(self.layouts), 2) or not actions.to(dtype).isfinite().all():
            largest = f", {actions.abs().max()} at most" if actions.numel() else ""
            raise ValueError(f"actions must have shape ({len(self.layouts)}, 2), one (dx, dy) per "
                             f"world, finite also in {dtype} (not NaN, infinite or too large); "
                             f"got shape {tuple(actions.shape)}{largest}")
        actions = actions.detach()  # a world is not differentiable: plan through the model
        self.actions.append(actions.clone())  # the caller may reuse its tensor
        self.positions = transition(self.positions, actions.to(self.device, dtype), self.layouts)
        self.steps_taken += 1
        self.path.append(self.positions)
        return self.observe()

    def distance_to_goal(self) -> torch.Tensor:
        """Euclidean distance from dot to goal, px: (B,)."""
        self._check_started()
        return (self.positions - self.goals).norm(dim=-1)

    def success(self) -> torch.Tensor:
        """Whether each dot is within ``SUCCESS_RADIUS`` px of its goal: (B,) bool."""
        return self.distance_to_goal() <= SUCCESS_RADIUS

    def rooms(self) -> torch.Tensor:
        """Room of each dot, 0 (leftmost) .. W: (B,) long."""
        self._check_started()
        return room_of(self.positions, self.layouts)
