"""Goal-conditioned planning with a world model: MPPI and CEM on a latent energy (notebook 06).

The planner never sees positions. It encodes the current observation and
the goal image, imagines ``N`` action sequences of ``H`` steps with the
world model's predictor, and scores each with the planning energy (the
paper's Eq. 13): the distance in latent space between the imagined states
and the encoded goal,

    S(a_1..a_H) = sum_{k=1..H} || zhat_k - z_goal ||       (cost="sum", the paper's)
    S(a_1..a_H) =               || zhat_H - z_goal ||       (cost="last", its ablation)
    S(a_1..a_H) =               d(zhat_H, z_goal)           (cost="learned", notebook 07)

where ``d`` is a learned cost-to-go (``models.cost.WithLearnedCost``): "last"
with a distance that knows the walls.

MPPI (the paper's Algorithm 1) then keeps the ``Q`` cheapest sequences
(the elites), weights them by ``exp(-(S_i - S_min) / tau)``, moves the mean
plan (and the spread) to their weighted average, and repeats ``J`` times.
CEM is the same loop with equal weights. The agent executes the first ``m``
actions of the mean plan and re-plans from the new observation, starting
from the previous plan shifted by ``m`` steps (warm start).

Two choices differ from the paper's code: the sampling noise is drawn every
``noise_period`` steps and joined by straight lines (the paper: i.i.d. per
step), so a sampled plan can wander far enough to find the door; and each
sampled step is clipped on its length, as the world and the data clip it.

Everything is batched over episodes: ``B`` episodes x ``N`` samples are one
call to :meth:`~ebjepa_tutorial.models.world.WorldModel.rollout`. Each
episode has its own seed, which fixes its task and its planner's noise, and
nothing couples the episodes of a batch: each draws its noise from its own
generator, and its elites, weights, mean and spread come from its own
samples alone. What the batch does change is floating-point rounding: a
network's batched kernels (convolutions, matrix products) may sum in an
order that depends on the batch size, as on the number of torch threads, so
an episode's latents can differ in their last bits when it is encoded alone.
After a few re-plans such a difference can change which samples are the
elites and move the episode's path by pixels. So an episode is reproduced
exactly by rerunning its whole batch with the same thread count; played
alone or in another batch it is the same computation and agrees up to that
rounding. With dynamics evaluated exactly per row (:class:`TrueDynamics`)
an episode gives the same path alone and in any batch.

Notebook 07 adds a two-level planner (:class:`TwoLevel`) and fits its coarse
model again on that planner's own episodes (:func:`fit_coarse_with_visits`).
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from types import SimpleNamespace

import torch

from .envs import (
    MAX_STEP,
    SUCCESS_RADIUS,
    Episodes,
    Trajectories,
    TwoRoomsEnv,
    clip_actions,
    make_episodes,
)
from .envs.two_rooms import (
    HIGH,
    LOW,
    in_wall,
    random_layouts,
    render,
    sample_positions,
    transition,
    wall_collision,
)
from .evaluation.metrics import wilson_interval
from .losses.world import windows
from .models.hierarchy import CoarseModel
from .models.world import trajectory_latents
from .training.hierarchy import CoarseConfig, coarse_data, fit_coarse_on
from .training.loop import History
from .utils import check_fields, is_int_at_least, is_positive

METHODS = ("mppi", "cem")
COSTS = ("sum", "last", "learned")
WORLDS = ("learned", "true", "true_xy")  # what run_episodes imagines with


@dataclass(frozen=True)
class PlannerConfig:
    """One planner. The defaults are the class-scale MPPI of notebook 06."""

    method: str = "mppi"  # "mppi" (weighted elites) or "cem" (plain mean of elites)
    # "sum": distance summed over the horizon; "last": final step only; "learned": a learned
    # cost-to-go from the last step (needs models.cost.WithLearnedCost)
    cost: str = "sum"
    horizon: int = 64  # H, imagined steps per plan
    samples: int = 200  # N, action sequences per iteration
    elites: int = 20  # Q, the best of them that move the plan
    iterations: int = 6  # J, refinements per re-plan
    # refinements (at most J) of every re-plan after an episode's first, which starts from
    # the previous plan rather than from standing still; 0: J, as the paper's agent
    warm_iterations: int = 3
    temperature: float = 0.05  # tau, MPPI's softness (latent-distance units)
    # spread of the sampled actions at the start of a re-plan, px: wide enough that some
    # samples of a plan pressed against the wall slide along it to the door
    init_std: float = 2.0
    update_std: bool = True  # False: keep init_std for every iteration (move the mean only)
    min_std: float = 0.05
    max_std: float = 2.0
    execute: int = 4  # m, actions executed before re-planning
    # 1: i.i.d. noise per step (Algorithm 1); p > 1: smooth noise, a fresh draw every p steps.
    # White noise averages out over a plan and does not explore far enough around the wall.
    noise_period: int = 8
    action_bound: float = MAX_STEP  # sampled steps are clipped to the longest in the data, px
    # Arrived: while the current state is within stop_px of the goal as the model sees it
    # (arrival_distance), the agent stands still and plans nothing. 0: plan at every re-plan
    # until the step budget ends, as the paper's agent does.
    stop_px: float = 2.0

    def __post_init__(self):
        if self.method not in METHODS or self.cost not in COSTS:
            raise ValueError(f"method must be one of {METHODS} and cost one of {COSTS}, "
                             f"got method={self.method!r}, cost={self.cost!r}")
        check_fields(self, {name: (is_int_at_least(1), "an int >= 1") for name in
                            ("horizon", "samples", "elites", "iterations", "execute",
                             "noise_period")})
        if not is_int_at_least(0)(self.warm_iterations):
            raise ValueError(f"warm_iterations must be an int >= 0 (0: iterations), got "
                             f"{self.warm_iterations!r}")
        if self.elites > self.samples:
            raise ValueError(f"elites (Q={self.elites}) cannot exceed samples (N={self.samples})")
        if self.execute > self.horizon:
            raise ValueError(f"execute (m={self.execute}) cannot exceed horizon "
                             f"(H={self.horizon})")
        check_fields(self, {name: (is_positive, "a finite number > 0", meaning)
                            for name, meaning in _POSITIVE_FIELDS.items()})
        if self.min_std > self.max_std:
            raise ValueError(f"min_std ({self.min_std}) cannot exceed max_std ({self.max_std}): "
                             "they are the range the updated spread is clamped to")
        if not (math.isfinite(self.stop_px) and self.stop_px >= 0):
            raise ValueError(f"stop_px must be a finite number >= 0 (0: never stop), got "
                             f"{self.stop_px!r}")
        if not isinstance(self.update_std, bool):
            raise ValueError(f"update_std must be True or False, got {self.update_std!r}")

    def warm(self) -> PlannerConfig:
        """This planner for the re-plans after an episode's first: warm_iterations (at most J)."""
        return replace(self, iterations=min(self.warm_iterations or self.iterations,
                                            self.iterations))


# Each must be > 0: a zero spread samples N copies of the mean (and with
# update_std=False never explores), a zero bound clips every step to nothing
# (the agent never moves), a zero temperature divides by zero.
_POSITIVE_FIELDS = {
    "temperature": "MPPI's softness in latent-distance units",
    "init_std": "the spread of the first samples of a re-plan, px",
    "min_std": "the smallest spread after an update, px",
    "max_std": "the largest spread after an update, px",
    "action_bound": f"the longest sampled step, px (the world allows {MAX_STEP})",
}


@dataclass(frozen=True)
class TwoLevel:
    """A coarse model that picks subgoals for the flat planner (notebook 07).

    At every re-plan ``config`` (MPPI over macro-actions of ``coarse.stride``
    steps, warm-started like the flat plan) plans from the current latent to the
    goal; the latent it imagines ``lookahead`` coarse steps ahead is the subgoal
    that the flat planner then plans towards over its short horizon.

    The final approach: once the coarse plan comes within ``reach_px`` of the goal
    (as the model sees it, :func:`arrival_distance`) by its subgoal, the subgoal is
    the goal itself. Without it an agent at the goal keeps chasing the coarse model's
    imprecise latents, and can walk off the goal again.
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


# -- the energy ------------------------------------------------------------------------------
def check_start_and_goal(z0, z_goal) -> None:
    """Raise a clear error unless ``z0`` is ``(B, D)`` and ``z_goal`` is ``(B, D')``.

    One goal row per episode; ``D'`` may differ from ``D`` (:class:`TrueDynamics`
    starts from positions and compares latents). A goal batch of 1 for ``B > 1``
    starts would broadcast silently, every episode planning towards the first
    goal, so it is refused too.
    """
    for name, z in (("z0", z0), ("z_goal", z_goal)):
        if not isinstance(z, torch.Tensor):
            raise TypeError(f"{name} must be a tensor of latents (B, D), got {type(z).__name__}")
    if z0.ndim != 2:
        raise ValueError(f"z0 must be start latents of shape (B, D), got {tuple(z0.shape)}")
    if z_goal.ndim != 2 or len(z_goal) != len(z0):
        raise ValueError(f"z_goal must be goal latents of shape ({len(z0)}, D), one per start "
                         f"in z0 {tuple(z0.shape)}; got {tuple(z_goal.shape)}"
                         f"{_goal_hint(len(z0), z_goal)}")


def _goal_hint(batch: int, z_goal: torch.Tensor) -> str:
    """What a wrongly shaped goal most likely is, and what to pass instead."""
    if z_goal.ndim in (4, 5):
        return "; that looks like images: encode them first with model.encode"
    if z_goal.ndim == 1:
        return "; a single latent needs its batch dimension: z_goal[None]"
    if z_goal.ndim == 2 and len(z_goal) == 1:
        return f"; for one goal shared by all episodes pass z_goal.expand({batch}, -1)"
    return ""


def planning_cost(model, z0: torch.Tensor, z_goal: torch.Tensor, actions: torch.Tensor,
                  cost: str = "sum") -> torch.Tensor:
    """Energy of each imagined plan: ``z0 (B, D), z_goal (B, D), actions (B, N, H, A) -> (B, N)``.

    ``model.rollout`` imagines the ``H`` latents of each of the ``B x N`` plans in
    one batch; the cost is the Euclidean latent distance to the goal, summed over
    the horizon (``"sum"``) or at the last step (``"last"``); or (``"learned"``)
    ``model.cost_to_go`` from the last latent. The px the plan spends are not added:
    a move straight at the goal lowers the head by about what it spends, so their
    sum would rank plans by the head's errors.
    """
    if cost not in COSTS:
        raise ValueError(f"cost must be one of {COSTS}, got {cost!r}")
    if cost == "learned" and not hasattr(model, "cost_to_go"):
        raise ValueError("cost='learned' needs a model with a cost-to-go head: "
                         "models.cost.WithLearnedCost(world_model, head)")
    check_start_and_goal(z0, z_goal)
    if actions.ndim != 4 or len(actions) != len(z0):
        raise ValueError(f"actions must be plans of shape ({len(z0)}, N, H, A), one batch of N "
                         f"per start in z0 {tuple(z0.shape)}; got {tuple(actions.shape)}")
    b, n, h, _ = actions.shape
    z = model.rollout(z0.repeat_interleave(n, dim=0), actions.flatten(0, 1)).view(b, n, h, -1)
    if z_goal.shape[1] != z.shape[-1]:
        raise ValueError(f"z_goal has latents of size {z_goal.shape[1]} but the model imagines "
                         f"latents of size {z.shape[-1]}: z_goal {tuple(z_goal.shape)}, z0 "
                         f"{tuple(z0.shape)}; encode the goal with the planning model")
    if cost == "learned":
        return model.cost_to_go(z[:, :, -1], z_goal[:, None])
    distance = (z - z_goal[:, None, None]).norm(dim=-1)  # (B, N, H)
    return distance.sum(dim=-1) if cost == "sum" else distance[..., -1]


# -- one update of the plan: MPPI and CEM ----------------------------------------------------
def _check_update_args(actions: torch.Tensor, costs: torch.Tensor, elites: int) -> None:
    if actions.ndim != 4 or costs.shape != actions.shape[:2]:
        raise ValueError(f"need actions (B, N, H, A) and costs (B, N), got "
                         f"{tuple(actions.shape)} and {tuple(costs.shape)}")
    if not 1 <= elites <= actions.shape[1]:
        raise ValueError(f"elites must be in 1..N={actions.shape[1]}, got {elites}")


def select_elites(actions: torch.Tensor, costs: torch.Tensor, elites: int):
    """The ``Q`` cheapest plans of each episode, cheapest first: ``(B, Q, H, A), (B, Q)``."""
    _check_update_args(actions, costs, elites)
    elite_costs, index = costs.topk(elites, dim=1, largest=False)
    elite_actions = actions.gather(1, index[:, :, None, None].expand(-1, -1, *actions.shape[2:]))
    return elite_actions, elite_costs


def mppi_weights(elite_costs: torch.Tensor, temperature: float) -> torch.Tensor:
    """``w_i = exp(-(S_i - S_min) / tau) / sum_j exp(-(S_j - S_min) / tau)``: ``(B, Q) -> (B, Q)``.

    Subtracting ``S_min`` changes nothing mathematically (it cancels in the
    ratio) but keeps ``exp`` from underflowing to 0/0 when costs are large.
    """
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


# -- a whole re-plan -------------------------------------------------------------------------
def smooth_noise(samples: int, horizon: int, dims: int, period: int,
                 generator: torch.Generator) -> torch.Tensor:
    """Standard normal noise ``(samples, horizon, dims)``, correlated over ``period`` steps.

    Independent draws at steps ``0, period, 2 period, ...`` joined by straight
    lines (``period=1``: i.i.d. per step). Smooth perturbations move a plan
    coherently, so a few iterations explore much farther than white noise,
    whose displacement grows only as the square root of the horizon.
    """
    knots = torch.randn(samples, dims, horizon // period + 2, generator=generator)
    if period == 1:
        return knots[..., :horizon].transpose(1, 2)
    line = torch.nn.functional.interpolate(knots, scale_factor=period, mode="linear",
                                           align_corners=True)[..., :horizon]
    return (line / line.std(dim=(0, 2), keepdim=True).clamp_min(1e-6)).transpose(1, 2)


def sample_plans(mean: torch.Tensor, std: torch.Tensor, samples: int,
                 generators: Sequence[torch.Generator], bound: float,
                 period: int = 1) -> torch.Tensor:
    """``N`` plans around each mean ``(B, H, A)`` -> ``(B, N, H, A)``, steps at most ``bound`` long.

    Steps are clipped on their length, as the environment clips them
    (:func:`~ebjepa_tutorial.envs.clip_actions`): the data held steps of up to
    ``bound`` px in any direction, so a box would show the model diagonal steps
    of up to 1.41 x ``bound`` that it never saw and that the world shortens.
    Episode ``b`` draws its noise from ``generators[b]`` alone, so its noise
    does not depend on which other episodes share the batch. Sample 0 is the mean
    itself, so a good plan is never lost to unlucky noise.
    """
    _, h, a = mean.shape
    noise = torch.stack([smooth_noise(samples, h, a, period, g) for g in generators])
    noise[:, 0] = 0
    return clip_actions(mean[:, None] + std[:, None] * noise.to(mean.device), bound)


@dataclass
class Plan:
    """The result of :func:`plan`: the mean plan ``(B, H, A)``, its spread, the cost history.

    ``costs``: ``(B, J)``, the cost of the cheapest sampled plan at each
    iteration. ``history`` (when recorded): per iteration, the sampled plans
    ``(B, N, H, A)`` and their costs ``(B, N)``, for pictures.
    """

    mean: torch.Tensor
    std: torch.Tensor
    costs: torch.Tensor
    history: list[tuple[torch.Tensor, torch.Tensor]] | None = None


@torch.no_grad()
def plan(model, z0: torch.Tensor, z_goal: torch.Tensor, config: PlannerConfig,
         generators: Sequence[torch.Generator], mean: torch.Tensor | None = None,
         record: bool = False) -> Plan:
    """Run ``J`` MPPI or CEM iterations from latents ``z0`` to goals ``z_goal`` (both ``(B, D)``).

    ``mean``: a warm start ``(B, H, A)`` (default zeros: stand still).
    """
    check_start_and_goal(z0, z_goal)
    b, h = z0.shape[0], config.horizon
    if mean is None:
        mean = z0.new_zeros(b, h, model.config.action_dim)
    if mean.shape != (b, h, model.config.action_dim) or len(generators) != b:
        raise ValueError(f"need a mean plan ({b}, {h}, {model.config.action_dim}) and {b} "
                         f"generators, got {tuple(mean.shape)} and {len(generators)}")
    std = torch.full_like(mean, config.init_std)
    best, history = [], [] if record else None
    for _ in range(config.iterations):
        actions = sample_plans(mean, std, config.samples, generators, config.action_bound,
                               config.noise_period)
        costs = planning_cost(model, z0, z_goal, actions, config.cost)
        if config.method == "mppi":
            mean, new_std = mppi_update(actions, costs, config.elites, config.temperature)
        else:
            mean, new_std = cem_update(actions, costs, config.elites)
        if config.update_std:
            std = new_std.clamp(config.min_std, config.max_std)
        best.append(costs.min(dim=1).values)
        if record:
            history.append((actions.cpu(), costs.cpu()))
    return Plan(mean, std, torch.stack(best, dim=1), history)


def shift_plan(mean: torch.Tensor, executed: int) -> torch.Tensor:
    """The warm start for the next re-plan: drop the executed actions, pad with zeros."""
    return torch.cat([mean[:, executed:], torch.zeros_like(mean[:, :executed])], dim=1)


# -- episodes --------------------------------------------------------------------------------
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
        def cat(name):
            return torch.cat([getattr(p, name) for p in parts])

        episodes = Episodes.concat([p.episodes for p in parts])
        return cls([s for p in parts for s in p.seeds], episodes, cat("paths"), cat("actions"),
                   cat("success"), cat("first_arrival"), sum(p.cpu_seconds for p in parts),
                   sum(p.wall_seconds for p in parts))

    def first(self, n: int) -> EpisodeResults:
        """The first ``n`` episodes (times: this batch's, pro rata)."""
        share = n / len(self.seeds)
        return EpisodeResults(self.seeds[:n], self.episodes[:n], self.paths[:n],
                              self.actions[:n], self.success[:n], self.first_arrival[:n],
                              self.cpu_seconds * share, self.wall_seconds * share)

    def as_trajectories(self) -> Trajectories:
        """The episodes as offline data: what the agent saw and did, as
        :func:`~ebjepa_tutorial.envs.generate_trajectories` stores a random walk."""
        return Trajectories(self.paths, self.actions, self.episodes.layouts,
                            torch.zeros(len(self.seeds), dtype=torch.bool))

    @property
    def success_rate(self) -> float:
        return self.success.float().mean().item()

    def interval(self, z: float = 1.96) -> tuple[float, float]:
        """The Wilson 95% interval of the success rate."""
        return wilson_interval(int(self.success.sum()), len(self.seeds), z)

    def mean_first_arrival(self) -> float:
        """Mean first-arrival step over the episodes that arrived (nan if none did)."""
        arrived = self.first_arrival[self.first_arrival >= 0]
        return arrived.float().mean().item() if len(arrived) else math.nan

    @property
    def cpu_seconds_per_episode(self) -> float:
        return self.cpu_seconds / len(self.seeds)

    def summary(self) -> str:
        low, high = self.interval()
        arrival = self.mean_first_arrival()
        arrived = ("no episode reached the goal" if arrival != arrival  # NaN: none arrived
                   else f"mean first arrival {arrival:.0f} steps")
        return (f"success {self.success_rate:.0%} (95% CI {low:.0%}-{high:.0%}) over "
                f"{len(self.seeds)} episodes, {arrived}, "
                f"{self.cpu_seconds_per_episode:.2f} s CPU per episode")


def episode_generators(seeds: Sequence[int],
                       walls: int = 1) -> tuple[Episodes, list[torch.Generator]]:
    """The task of each seed and the generator its planner continues with.

    ``walls``: 1 for Two Rooms, 2 for Three Rooms (layouts ``(B, 2 * walls)``,
    start and goal in the outer rooms; see :func:`~ebjepa_tutorial.envs.make_episodes`).
    """
    if len(seeds) < 1:
        raise ValueError("need at least one episode seed")
    generators = [torch.Generator().manual_seed(int(seed)) for seed in seeds]
    return Episodes.concat([make_episodes(1, g, walls) for g in generators]), generators


@torch.no_grad()
def arrival_distance(model, px: float, n: int = 512, seed: int = 0, walls: int = 1) -> float:
    """The latent distance that means "within ``px`` of the goal" to ``model``.

    The median of ``||Enc(o') - Enc(o)||`` over ``n`` random frames ``o`` (fresh
    layouts of ``walls`` walls, dots anywhere on the floor) and ``o'``, the same
    frame with the dot moved ``px`` in a random direction (a wall may cut the
    move short). Rendering positions here calibrates the model once, on frames
    of the world it plans in; an agent that stops below this distance still
    decides from its observation and the goal image alone.
    """
    generator = torch.Generator().manual_seed(seed)
    layouts = random_layouts(n, generator, walls)
    here = sample_positions(layouts, generator)
    angle = 2 * math.pi * torch.rand(n, generator=generator)
    there = wall_collision(here, px * torch.stack([angle.cos(), angle.sin()], dim=-1), layouts)
    device = next(model.parameters()).device
    z_here, z_there = (model.encode(render(p, layouts).to(device)) for p in (here, there))
    return (z_there - z_here).norm(dim=-1).median().item()


@torch.no_grad()
def run_episodes(model, seeds: Sequence[int], config: PlannerConfig = PlannerConfig(),
                 steps: int | None = None, radius: float = SUCCESS_RADIUS,
                 batch: int | None = None, world: str = "learned",
                 walls: int = 1, two_level: TwoLevel | None = None) -> EpisodeResults:
    """Plan and act in one episode per seed; the agent re-plans every ``m`` steps.

    Episode ``seed`` draws its layout, start and goal (the two outer rooms) and
    then its planner's noise from ``torch.Generator().manual_seed(seed)``.
    ``walls``: 1 for Two Rooms, 2 for Three Rooms. ``steps``: the episode's
    length; None gives the world's step budget (200 steps with one wall, 120
    with two: :func:`~ebjepa_tutorial.envs.step_budget`). ``batch``
    episodes run at once (default: all of them); the same batches and thread
    count reproduce the paths exactly (other batches: see the module docstring
    on rounding). ``world`` says what the planner imagines with:
    ``"learned"``, the world model (the real task); ``"true"`` and
    ``"true_xy"``, the diagnoses of :class:`TrueDynamics`. With ``config.stop_px``
    the model's :func:`arrival_distance` is calibrated once, its CPU time counted.
    ``two_level``: plan towards its subgoals instead of the goal (a learned world only;
    it re-plans once per coarse step, so ``config.execute`` must be its stride; its final
    approach is calibrated as ``stop_px`` is).
    """
    if world not in WORLDS:
        raise ValueError(f"world must be one of {WORLDS}, got {world!r}")
    if two_level is not None and (world != "learned"
                                  or config.execute != two_level.coarse.stride):
        raise ValueError(f"a two-level planner needs world='learned' and execute equal to its "
                         f"stride ({two_level.coarse.stride}); got world={world!r}, "
                         f"execute={config.execute}")
    seeds = list(seeds)
    batch = batch or len(seeds)
    model.eval()
    cpu, wall = time.process_time(), time.perf_counter()
    arrived = None  # the energy below which the agent stands still: pixels for "true_xy"
    if config.stop_px:
        arrived = (config.stop_px if world == "true_xy"
                   else arrival_distance(model, config.stop_px, walls=walls))
    if two_level is not None:
        two_level = two_level.calibrate(model, walls)
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    result = EpisodeResults.concat([
        _run_batch(model, seeds[i:i + batch], config, steps, radius, world, arrived, walls,
                   two_level)
        for i in range(0, len(seeds), batch)])
    return replace(result, cpu_seconds=result.cpu_seconds + cpu,
                   wall_seconds=result.wall_seconds + wall)


def _run_batch(model, seeds: list[int], config: PlannerConfig, steps: int | None,
               radius: float, world: str, arrived: float | None, walls: int,
               two_level: TwoLevel | None = None) -> EpisodeResults:
    """:func:`run_episodes` for one batch, all at once; ``arrived``: the stopping distance."""
    episodes, generators = episode_generators(seeds, walls)
    env = TwoRoomsEnv(next(model.parameters()).device)
    cpu, wall = time.process_time(), time.perf_counter()
    observation = env.reset(episodes=episodes)
    steps = env.step_budget if steps is None else steps
    agent = _Agent(model, env, world, config, generators, arrived, two_level)
    paths, first = [env.positions.cpu()], torch.full((len(seeds),), -1, dtype=torch.long)
    actions = []
    while env.steps_taken < steps:
        for action in agent.act(observation)[:, : steps - env.steps_taken].unbind(1):
            observation = env.step(action)
            paths.append(env.positions.cpu())
            actions.append(action.cpu())
            first[(first < 0) & env.success(radius).cpu()] = env.steps_taken
    return EpisodeResults(seeds, episodes, torch.stack(paths, dim=1), torch.stack(actions, dim=1),
                          env.success(radius).cpu(), first,
                          time.process_time() - cpu, time.perf_counter() - wall)


class _Agent:
    """The planning agent of one batch of episodes in ``env``.

    Every ``config.execute`` steps it re-plans the episodes still under way, each
    plan warm-started from the previous one shifted by the steps executed; the
    first plan of an episode starts cold, with all ``J`` iterations. A two-level
    agent carries its coarse plan the same way, shifted by one coarse step.
    """

    def __init__(self, model, env: TwoRoomsEnv, world: str, config: PlannerConfig,
                 generators: Sequence[torch.Generator], arrived: float | None,
                 two_level: TwoLevel | None):
        if world == "learned":
            self.imagine, self.z_goal = model, model.encode(env.goal_images())
        else:
            self.imagine = TrueDynamics(env.layouts, model if world == "true" else None)
            self.z_goal = self.imagine.embed(env.goals)
        self.model, self.learned = model, world == "learned"  # else a TrueDynamics diagnosis
        self.env, self.generators, self.arrived = env, generators, arrived
        self.config, self.two_level = config, two_level
        self.mean = self.z_goal.new_zeros(len(generators), config.horizon,
                                          model.config.action_dim)  # (B, H, A)
        if two_level is not None:
            self.high = two_level.config
            self.coarse = self.z_goal.new_zeros(len(generators), self.high.horizon, 2)

    def act(self, observation: torch.Tensor) -> torch.Tensor:
        """Re-plan from ``observation``; the next ``execute`` actions ``(B, m, A)``."""
        start = self.model.encode(observation) if self.learned else self.env.positions
        moving = self._under_way(start)
        if len(moving):
            self._replan(start, moving)
        actions, self.mean = self.mean, shift_plan(self.mean, self.config.execute)
        self.config = self.config.warm()
        if self.two_level is not None:
            self.high, self.coarse = self.high.warm(), shift_plan(self.coarse, 1)
        return actions[:, : self.config.execute]

    def _under_way(self, start: torch.Tensor) -> torch.Tensor:
        """Indices of the episodes to plan; the arrived ones stand still (zero actions)."""
        everyone = torch.arange(len(start), device=self.mean.device)
        if self.arrived is None:
            return everyone
        here = start if self.learned else self.imagine.embed(start)
        under_way = (here - self.z_goal).norm(dim=-1) >= self.arrived  # (B,)
        self.mean = torch.where(under_way[:, None, None], self.mean, 0.0)
        return everyone[under_way]

    def _replan(self, start: torch.Tensor, moving: torch.Tensor) -> None:
        """New plans (and subgoals, for two levels) for the episodes ``moving``."""
        imagine = self.imagine if self.learned else self.imagine.rows(moving)
        mine = [self.generators[i] for i in moving.tolist()]
        target = self.z_goal[moving]
        if self.two_level is not None:
            target, self.coarse[moving] = self.two_level.subgoals(
                start[moving], target, self.high, mine, self.coarse[moving])
        self.mean[moving] = plan(imagine, start[moving], target, self.config, mine,
                                 self.mean[moving]).mean


def dot_grid(spacing: float = 1.0, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Dot positions every ``spacing`` px over the arena: ``coords (G,)``, ``xy (G*G, 2)``.

    Row ``i * G + j`` of ``xy`` is ``(x=coords[j], y=coords[i])``: image order.
    """
    coords = torch.arange(LOW, HIGH + 1e-6, spacing, device=device)
    ys, xs = torch.meshgrid(coords, coords, indexing="ij")
    return coords, torch.stack([xs.flatten(), ys.flatten()], dim=1)


# -- diagnosis: is it the predictor or the energy that fails? ------------------------------
class TrueDynamics:
    """A stand-in world model that imagines with the TRUE motion of its world (a diagnosis).

    Its "latent" of a plan is found without the predictor: the dot moves by
    :func:`~ebjepa_tutorial.envs.two_rooms.transition` in its episode's layout
    and each visited position is looked up in a table of ``model``'s
    encodings of the dot at every point of a grid (``spacing`` px, nearest
    point). ``model=None`` scores positions directly: the energy is then the
    Euclidean distance in pixels, the best a distance can do without knowing
    about walls. ``layouts``: ``(B, 2W)``, one per episode (any number W of
    walls: Two Rooms, Three Rooms); rows of a rollout batch belong to the
    episodes in order, ``N`` each (as :func:`planning_cost` repeats them).
    """

    def __init__(self, layouts: torch.Tensor, model=None, spacing: float = 1.0):
        self.config = SimpleNamespace(action_dim=2)
        self.layouts, self.spacing = layouts, spacing
        coords, grid = dot_grid(spacing, layouts.device)
        self.side = len(coords)
        if model is None:
            self.tables = grid.expand(len(layouts), -1, -1)
        else:
            self.tables = torch.stack([
                torch.cat([model.encode(render(chunk, layout.expand(len(chunk), -1)))
                           for chunk in grid.split(1024)])
                for layout in layouts[:, None]])  # (B, G*G, D)

    def rows(self, index: torch.Tensor) -> TrueDynamics:
        """The same stand-in for the episodes ``index`` alone (the ones still planning)."""
        part = copy.copy(self)
        part.layouts, part.tables = self.layouts[index], self.tables[index]
        return part

    def embed(self, positions: torch.Tensor, episode: torch.Tensor | None = None):
        """The table's latents at ``positions`` ``(R, 2)`` of episodes ``episode`` ``(R,)``."""
        if episode is None:
            episode = torch.arange(len(positions), device=positions.device)
        ij = ((positions - LOW) / self.spacing).round().long().clamp(0, self.side - 1)
        return self.tables[episode, ij[:, 1] * self.side + ij[:, 0]]

    def rollout(self, positions: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """Positions ``(B*N, 2)``, actions ``(B*N, H, 2)`` -> looked-up latents ``(B*N, H, D)``."""
        rows = torch.arange(len(positions), device=positions.device)
        episode = rows // (len(positions) // len(self.layouts))
        layouts, out = self.layouts[episode], []
        for action in actions.unbind(1):
            positions = transition(positions, action, layouts)
            out.append(self.embed(positions, episode))
        return torch.stack(out, dim=1)


# -- pictures --------------------------------------------------------------------------------
def latent_distance(z: torch.Tensor, z_goal: torch.Tensor) -> torch.Tensor:
    """``||z - z_goal||`` over the last dimension: chapter 06's energy of one state."""
    return (z - z_goal).norm(dim=-1)


@torch.no_grad()
def energy_map(model, layout: torch.Tensor, goal: torch.Tensor, spacing: float = 1.0,
               distance=latent_distance):
    """The planner's view of one layout: ``distance(Enc(o_x), Enc(o_goal))`` for every dot
    position x (default: the latent distance; notebook 07 passes a cost-to-go head).

    ``layout``: ``(2W,)`` long, W walls (``(2,)`` for Two Rooms); ``goal``: ``(2,)``
    px. Returns ``(coords (G,), energy (G, G))`` with ``energy[i, j]`` at
    ``(x=coords[j], y=coords[i])`` (image orientation), NaN where the dot cannot
    be (inside any wall). Frames are rendered on the CPU and encoded on the
    model's device; the map is on the CPU.
    """
    device = next(model.parameters()).device
    layout, goal = layout.cpu(), goal.cpu()
    coords, positions = dot_grid(spacing)
    layouts = layout.view(1, -1).expand(len(positions), -1)
    free = ~in_wall(positions, layouts)
    z_goal = model.encode(render(goal.view(1, 2), layout.view(1, -1)).to(device))
    energy = torch.full((len(positions),), math.nan)
    for chunk in free.nonzero().squeeze(1).split(1024):
        z = model.encode(render(positions[chunk], layouts[chunk]).to(device))
        energy[chunk] = distance(z, z_goal).cpu()
    return coords, energy.view(len(coords), len(coords))


@torch.no_grad()
def energy_by_distance(model, episodes: Episodes, edges=(0, 5, 10, 15, 20, 30, 40, 60, 90),
                       spacing: float = 2.0) -> torch.Tensor:
    """The energy's shape: its mean in rings of pixel distance from the goal, ``(len(edges)-1,)``.

    Each episode's layout and goal give an :func:`energy_map`; every free dot
    position falls in ring ``i`` when ``edges[i] <= distance < edges[i + 1]``,
    and each ring is averaged over all positions of all episodes (NaN if empty).
    A useful energy keeps rising with distance; a flat tail means the planner
    is blind out there.
    """
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


# -- a coarse model that learns from its own planner (notebook 07) --------------------------
@dataclass(frozen=True)
class CoarseFit:
    """The coarse model's fit on ``coarse``'s random walks, then again with the episodes of
    the two-level planner built on the first fit added (DAgger, Ross et al., 2011).

    A planner seeks out what its model gets wrong, a long macro-action into a wall beside
    a door, and random walks rarely go there; the planner's own episodes show the model
    what really happens where it is asked. The planner: ``low`` and a :class:`TwoLevel` of
    ``high``, ``lookahead`` and ``reach_px``. It plays ``episodes`` episodes of ``steps``
    steps (seeds from ``first_seed``, a range no evaluation uses), cut into windows as long
    as the walks, one starting every ``every`` steps.
    """

    coarse: CoarseConfig
    low: PlannerConfig
    high: PlannerConfig
    lookahead: int
    reach_px: float
    episodes: int = 300
    steps: int = 200
    every: int = 8
    first_seed: int = 40_000
    batch: int = 10  # episodes played at once

    def __post_init__(self):
        check_fields(self, {name: (is_int_at_least(1), "an int >= 1") for name in
                            ("lookahead", "episodes", "steps", "every", "batch")})


def fit_coarse_with_visits(model, config: CoarseFit,
                           progress: bool = True) -> tuple[CoarseModel, History]:
    """A coarse model fitted on ``model``'s frozen latents of random walks and of its own
    planner's episodes: ``(coarse, history of the second fit)``."""
    latents, actions = coarse_data(model, config.coarse)
    first, _ = fit_coarse_on(latents, actions, config.coarse, progress)
    z, a = planner_windows(model, first, config, actions.shape[1])
    return fit_coarse_on(torch.cat([latents, z]), torch.cat([actions, a]), config.coarse,
                         progress)


def planner_windows(model, coarse: CoarseModel, config: CoarseFit,
                    length: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The episodes of the two-level planner on ``coarse``, cut into windows of ``length``
    actions: ``(latents (W, length + 1, D), actions (W, length, 2))``."""
    seeds = range(config.first_seed, config.first_seed + config.episodes)
    coarse = copy.deepcopy(coarse).to(next(model.parameters()).device)  # plans beside model
    two_level = TwoLevel(coarse, config.high, config.lookahead, config.reach_px)
    played = run_episodes(model, seeds, config.low, config.steps, batch=config.batch,
                          walls=config.coarse.walls, two_level=two_level).as_trajectories()
    latents = trajectory_latents(model, played)  # (E, steps + 1, D)
    return (windows(latents, length + 1, config.every),
            windows(played.actions, length, config.every))
