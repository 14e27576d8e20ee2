"""Environments: the Two Rooms world (``walls=2``: Three Rooms), its offline data, its episodes.

- ``two_rooms``: geometry, :func:`transition` (the one rule of motion), rendering
- ``trajectories``: the paper's random-walk data policy, generated in batches
- ``episodes``: evaluation tasks and :class:`TwoRoomsEnv`, the batch a planner acts in
"""

from .episodes import (
    EPISODE_STEPS,
    SUCCESS_RADIUS,
    THREE_ROOMS_EPISODE_STEPS,
    Episodes,
    TwoRoomsEnv,
    make_episodes,
    step_budget,
)
from .trajectories import Trajectories, generate_trajectories, sample_von_mises
from .two_rooms import (
    MAX_STEP,
    clip_actions,
    random_layouts,
    render,
    room_of,
    sample_positions,
    shortest_path_length,
    transition,
    wall_collision,
)

__all__ = [
    "EPISODE_STEPS", "MAX_STEP", "SUCCESS_RADIUS", "THREE_ROOMS_EPISODE_STEPS", "Episodes",
    "Trajectories", "TwoRoomsEnv", "clip_actions", "generate_trajectories", "make_episodes",
    "random_layouts", "render", "room_of", "sample_positions", "sample_von_mises",
    "shortest_path_length", "step_budget", "transition", "wall_collision",
]  # fmt: skip
