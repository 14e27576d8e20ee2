"""One entry for the notebooks: the model of a config, loaded if its run was saved, else trained.

:func:`train_or_load` picks the chapter's recipe from the type of the config,
so every notebook calls the same function with its own data.
"""

from __future__ import annotations

from functools import singledispatch

from .image import ImageJEPAConfig
from .image import train_or_load as train_image
from .video import VideoJEPAConfig
from .video import train_or_load as train_video
from .world import WorldTrainConfig
from .world import train_or_load as train_world


@singledispatch
def train_or_load(config, name: str, data=None, device=None, **options):
    """``(model in eval mode, history)`` of the run ``config``, saved as ``name``.

    Loaded from ``checkpoints/<name>.pt`` (shipped) or ``data/cache/checkpoints/``
    when this exact run was saved, else trained on ``data`` and saved; prints
    which, and how long it took. ``data``: uint8 images ``(N, 3, 32, 32)`` for
    an :class:`~ebjepa_tutorial.training.image.ImageJEPAConfig` (``options``:
    ``encoder_only``), the training digits ``(D, 1, 28, 28)`` for a
    :class:`~ebjepa_tutorial.training.video.VideoJEPAConfig`, nothing for a
    :class:`~ebjepa_tutorial.training.world.WorldTrainConfig` (it makes its own).
    ``device``: where the model is trained and returned, loaded or not (each recipe's
    default is its own; the world model's is the best available, cuda, mps, cpu).
    """
    raise TypeError(f"no recipe trains a {type(config).__name__}: pass an ImageJEPAConfig, "
                    "a VideoJEPAConfig or a WorldTrainConfig")


@train_or_load.register(ImageJEPAConfig)
def _image(config, name, data=None, device=None, encoder_only: bool = False, step=None):
    return train_image(config, name, data, device or "cpu", encoder_only, step)


@train_or_load.register(VideoJEPAConfig)
def _video(config, name, data=None, device=None):
    return train_video(config, name, data, device)


@train_or_load.register(WorldTrainConfig)
def _world(config, name, data=None, device=None):
    if data is not None:
        raise ValueError("a world model makes its own data from its config; pass data=None")
    return train_world(config, name, device)
