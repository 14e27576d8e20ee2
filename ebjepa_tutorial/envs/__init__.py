"""Environments: the Two Rooms world and its geometry (``two_rooms``), its offline data
(``trajectories``), its evaluation episodes and batched environment (``episodes``)."""

from .episodes import SUCCESS_RADIUS, Episodes, TwoRoomsEnv, make_episodes, step_budget
from .trajectories import Trajectories, generate_trajectories
from .two_rooms import (
    MAX_STEP,
    clip_actions,
    random_layouts,
    render,
    room_of,
    sample_positions,
    shortest_path_length,
    transition,
)

__all__ = [
    "MAX_STEP", "SUCCESS_RADIUS", "Episodes", "Trajectories", "TwoRoomsEnv", "clip_actions",
    "generate_trajectories", "make_episodes", "random_layouts", "render", "room_of",
    "sample_positions", "shortest_path_length", "step_budget", "transition",
]  # fmt: skip
