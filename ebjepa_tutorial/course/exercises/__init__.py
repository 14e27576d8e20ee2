"""Checkers for the notebooks' exercises: is the learner's function right?

Each ``check_*`` runs the learner's function and the course's implementation on
the same small inputs, prints a one-line verdict when they agree, and otherwise
raises :class:`ExerciseError` saying in plain words which input went wrong and
how: one of the exercise's typical mistakes (a wrong variant per mistake, see
:func:`common.diagnose`) or a general one (a sign flip, a factor off, an input
changed in place, a gradient that does not flow, the wrong axis, a transposed
result, a float or a tuple where a tensor belongs). Where the output trains
something, the gradients are compared too. A failed check offers the next hint;
``hint("name")`` asks for one: the idea, then the formula, then an outline of the
code. One module per chapter's exercises, each exercise's hints beside its checker.
"""

from .beyond import check_spread_loss, check_step_violation
from .common import Case, ExerciseError, compare, hint, whose
from .planning import check_mppi_update
from .sigreg import check_epps_pulley
from .two_rooms import check_slab_crossing, check_wall_collision
from .vicreg import (
    check_covariance_term,
    check_variance_term,
    check_vicreg,
    check_vicreg_paper_to_ebjepa,
)
from .video import check_parallel_rollout_loss
from .world_model import check_inverse_dynamics, check_temporal_similarity

__all__ = [
    "Case",
    "ExerciseError",
    "check_covariance_term",
    "check_epps_pulley",
    "check_inverse_dynamics",
    "check_mppi_update",
    "check_parallel_rollout_loss",
    "check_slab_crossing",
    "check_spread_loss",
    "check_step_violation",
    "check_temporal_similarity",
    "check_variance_term",
    "check_vicreg",
    "check_vicreg_paper_to_ebjepa",
    "check_wall_collision",
    "compare",
    "hint",
    "whose",
]
