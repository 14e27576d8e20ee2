"""The notebooks' exercise checkers, one module per part of the course; their words are in
hints.yaml (each exercise's hints and typical mistakes) and general.yaml (any exercise's)."""

from .beyond import check_spread_loss, check_step_violation
from .collapse import (
    check_covariance_term,
    check_epps_pulley,
    check_variance_term,
    check_vicreg,
    check_vicreg_paper_to_ebjepa,
)
from .common import ExerciseError, checked, hint, whose
from .two_rooms import check_slab_crossing, check_wall_collision
from .video import check_parallel_rollout_loss
from .world_and_planning import (
    check_inverse_dynamics,
    check_mppi_update,
    check_temporal_similarity,
)

__all__ = [
    "ExerciseError", "checked", "hint", "whose", "check_variance_term", "check_covariance_term",
    "check_vicreg", "check_vicreg_paper_to_ebjepa", "check_epps_pulley",
    "check_parallel_rollout_loss", "check_slab_crossing", "check_wall_collision",
    "check_temporal_similarity", "check_inverse_dynamics", "check_mppi_update",
    "check_step_violation", "check_spread_loss",
]
