"""Evaluation episodes in Two Rooms, and the batched environment a planner acts in.

An episode: a fresh layout, a start in one outer room and a goal in the other, shown as an
image. It succeeds when the dot ends within ``SUCCESS_RADIUS`` = 4.5 px of the goal within
the step budget: 200 steps in Two Rooms, where a good path takes 30.1 steps at the median
and 69.9 at worst; 120 in Three Rooms (42.4 and 94.8), tight enough that a planner sliding
along the walls until it stumbles on a door runs out of time.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..utils import as_generator
from .two_rooms import (
    check_actions,
    check_layouts,
    check_positions,
    random_layouts,
    render,
    room_of,
    sample_positions,
    transition,
    wall_count,
)

SUCCESS_RADIUS = 4.5
EPISODE_STEPS = 200
THREE_ROOMS_EPISODE_STEPS = 120  # the worst good path's 95 steps and 25 to spare


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
    """``n`` tasks, start and goal uniform over the floors of the two outer rooms (which holds
    the start is drawn per task). ``walls``: 1 or 2; ``seed``: an int or a ``torch.Generator``."""
    generator = as_generator(seed)
    layouts = random_layouts(n, generator, walls)
    start_rooms = torch.randint(0, 2, (n,), generator=generator) * walls  # 0 or the last room
    starts = sample_positions(layouts, generator, start_rooms)
    goals = sample_positions(layouts, generator, walls - start_rooms)
    return Episodes(layouts, starts, goals)


def step_budget(layouts: torch.Tensor) -> int:
    """The steps an episode of these layouts (B, 2W) may take: 200 with one wall, 120 with two."""
    return {1: EPISODE_STEPS, 2: THREE_ROOMS_EPISODE_STEPS}[wall_count(layouts)]


class TwoRoomsEnv:
    """A batch of Two (or Three) Rooms worlds that a planner acts in, all stepped at once.

    >>> env = TwoRoomsEnv()
    >>> obs = env.reset(n=100, seed=1)          # (100, 2, 65, 65)
    >>> goal = env.goal_images()                # (100, 2, 65, 65)
    >>> obs = env.step(torch.zeros(100, 2))      # actions (B, 2), clipped to MAX_STEP
    >>> env.success()                           # (100,) bool

    State: ``positions``, ``goals`` (B, 2), ``layouts`` (B, 2W), ``steps_taken``; ``path``
    (each step's positions, start first) and ``actions``. Steps use :func:`transition`.
    """

    def __init__(self, device: str | torch.device = "cpu"):
        self.device = torch.device(device)
        self.positions: torch.Tensor | None = None

    def reset(self, n: int = 1, seed=0, episodes: Episodes | None = None) -> torch.Tensor:
        """Start ``n`` new Two Rooms episodes from ``seed`` (or the given ones); observe them."""
        episodes = make_episodes(n, seed) if episodes is None else episodes
        check_layouts(episodes.layouts)
        check_positions(episodes.starts, episodes.layouts)
        self.episodes = episodes.to(self.device)
        self.layouts, self.goals = self.episodes.layouts, self.episodes.goals
        self.step_budget = step_budget(self.layouts)  # EPISODE_STEPS or THREE_ROOMS_...
        self.positions = self.episodes.starts.clone()
        self.steps_taken, self.path, self.actions = 0, [self.positions], []
        return self.observe()

    def observe(self) -> torch.Tensor:
        """Current images: (B, 2, 65, 65) float32."""
        self._check_started()
        return render(self.positions, self.layouts)

    def _check_started(self) -> None:
        if self.positions is None:
            raise RuntimeError("call env.reset(n, seed) before using the environment")

    def goal_images(self) -> torch.Tensor:
        """Goal images: (B, 2, 65, 65) float32."""
        return self.episodes.goal_images()

    def step(self, actions: torch.Tensor) -> torch.Tensor:
        """Move every world by its action (B, 2); returns the new observations."""
        self._check_started()
        check_actions(actions, len(self.layouts), self.positions.dtype)
        self.actions.append(actions.clone())  # the caller may reuse its tensor
        actions = actions.to(device=self.device, dtype=self.positions.dtype)
        self.positions = transition(self.positions, actions, self.layouts)
        self.steps_taken += 1
        self.path.append(self.positions)
        return self.observe()

    def distance_to_goal(self) -> torch.Tensor:
        """Euclidean distance from dot to goal, px: (B,)."""
        return (self.positions - self.goals).norm(dim=-1)

    def success(self) -> torch.Tensor:
        """Whether each dot is within ``SUCCESS_RADIUS`` px of its goal: (B,) bool."""
        return self.distance_to_goal() <= SUCCESS_RADIUS

    def rooms(self) -> torch.Tensor:
        """Room of each dot, 0 (leftmost) .. W: (B,) long."""
        return room_of(self.positions, self.layouts)
