"""Networks: encoders (images -> embeddings) and heads (embeddings -> projections)."""

from .encoders import ResNet18, ViT, build_encoder
from .heads import Projector, build_projector

__all__ = ["ResNet18", "ViT", "build_encoder", "Projector", "build_projector"]
