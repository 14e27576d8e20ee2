"""MPPI and CEM on a latent energy: one re-plan of notebook 06's agent. A plan of ``H``
imagined steps from ``z0 = Enc(o_t)`` costs (the paper's Eq. 13; cost="last" keeps its last
term, cost="learned" is ``model.cost_to_go(zhat_H, z_goal)``, notebook 07)

    S(a_1..a_H) = sum_{k=1..H} || zhat_k - z_goal ||       (cost="sum")

MPPI (the paper's Algorithm 1) moves the plan ``J`` times to the average of the ``Q``
cheapest of ``N`` samples weighted by ``exp(-(S_i - S_min) / tau)``; CEM weights them equally.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch

from ..envs import MAX_STEP, clip_actions
from ..utils import check_fields, is_int_at_least, is_non_negative, is_positive

METHODS = ("mppi", "cem")
COSTS = ("sum", "last", "learned")
MIN_STD = 0.05  # the smallest spread after an update, px: agreeing elites still explore


@dataclass(frozen=True)
class Noise:
    """How a re-plan samples around its mean: a spread of ``std`` px at first, a fresh draw
    every ``period`` steps joined by straight lines, each step clipped to ``bound`` px."""

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
    stop_px: float = 2.0  # stand still within this of the goal (mpc.arrival_distance); 0: never

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
                 for name in ("horizon", "samples", "elites", "iterations", "execute")}
        check_fields(self, {**rules, "temperature": (is_positive, "a finite number > 0")})
        if self.elites > self.samples or self.execute > self.horizon:
            raise ValueError(f"need elites <= samples and execute <= horizon, got elites "
                             f"(Q={self.elites}), samples (N={self.samples}), execute "
                             f"(m={self.execute}), horizon (H={self.horizon})")

    def warm(self) -> PlannerConfig:
        """This planner for the re-plans after an episode's first: warm_iterations (at most J)."""
        return replace(self, iterations=min(self.habits.warm_iterations or self.iterations,
                                            self.iterations))


def check_start_and_goal(z0, z_goal) -> None:
    """Raise unless ``z0`` and ``z_goal`` are both ``(B, D)``: a goal batch of 1 would
    broadcast silently towards the first goal."""
    if z0.ndim != 2 or z_goal.ndim != 2 or len(z_goal) != len(z0):
        hint = {1: "; a single latent needs its batch dimension: z_goal[None]",
                4: "; that looks like images: encode them first with model.encode"}
        hint = hint.get(min(z_goal.ndim, 4), "")
        if z_goal.ndim == 2 and len(z_goal) == 1:
            hint = f"; for one goal shared by all starts pass z_goal.expand({len(z0)}, -1)"
        raise ValueError(f"z0 and z_goal must be latents (B, D), one goal per start; got z0 "
                         f"{tuple(z0.shape)}, z_goal {tuple(z_goal.shape)}{hint}")


def goal_distance(model, z: torch.Tensor, z_goal: torch.Tensor) -> torch.Tensor:
    """The energy of single states, ``||z - z_goal||`` over the last dimension: ``(...)``
    (a model with a ``distance`` of its own, like ``TrueDynamics``, measures its way)."""
    if hasattr(model, "distance"):
        return model.distance(z, z_goal)
    return (z - z_goal).norm(dim=-1)


def planning_cost(model, z0: torch.Tensor, z_goal: torch.Tensor, actions: torch.Tensor,
                  cost: str = "sum") -> torch.Tensor:
    """Energy of each imagined plan: ``z0 (B, D), z_goal (B, D), actions (B, N, H, A) -> (B, N)``:
    the latent distance to the goal summed over the horizon (``"sum"``), at the last step
    (``"last"``), or ``model.cost_to_go(zhat_H (B, N, D), z_goal (B, 1, D))`` (``"learned"``)."""
    if cost not in COSTS or (cost == "learned" and not hasattr(model, "cost_to_go")):
        raise ValueError(f"cost must be one of {COSTS}, got {cost!r} ('learned' needs a model "
                         "with a cost_to_go(z, z_goal) method: notebook 07's WithLearnedCost)")
    check_start_and_goal(z0, z_goal)
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
    """``w_i = exp(-(S_i - S_min) / tau) / sum_j exp(-(S_j - S_min) / tau)``: ``(B, Q) -> (B, Q)``.

    ``S_min`` cancels in the ratio but keeps ``exp`` from underflowing to 0/0.
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


def smooth_noise(samples: int, horizon: int, dims: int, period: int,
                 generator: torch.Generator) -> torch.Tensor:
    """Standard normal noise ``(samples, horizon, dims)``: independent draws at steps ``0,
    period, 2 period, ...`` joined by straight lines (``period=1``: i.i.d.)."""
    knots = torch.randn(samples, dims, horizon // period + 2, generator=generator)
    if period == 1:
        return knots[..., :horizon].transpose(1, 2)
    line = torch.nn.functional.interpolate(knots, scale_factor=period, mode="linear",
                                           align_corners=True)[..., :horizon]
    return (line / line.std(dim=(0, 2), keepdim=True).clamp_min(1e-6)).transpose(1, 2)


# Notebook 06 shows this function in a code cell and runs its own copy (a test keeps the two equal).
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
    """What :func:`plan` returns: the mean plan ``(B, H, A)``, its spread, ``costs (B, J)``
    (the cheapest sample's per iteration) and, with ``record``, each iteration's samples
    ``(B, N, H, A)`` and costs ``(B, N)``."""

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
