"""Energies and losses, one module per family.

- ``vicreg``: the invariance, variance and covariance terms (chapters 00-01),
  re-exported here, so ``losses.variance_term`` is the VICReg term
- ``sigreg``: SIGReg, the Epps-Pulley test on random 1-D projections (chapter 02)
- ``rollout``: the video JEPA's K-step rollout loss (chapter 03)
- ``world``: the world model's prediction, similarity and inverse-dynamics terms (chapter 05);
  ``training.world.world_model_step`` weighs them with the variance and covariance
"""

from . import rollout, sigreg, vicreg, world
from .vicreg import (
    covariance_matrix,
    covariance_term,
    invariance_term,
    variance_and_covariance,
    variance_term,
    vicreg_loss,
)

__all__ = [
    "covariance_matrix",
    "covariance_term",
    "invariance_term",
    "rollout",
    "sigreg",
    "variance_and_covariance",
    "variance_term",
    "vicreg",
    "vicreg_loss",
    "world",
]
