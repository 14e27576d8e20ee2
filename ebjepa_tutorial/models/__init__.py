"""Networks: encoders (images -> embeddings) and heads (embeddings -> projections)."""

from .encoders import ResNet18
from .heads import Projector, build_projector

__all__ = ["ResNet18", "Projector", "build_projector"]
