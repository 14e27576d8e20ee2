"""One entry for the notebooks: the model of a config, loaded if its run was saved, else trained."""

from __future__ import annotations

from .image import ImageJEPAConfig
from .image import train_or_load as train_image
from .video import VideoJEPAConfig
from .video import train_or_load as train_video
from .world import WorldTrainConfig
from .world import train_or_load as train_world


def train_or_load(config, name: str, data=None, device=None, **options):
    """``(model in eval mode, history)`` of the run ``config``, saved as ``name``.

    Loaded from ``checkpoints/<name>.pt`` (shipped) or ``data/cache/checkpoints/`` when this
    exact run was saved, else trained on ``data`` and saved: uint8 images ``(N, 3, 32, 32)``
    for an ``ImageJEPAConfig`` (``options``: ``encoder_only``, ``step``), the training digits
    ``(D, 1, 28, 28)`` for a ``VideoJEPAConfig``, nothing for a ``WorldTrainConfig`` (it makes
    its own). ``device``: where the model is trained and returned (default: the recipe's own).
    """
    if isinstance(config, ImageJEPAConfig):
        return train_image(config, name, data, device or "cpu", **options)
    if isinstance(config, VideoJEPAConfig):
        return train_video(config, name, data, device, **options)
    if not isinstance(config, WorldTrainConfig):
        raise TypeError(f"no recipe trains a {type(config).__name__}: pass an ImageJEPAConfig, "
                        "a VideoJEPAConfig or a WorldTrainConfig")
    if data is not None:
        raise ValueError("a world model makes its own data from its config; pass data=None")
    return train_world(config, name, device, **options)
