"""Energies and losses, one module per family: ``vicreg`` (chapters 00-01, its terms re-exported
here), ``sigreg`` (02), ``rollout`` (the video JEPA's K-step loss, 03), ``world`` (05)."""

from . import rollout, sigreg, vicreg, world
from .vicreg import covariance_matrix, covariance_term, invariance_term, variance_term, vicreg_loss

__all__ = ["covariance_matrix", "covariance_term", "invariance_term", "rollout", "sigreg",
           "variance_term", "vicreg", "vicreg_loss", "world"]
