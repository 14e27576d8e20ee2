"""Goal-conditioned planning with a world model (notebooks 06 and 07): ``mppi`` (the energy, one
re-plan), ``mpc`` (the agent, the episode runner), ``diagnosis`` (pictures, true motion)."""

from .diagnosis import TrueDynamics, dot_grid, energy_by_distance, energy_map
from .mpc import EpisodeResults, arrival_distance, episode_generators, mpc_loop, run_episodes
from .mppi import (
    MIN_STD,
    Habits,
    Noise,
    PlannerConfig,
    cem_update,
    goal_distance,
    mppi_iteration,
    mppi_update,
    mppi_weights,
    plan,
    planning_cost,
    shift_plan,
    smooth_noise,
    weighted_mean_std,
)

__all__ = [
    "MIN_STD", "EpisodeResults", "Habits", "Noise", "PlannerConfig", "TrueDynamics",
    "arrival_distance", "cem_update", "dot_grid", "energy_by_distance", "energy_map",
    "episode_generators", "goal_distance", "mpc_loop", "mppi_iteration", "mppi_update",
    "mppi_weights", "plan", "planning_cost", "run_episodes", "shift_plan", "smooth_noise",
    "weighted_mean_std",
]
