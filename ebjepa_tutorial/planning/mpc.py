"""The agent: model-predictive control in Two Rooms, and the batched episode runner (notebook 06).
An episode's seed fixes its task and its planner's noise; it reproduces exactly with the same
batch and threads (batched kernels may sum in another order)."""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch

from ..envs import SUCCESS_RADIUS, Episodes, TwoRoomsEnv, make_episodes
from ..envs.two_rooms import random_layouts, render, sample_positions, wall_collision
from ..evaluation.metrics import wilson_interval
from .diagnosis import StateEnv, TrueDynamics
from .mppi import PlannerConfig, goal_distance, mppi_iteration, plan, shift_plan

WORLDS = ("learned", "true", "true_xy")  # what run_episodes imagines with


@dataclass
class EpisodeResults:
    """What happened in a batch of episodes (one row per seed)."""

    seeds: list[int]
    episodes: Episodes
    paths: torch.Tensor  # (B, steps + 1, 2) dot positions, start first
    actions: torch.Tensor  # (B, steps, 2) what the agent asked; action t moved paths[:, t]
    success: torch.Tensor  # (B,) bool: within SUCCESS_RADIUS of the goal at the end
    first_arrival: torch.Tensor  # (B,) long: first step within the radius, -1 if never
    cpu_seconds: float  # process CPU time of the whole batch
    wall_seconds: float

    @classmethod
    def concat(cls, parts: Sequence[EpisodeResults]) -> EpisodeResults:
        """One result from batches run one after the other (times add up)."""
        tensors = [torch.cat([getattr(p, name) for p in parts])
                   for name in ("paths", "actions", "success", "first_arrival")]
        return cls([s for p in parts for s in p.seeds],
                   Episodes.concat([p.episodes for p in parts]), *tensors,
                   sum(p.cpu_seconds for p in parts), sum(p.wall_seconds for p in parts))

    def first(self, n: int) -> EpisodeResults:
        """The first ``n`` episodes (times: this batch's, pro rata)."""
        share = n / len(self.seeds)
        return EpisodeResults(self.seeds[:n], self.episodes[:n], self.paths[:n],
                              self.actions[:n], self.success[:n], self.first_arrival[:n],
                              self.cpu_seconds * share, self.wall_seconds * share)

    @property
    def success_rate(self) -> float:
        return self.success.float().mean().item()

    def interval(self) -> tuple[float, float]:
        """The Wilson 95% interval of the success rate."""
        return wilson_interval(int(self.success.sum()), len(self.seeds))

    @property
    def cpu_seconds_per_episode(self) -> float:
        return self.cpu_seconds / len(self.seeds)

    def summary(self) -> str:
        """Success, its interval, the mean first-arrival step of those that arrived, CPU time."""
        low, high = self.interval()
        steps = self.first_arrival[self.first_arrival >= 0].float()  # the episodes that arrived
        arrived = (f"mean first arrival {steps.mean().item():.0f} steps" if len(steps)
                   else "no episode reached the goal")
        return (f"success {self.success_rate:.0%} (95% CI {low:.0%}-{high:.0%}) over "
                f"{len(self.seeds)} episodes, {arrived}, "
                f"{self.cpu_seconds_per_episode:.2f} s CPU per episode")


def episode_generators(seeds: Sequence[int],
                       walls: int = 1) -> tuple[Episodes, list[torch.Generator]]:
    """The task of each seed and the generator its planner continues with; ``walls``: 1 for
    Two Rooms, 2 for Three Rooms (start and goal in the outer rooms)."""
    generators = [torch.Generator().manual_seed(int(seed)) for seed in seeds]
    return Episodes.concat([make_episodes(1, g, walls) for g in generators]), generators


@torch.no_grad()
def arrival_distance(model, px: float, walls: int = 1) -> float:
    """The latent distance that means "within ``px`` of the goal" to ``model``: the median
    of ``||Enc(o') - Enc(o)||`` over 512 random frames ``o`` (seed 0) and ``o'``, the dot
    moved ``px`` in a random direction (a wall may cut the move short)."""
    n, generator = 512, torch.Generator().manual_seed(0)
    layouts = random_layouts(n, generator, walls)
    here = sample_positions(layouts, generator)
    angle = 2 * math.pi * torch.rand(n, generator=generator)
    there = wall_collision(here, px * torch.stack([angle.cos(), angle.sin()], dim=-1), layouts)
    device = next(model.parameters()).device
    z_here, z_there = (model.encode(render(p, layouts).to(device)) for p in (here, there))
    return (z_there - z_here).norm(dim=-1).median().item()


# Notebook 06 shows this function in a code cell and runs its own copy (a test keeps the two equal).
def mpc_loop(model, env, config, generators, steps, arrived=None, aim=None):
    """Play the B episodes of ``env`` for ``steps`` steps, re-planning every m = config.execute.

    generators: one per episode (its planner's noise). arrived: the latent distance to the
    goal below which an episode stands still and plans nothing (None: always plan).
    aim(z, z_goal, moving): nearer targets (B, D) to plan towards (notebook 07's two levels).
    """
    z_goal = model.encode(env.goal_images())  # (B, D): each goal image, encoded once
    mean = z_goal.new_zeros(len(generators), config.horizon, 2)  # (B, H, A): stand still
    while env.steps_taken < steps:
        z = model.encode(env.observe())  # (B, D): where each dot is, as the model sees it
        moving = torch.ones(len(z), dtype=torch.bool, device=z.device)  # (B,) still under way
        if arrived is not None:
            moving = goal_distance(model, z, z_goal) >= arrived
        mean[~moving] = 0  # the arrived stand still
        target = z_goal if aim is None else aim(z, z_goal, moving)  # (B, D)
        rows = moving.nonzero()[:, 0]
        if len(rows):  # plan H steps ahead, from the previous plan (J iterations the first time)
            mine = [generators[i] for i in rows.tolist()]
            mean[rows] = plan(model, z[rows], target[rows], config, mine, mean[rows],
                              iteration=mppi_iteration).mean
        for action in mean[:, : config.execute].unbind(1)[: steps - env.steps_taken]:
            env.step(action)  # execute the first m actions in the world
        mean = shift_plan(mean, config.execute)  # warm start: the rest of the plan, then zeros
        config = config.warm()  # later re-plans refine habits.warm_iterations times


@torch.no_grad()
def run_episodes(model, seeds: Sequence[int], config: PlannerConfig, steps: int | None = None,
                 batch: int | None = None, world: str = "learned", walls: int = 1,
                 two_level=None, loop=mpc_loop) -> EpisodeResults:
    """Plan and act in one episode per seed with ``loop`` and the planner ``config``.

    Episode ``seed`` draws its layout, start and goal, then its planner's noise, from
    ``torch.Generator().manual_seed(seed)``. ``steps``: None gives the world's step budget;
    ``batch`` episodes run at once (default: all). ``world``: ``"learned"`` imagines with the
    world model, ``"true"`` and ``"true_xy"`` with :class:`~.diagnosis.TrueDynamics`.
    ``two_level``: a high level that picks subgoals, such as notebook 07's ``TwoLevel``:
    ``calibrate(model, walls)`` -> the one to use, ``aim(generators)`` -> one batch's ``aim``.
    """
    if world not in WORLDS:
        raise ValueError(f"world must be one of {WORLDS}, got {world!r}")
    seeds, batch = list(seeds), batch or len(seeds)
    model.eval()
    cpu, wall = time.process_time(), time.perf_counter()
    arrived = None  # the energy below which the agent stands still: pixels for "true_xy"
    stop_px = config.habits.stop_px
    if stop_px:
        arrived = stop_px if world == "true_xy" else arrival_distance(model, stop_px, walls=walls)
    if two_level is not None:
        two_level = two_level.calibrate(model, walls)
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    result = EpisodeResults.concat([
        _run_batch(model, seeds[i:i + batch], config, steps, world, arrived, walls, two_level,
                   loop) for i in range(0, len(seeds), batch)])
    return replace(result, cpu_seconds=result.cpu_seconds + cpu,
                   wall_seconds=result.wall_seconds + wall)


def _run_batch(model, seeds: list[int], config: PlannerConfig, steps: int | None, world: str,
               arrived: float | None, walls: int, two_level, loop) -> EpisodeResults:
    """:func:`run_episodes` for one batch; ``arrived``: the stopping distance."""
    episodes, generators = episode_generators(seeds, walls)
    env = (TwoRoomsEnv if world == "learned" else StateEnv)(next(model.parameters()).device)
    cpu, wall = time.process_time(), time.perf_counter()
    env.reset(episodes=episodes)
    if world != "learned":  # the diagnosis imagines with the true motion
        model = TrueDynamics(env.layouts, model if world == "true" else None)
    aim = None if two_level is None else two_level.aim(generators)
    loop(model, env, config, generators, env.step_budget if steps is None else steps,
         arrived, aim)
    paths, actions = torch.stack(env.path, dim=1).cpu(), torch.stack(env.actions, dim=1).cpu()
    within = (paths[:, 1:] - episodes.goals[:, None]).norm(dim=-1) <= SUCCESS_RADIUS  # (B, T)
    first = torch.where(within.any(dim=1), within.long().argmax(dim=1) + 1, -1)
    return EpisodeResults(seeds, episodes, paths, actions, within[:, -1], first,
                          time.process_time() - cpu, time.perf_counter() - wall)
