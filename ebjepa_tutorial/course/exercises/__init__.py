"""Checkers for the notebooks' exercises: is the learner's function right?

Each ``check_*`` runs the learner's function and the package's reference
implementation on the same small inputs, prints a one-line verdict when they
agree, and otherwise raises :class:`ExerciseError` saying in plain words which
input went wrong and how. Each checker also knows its exercise's typical
mistakes (a wrong variant per mistake, see :func:`common.diagnose`): when the
learner's output matches one, the message names it and how to fix it. Where
the lesson depends on a gradient, the gradient is compared too. One module per
chapter's exercises.
"""

from .beyond import check_spread_loss, check_step_violation
from .common import Case, ExerciseError, compare
from .planning import check_mppi_update
from .sigreg import check_epps_pulley
from .two_rooms import check_wall_collision
from .vicreg import (
    check_covariance_term,
    check_variance_term,
    check_vicreg,
    check_vicreg_paper_to_ebjepa,
)
from .video import check_rollout_loss
from .world_model import check_inverse_dynamics, check_temporal_similarity

__all__ = [
    "Case",
    "ExerciseError",
    "check_covariance_term",
    "check_epps_pulley",
    "check_inverse_dynamics",
    "check_mppi_update",
    "check_rollout_loss",
    "check_spread_loss",
    "check_step_violation",
    "check_temporal_similarity",
    "check_variance_term",
    "check_vicreg",
    "check_vicreg_paper_to_ebjepa",
    "check_wall_collision",
    "compare",
]
