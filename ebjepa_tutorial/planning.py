"""Goal-conditioned planning with a world model (notebooks 06 and 07): the energy of a plan,
MPPI and CEM (the paper's Eq. 13 and Algorithm 1), the re-planning agent, its batched episodes,
and a diagnosis that imagines with the true motion."""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from types import SimpleNamespace

import torch

from . import envs
from .envs import MAX_STEP, clip_actions
from .envs.trajectories import roll_out
from .envs.two_rooms import HIGH, LOW, in_wall, wall_collision
from .evaluation.metrics import wilson_interval
from .utils import check_fields, is_int_at_least, is_non_negative, is_positive

METHODS = ("mppi", "cem")
COSTS = ("sum", "last", "learned")
WORLDS = ("learned", "true", "true_xy")  # what run_episodes imagines with
MIN_STD = 0.05  # the smallest spread after an update, px: agreeing elites still explore


@dataclass(frozen=True)
class Noise:
    """How a re-plan samples around its mean: a spread of ``std`` px at first, a fresh draw
    about every ``period`` steps joined by straight lines, each step clipped to ``bound`` px."""

    std: float = 2.0  # wide enough for samples pressed on the wall to slide along it to the door
    period: int = 8  # 1: i.i.d. noise per step (Algorithm 1); white noise explores too little
    bound: float = MAX_STEP  # the longest step in the data (the coarse level: its stride's)

    def __post_init__(self):
        check_fields(self, {
            "std": (is_positive, "a finite number > 0", "the spread of the first samples, px"),
            "period": (is_int_at_least(1), "an int >= 1"),
            "bound": (is_positive, "a finite number > 0", "the longest sampled step, px")})


@dataclass(frozen=True)
class Habits:
    """Two habits that cut an episode's cost several times (notebook 06, "Speed"). The
    paper's agent has neither: ``Habits(warm_iterations=0, stop_px=0)``."""

    warm_iterations: int = 3  # refinements (at most J) of a re-plan from the previous plan; 0: J
    stop_px: float = 2.0  # stand still within this of the goal (see arrival_distance); 0: never

    def __post_init__(self):
        check_fields(self, {"warm_iterations": (is_int_at_least(0), "an int >= 0"),
                            "stop_px": (is_non_negative, "a finite number >= 0")})


@dataclass(frozen=True)
class PlannerConfig:
    """One planner. The defaults are the class-scale MPPI of notebook 06."""

    method: str = "mppi"  # "mppi" (weighted elites) or "cem" (plain mean of elites)
    cost: str = "sum"  # "sum" over the horizon, "last" step only, "learned" cost-to-go
    horizon: int = 64  # H, imagined steps per plan
    samples: int = 200  # N, action sequences per iteration
    elites: int = 20  # Q, the best of them that move the plan
    iterations: int = 6  # J, refinements per re-plan
    temperature: float = 0.05  # tau, MPPI's softness (latent-distance units)
    execute: int = 4  # m, actions executed before re-planning
    noise: Noise = Noise()  # how the samples are drawn around the plan
    habits: Habits = Habits()  # fewer refinements of a warm plan; standing still once arrived

    def __post_init__(self):
        if self.method not in METHODS or self.cost not in COSTS:
            raise ValueError(f"method must be one of {METHODS} and cost one of {COSTS}, "
                             f"got method={self.method!r}, cost={self.cost!r}")
        rules = {name: (is_int_at_least(1), "an int >= 1")
                 for name in ("horizon", "elites", "iterations", "execute")}
        check_fields(self, {**rules, "temperature": (is_positive, "a finite number > 0"),
                            "samples": (is_int_at_least(2), "an int >= 2",
                                        "plans per iteration: sample 0 is the mean"),
                            "noise": (lambda v: isinstance(v, Noise), "a planning.Noise(...)"),
                            "habits": (lambda v: isinstance(v, Habits), "a planning.Habits(...)")})
        if self.elites > self.samples or self.execute > self.horizon:
            raise ValueError(f"need elites <= samples and execute <= horizon, got elites "
                             f"(Q={self.elites}), samples (N={self.samples}), execute "
                             f"(m={self.execute}), horizon (H={self.horizon})")

    def warm(self) -> PlannerConfig:
        """This planner for the re-plans after an episode's first: warm_iterations (at most J)."""
        return replace(self, iterations=min(self.habits.warm_iterations or self.iterations,
                                            self.iterations))


def goal_distance(model, z: torch.Tensor, z_goal: torch.Tensor) -> torch.Tensor:
    """The energy of single states, ``||z - z_goal||`` over the last dimension: ``(...)``
    (a model with a ``distance`` of its own, like ``TrueDynamics``, measures its way)."""
    if hasattr(model, "distance"):
        return model.distance(z, z_goal)
    return (z - z_goal).norm(dim=-1)


def planning_cost(model, z0: torch.Tensor, z_goal: torch.Tensor, actions: torch.Tensor,
                  cost: str = "sum") -> torch.Tensor:
    """The energy of each imagined plan, ``z0 (B, D), z_goal (B, D), actions (B, N, H, A) ->
    (B, N)``: ``S = sum_{k=1..H} ||zhat_k - z_goal||`` (``"sum"``, the paper's Eq. 13), its
    last term (``"last"``), or ``model.cost_to_go(zhat_H, z_goal)`` (``"learned"``)."""
    if cost not in COSTS or (cost == "learned" and not hasattr(model, "cost_to_go")):
        raise ValueError(f"cost must be one of {COSTS}, got {cost!r} ('learned' needs a model "
                         "with a cost_to_go(z, z_goal) method: notebook 07's WithLearnedCost)")
    if z0.ndim != 2 or z_goal.ndim != 2 or len(z_goal) != len(z0):  # (1, D) would broadcast
        raise ValueError(f"z0 and z_goal must be latents (B, D), one goal per start; got z0 "
                         f"{tuple(z0.shape)}, z_goal {tuple(z_goal.shape)} (images? encode them "
                         "first with model.encode; one start: z0[None] and z_goal[None]; one goal "
                         f"for all starts: z_goal.expand({len(z0) if z0.ndim == 2 else 'B'}, -1))")
    if actions.ndim != 4 or len(actions) != len(z0):
        raise ValueError(f"actions must be plans ({len(z0)}, N, H, A), N per start in z0 "
                         f"{tuple(z0.shape)}; got {tuple(actions.shape)}")
    b, n, h, _ = actions.shape
    z = model.rollout(z0.repeat_interleave(n, dim=0), actions.flatten(0, 1)).view(b, n, h, -1)
    if cost == "learned":
        return model.cost_to_go(z[:, :, -1], z_goal[:, None])
    energy = goal_distance(model, z, z_goal[:, None, None])  # (B, N, H)
    return energy.sum(dim=-1) if cost == "sum" else energy[..., -1]


def select_elites(actions: torch.Tensor, costs: torch.Tensor, elites: int):
    """The ``Q`` cheapest plans of each episode, cheapest first: ``(B, Q, H, A), (B, Q)``."""
    elite_costs, index = costs.topk(elites, dim=1, largest=False)
    elite_actions = actions.gather(1, index[:, :, None, None].expand(-1, -1, *actions.shape[2:]))
    return elite_actions, elite_costs


def mppi_weights(elite_costs: torch.Tensor, temperature: float) -> torch.Tensor:
    """``w_i = exp(-(S_i - S_min) / tau) / sum_j exp(-(S_j - S_min) / tau)``: (B, Q) -> (B, Q)."""
    # S_min cancels in the ratio but keeps exp from underflowing to 0/0
    shifted = elite_costs - elite_costs.min(dim=1, keepdim=True).values
    return torch.softmax(-shifted / temperature, dim=1)


def weighted_mean_std(elite_actions: torch.Tensor, weights: torch.Tensor):
    """Mean and std of the elites under ``weights`` (B, Q): two ``(B, H, A)`` tensors."""
    w = weights[:, :, None, None]
    mean = (w * elite_actions).sum(dim=1)
    std = (w * (elite_actions - mean[:, None]).pow(2)).sum(dim=1).sqrt()
    return mean, std


def mppi_update(actions: torch.Tensor, costs: torch.Tensor, elites: int, temperature: float):
    """One MPPI update: sampled plans ``(B, N, H, A)`` and costs ``(B, N)`` -> new mean, std."""
    elite_actions, elite_costs = select_elites(actions, costs, elites)
    return weighted_mean_std(elite_actions, mppi_weights(elite_costs, temperature))


def cem_update(actions: torch.Tensor, costs: torch.Tensor, elites: int):
    """One CEM update: the plain mean and std of the ``Q`` elites."""
    elite_actions, _ = select_elites(actions, costs, elites)
    uniform = elite_actions.new_full(elite_actions.shape[:2], 1.0 / elites)
    return weighted_mean_std(elite_actions, uniform)


def smooth_noise(samples: int, horizon: int, dims: int, period: int,
                 generator: torch.Generator) -> torch.Tensor:
    """Standard normal noise ``(samples, horizon, dims)``: independent draws a little over
    ``period`` steps apart (evenly over ``period * (horizon // period + 2)`` steps, cut to
    ``horizon``), joined by straight lines (``period=1``: i.i.d.)."""
    knots = torch.randn(samples, dims, horizon // period + 2, generator=generator)
    if period == 1:
        return knots[..., :horizon].transpose(1, 2)
    line = torch.nn.functional.interpolate(knots, scale_factor=period, mode="linear",
                                           align_corners=True)[..., :horizon]
    return (line / line.std(dim=(0, 2), keepdim=True).clamp_min(1e-6)).transpose(1, 2)


# Notebook 06 shows this function in a code cell and runs its own copy (a test keeps them equal).
def mppi_iteration(model, z0, z_goal, mean, std, config, generators):
    """One MPPI (or CEM) iteration for B episodes: sample, imagine, score, update.

    z0 (B, D), z_goal (B, D); mean, std (B, H, A): the plan and its spread.
    Returns the new mean and std (B, H, A), the samples (B, N, H, A) and their costs (B, N).
    """
    # 1. Sample N plans around the mean: a_i = mean + std * eps_i, each episode with its own
    # generator; eps is smooth noise (a fresh draw every noise.period steps).
    eps = torch.stack([smooth_noise(config.samples, config.horizon, mean.shape[-1],
                                    config.noise.period, g) for g in generators])
    eps[:, 0] = 0  # sample 0 is the mean itself: a good plan is never lost to bad luck
    actions = clip_actions(mean[:, None] + std[:, None] * eps.to(mean.device),
                           config.noise.bound)  # (B, N, H, A), no step longer than the data's
    # 2. Imagine each plan with the predictor, 3. score it: S_i = sum_k ||zhat_k - z_goal||
    costs = planning_cost(model, z0, z_goal, actions, config.cost)  # (B, N)
    # 4. Keep the Q cheapest, weight them by exp(-(S_i - S_min) / tau): the new mean and spread
    if config.method == "mppi":
        mean, std = mppi_update(actions, costs, config.elites, config.temperature)
    else:  # CEM: every elite counts the same
        mean, std = cem_update(actions, costs, config.elites)
    spread = std.clamp_min(MIN_STD)  # a spread of 0 would stop the search for good
    return mean, spread, actions, costs


@dataclass
class Plan:
    """:func:`plan`'s mean plan and spread ``(B, H, A)``, its cheapest sample's cost per iteration
    ``(B, J)`` and, with ``record``, each iteration's samples ``(B, N, H, A)`` and costs."""

    mean: torch.Tensor
    std: torch.Tensor
    costs: torch.Tensor
    history: list[tuple[torch.Tensor, torch.Tensor]] | None = None


@torch.no_grad()
def plan(model, z0: torch.Tensor, z_goal: torch.Tensor, config: PlannerConfig,
         generators: Sequence[torch.Generator], mean: torch.Tensor | None = None,
         record: bool = False, iteration=mppi_iteration) -> Plan:
    """Run ``J`` iterations from latents ``z0`` to goals ``z_goal`` (both ``(B, D)``) from the
    warm start ``mean`` ``(B, H, A)`` (default zeros: stand still) with ``iteration``."""
    if not (isinstance(generators, Sequence) and len(generators) == len(z0)
            and all(isinstance(g, torch.Generator) for g in generators)):  # else one is shared
        raise ValueError(f"generators must be one torch.Generator per start, {len(z0)} here: "
                         f"[torch.Generator().manual_seed(s) for s in seeds]; got {generators!r}")
    if mean is None:
        mean = z0.new_zeros(len(z0), config.horizon, model.config.action_dim)
    std = torch.full_like(mean, config.noise.std)
    best, history = [], [] if record else None
    for _ in range(config.iterations):
        mean, std, actions, costs = iteration(model, z0, z_goal, mean, std, config, generators)
        best.append(costs.min(dim=1).values)
        if record:
            history.append((actions.cpu(), costs.cpu()))
    return Plan(mean, std, torch.stack(best, dim=1), history)


def shift_plan(mean: torch.Tensor, executed: int) -> torch.Tensor:
    """The warm start for the next re-plan: drop the executed actions, pad with zeros."""
    return torch.cat([mean[:, executed:], torch.zeros_like(mean[:, :executed])], dim=1)


@dataclass
class EpisodeResults:
    """What happened in a batch of episodes (one row per seed)."""

    seeds: list[int]
    episodes: envs.Episodes
    paths: torch.Tensor  # (B, steps + 1, 2) dot positions, start first
    actions: torch.Tensor  # (B, steps, 2) what the agent asked; action t moved paths[:, t]
    success: torch.Tensor  # (B,) bool: within SUCCESS_RADIUS of the goal at the end
    first_arrival: torch.Tensor  # (B,) long: first step within the radius, -1 if never
    cpu_seconds: float  # process CPU time of the whole batch
    wall_seconds: float

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


def episode_generators(seeds: Sequence[int], walls: int = 1):
    """``(episodes, generators)``: the task of each seed (``walls``: 1 Two Rooms, 2 Three
    Rooms) and the generator its planner continues with."""
    generators = [torch.Generator().manual_seed(int(seed)) for seed in seeds]
    return envs.Episodes.concat([envs.make_episodes(1, g, walls) for g in generators]), generators


@torch.no_grad()
def arrival_distance(model, px: float, walls: int = 1) -> float:
    """The latent distance that means "within ``px`` of the goal" to ``model``: the median
    of ``||Enc(o') - Enc(o)||`` over 512 random frames ``o`` (seed 0) and ``o'``, the dot
    moved ``px`` in a random direction (a wall may cut the move short)."""
    n, generator = 512, torch.Generator().manual_seed(0)
    layouts = envs.random_layouts(n, generator, walls)
    here = envs.sample_positions(layouts, generator)
    angle = 2 * math.pi * torch.rand(n, generator=generator)
    there = wall_collision(here, px * torch.stack([angle.cos(), angle.sin()], dim=-1), layouts)
    device = next(model.parameters()).device
    z_here, z_there = (model.encode(envs.render(p, layouts).to(device)) for p in (here, there))
    return (z_there - z_here).norm(dim=-1).median().item()


# Notebook 06 shows this function in a code cell and runs its own copy (a test keeps them equal).
def mpc_loop(model, env, config, generators, steps, arrived=None, aim=None):
    """Play the B episodes of ``env`` for ``steps`` steps, re-planning every m = config.execute.

    generators: one per episode (its planner's noise). arrived: the latent distance to the
    goal below which an episode stands still and plans nothing (None: always plan).
    aim(z, z_goal, moving): nearer targets (B, D) to plan towards (notebook 07's two levels).
    """
    z_goal = model.encode(env.goal_images())  # (B, D): each goal image, encoded once
    mean = z_goal.new_zeros(len(generators), config.horizon, model.config.action_dim)  # (B, H, A)
    while env.steps_taken < steps:
        z = model.encode(env.observe())  # (B, D): where each dot is, as the model sees it
        moving = torch.ones(len(z), dtype=torch.bool, device=z.device)  # (B,) still under way
        if arrived is not None:
            moving = goal_distance(model, z, z_goal) >= arrived
        mean[~moving] = 0  # the arrived stand still
        target = z_goal if aim is None else aim(z, z_goal, moving)  # (B, D)
        rows = moving.nonzero()[:, 0]  # (R,): the episodes that plan
        if len(rows):  # plan H steps ahead, from the previous plan (J iterations the first time)
            mine = [generators[i] for i in rows.tolist()]
            mean[rows] = plan(model, z[rows], target[rows], config, mine, mean[rows],
                              iteration=mppi_iteration).mean
        # execute the first m actions in the world, each (B, 2); the slice keeps the last
        # re-plan from running past the step budget
        for action in mean[:, : config.execute].unbind(1)[: steps - env.steps_taken]:
            env.step(action)
        mean = shift_plan(mean, config.execute)  # warm start: the rest of the plan, then zeros
        config = config.warm()  # later re-plans refine habits.warm_iterations times


@torch.no_grad()
def run_episodes(model, seeds: Sequence[int], config: PlannerConfig, steps: int | None = None,
                 batch: int | None = None, world: str = "learned", walls: int = 1,
                 two_level=None, loop=mpc_loop) -> EpisodeResults:
    """Play one episode per seed (its layout, start, goal, then its planner's noise drawn from
    ``manual_seed(seed)``) with ``loop``, ``batch`` at a time (default: all), for ``steps``
    (default: the world's budget). ``world``: imagine with the ``"learned"`` model, or with the
    true motion (:class:`TrueDynamics`) and its energy (``"true"``) or pixels (``"true_xy"``).
    ``two_level``: a high level that picks subgoals, as notebook 07's ``TwoLevel``."""
    if world not in WORLDS:
        raise ValueError(f"world must be one of {WORLDS}, got {world!r}")
    if isinstance(seeds, int):  # a count or one seed? neither is guessed
        raise TypeError(f"seeds must be a sequence of ints, one episode each (e.g. "
                        f"range({seeds}, {seeds} + 10)); got the int {seeds}")
    seeds = list(seeds)
    batch = len(seeds) if batch is None else batch
    if not seeds or not (steps is None or is_int_at_least(1)(steps)) or not is_int_at_least(1)(
            batch):
        raise ValueError(f"run_episodes needs at least one seed (one episode per seed), steps "
                         f"None or an int >= 1 and batch None or an int >= 1; got {len(seeds)} "
                         f"seeds, steps={steps!r}, batch={batch!r}")
    model.eval()
    cpu, wall = time.process_time(), time.perf_counter()
    arrived = None  # the energy below which the agent stands still: pixels for "true_xy"
    stop_px = config.habits.stop_px
    if stop_px:
        arrived = stop_px if world == "true_xy" else arrival_distance(model, stop_px, walls=walls)
    if two_level is not None:
        two_level = two_level.calibrate(model, walls)
    played = [_run_batch(model, seeds[i:i + batch], config, steps, world, arrived, walls,
                         two_level, loop) for i in range(0, len(seeds), batch)]
    episodes = envs.Episodes.concat([tasks for tasks, _ in played])
    paths = torch.cat([torch.stack(env.path, dim=1).cpu() for _, env in played])  # (B, T + 1, 2)
    actions = torch.cat([torch.stack(env.actions, dim=1).cpu() for _, env in played])
    within = (paths[:, 1:] - episodes.goals[:, None]).norm(dim=-1) <= envs.SUCCESS_RADIUS
    first = torch.where(within.any(dim=1), within.long().argmax(dim=1) + 1, -1)
    return EpisodeResults(seeds, episodes, paths, actions, within[:, -1], first,
                          time.process_time() - cpu, time.perf_counter() - wall)


def _run_batch(model, seeds: list[int], config: PlannerConfig, steps: int | None, world: str,
               arrived: float | None, walls: int, two_level, loop):
    """:func:`run_episodes` for one batch: ``(its episodes, the environment that played them)``."""
    episodes, generators = episode_generators(seeds, walls)
    env = (envs.TwoRoomsEnv if world == "learned" else StateEnv)(next(model.parameters()).device)
    env.reset(episodes=episodes)
    if world != "learned":  # the diagnosis imagines with the true motion
        model = TrueDynamics(env.layouts, model if world == "true" else None)
    aim = None if two_level is None else two_level.aim(generators)
    loop(model, env, config, generators, env.step_budget if steps is None else steps,
         arrived, aim)
    return episodes, env


def dot_grid(spacing: float = 1.0, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Dot positions every ``spacing`` px over the arena: ``coords (G,)``, ``xy (G*G, 2)``;
    row ``i * G + j`` of ``xy`` is ``(x=coords[j], y=coords[i])``: image order."""
    coords = torch.arange(LOW, HIGH + 1e-6, spacing, device=device)
    ys, xs = torch.meshgrid(coords, coords, indexing="ij")
    return coords, torch.stack([xs.flatten(), ys.flatten()], dim=1)


class StateEnv(envs.TwoRoomsEnv):
    """The world as :class:`TrueDynamics` sees it: states ``[episode, x, y]`` (B, 3), no images."""

    @staticmethod
    def states(positions: torch.Tensor) -> torch.Tensor:
        rows = torch.arange(len(positions), device=positions.device, dtype=positions.dtype)
        return torch.cat([rows[:, None], positions], dim=1)

    def observe(self) -> torch.Tensor:
        return self.states(self.positions)

    def goal_images(self) -> torch.Tensor:
        return self.states(self.goals)


class TrueDynamics:
    """A world model that imagines with the TRUE motion (a diagnosis): states ``[episode, x, y]``
    move by ``transition`` in their episode's layout (``layouts (B, 2W)``); ``distance`` is that
    of ``model``'s latents at the nearest points of a 1-px grid (``model=None``: pixels)."""

    def __init__(self, layouts: torch.Tensor, model=None):
        self.config = SimpleNamespace(action_dim=2)
        self.layouts = layouts
        coords, grid = dot_grid(1.0, layouts.device)
        self.side = len(coords)
        if model is None:
            self.tables = grid.expand(len(layouts), -1, -1)
        else:
            self.tables = torch.stack([
                torch.cat([model.encode(envs.render(chunk, layout.expand(len(chunk), -1)))
                           for chunk in grid.split(1024)])
                for layout in layouts[:, None]])  # (B, G*G, D)

    def encode(self, states: torch.Tensor) -> torch.Tensor:
        return states

    def embed(self, states: torch.Tensor) -> torch.Tensor:
        """The table's latents at states ``(..., 3)`` -> ``(..., D)``."""
        ij = (states[..., 1:] - LOW).round().long().clamp(0, self.side - 1)  # the 1-px grid
        return self.tables[states[..., 0].long(), ij[..., 1] * self.side + ij[..., 0]]

    def distance(self, z: torch.Tensor, z_goal: torch.Tensor) -> torch.Tensor:
        return (self.embed(z) - self.embed(z_goal)).norm(dim=-1)

    def rollout(self, states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """States ``(R, 3)``, actions ``(R, H, 2)`` -> the states visited ``(R, H, 3)``."""
        visited = roll_out(states[:, 1:], actions, self.layouts[states[:, 0].long()])[:, 1:]
        return torch.cat([states[:, None, :1].expand(-1, visited.shape[1], -1), visited], dim=-1)


@torch.no_grad()
def energy_map(model, layout: torch.Tensor, goal: torch.Tensor, spacing: float = 1.0,
               distance=None):
    """``||Enc(o_x) - Enc(o_goal)||`` (or ``distance(z, z_goal)``, e.g. a cost-to-go head) at every
    dot position x of one layout ``(2W,)``, goal ``(2,)`` px: ``coords (G,), energy (G, G)`` on
    the CPU, ``energy[i, j]`` at ``(x=coords[j], y=coords[i])``, NaN inside the walls."""
    device = next(model.parameters()).device
    layout, goal = layout.cpu(), goal.cpu()
    coords, positions = dot_grid(spacing)
    layouts = layout.view(1, -1).expand(len(positions), -1)
    free = ~in_wall(positions, layouts)
    z_goal = model.encode(envs.render(goal.view(1, 2), layout.view(1, -1)).to(device))
    energy = torch.full((len(positions),), math.nan)
    for chunk in free.nonzero().squeeze(1).split(1024):
        z = model.encode(envs.render(positions[chunk], layouts[chunk]).to(device))
        energy[chunk] = ((z - z_goal).norm(dim=-1) if distance is None
                         else distance(z, z_goal)).cpu()
    return coords, energy.view(len(coords), len(coords))


@torch.no_grad()
def energy_by_distance(model, episodes: envs.Episodes, edges=(0, 5, 10, 15, 20, 30, 40, 60, 90),
                       spacing: float = 2.0) -> torch.Tensor:
    """The energy's mean in rings ``edges[i] <= distance < edges[i + 1]`` px from the goal,
    over the free dot positions of each episode's :func:`energy_map`: ``(len(edges) - 1,)``
    (NaN if empty). A useful energy keeps rising with distance."""
    edges = torch.as_tensor(edges, dtype=torch.float32)
    rings = len(edges) - 1
    sums, counts = torch.zeros(rings), torch.zeros(rings)
    positions = dot_grid(spacing)[1]  # the rows of every energy_map, flattened
    for layout, goal in zip(episodes.layouts.cpu(), episodes.goals.cpu()):
        energy = energy_map(model, layout, goal, spacing)[1].flatten()
        free = energy.isfinite()
        distance = (positions - goal).norm(dim=-1)
        ring = torch.bucketize(distance[free], edges, right=True) - 1
        keep = (ring >= 0) & (ring < rings)
        sums += torch.bincount(ring[keep], energy[free][keep], minlength=rings).float()
        counts += torch.bincount(ring[keep], minlength=rings).float()
    return sums / counts
