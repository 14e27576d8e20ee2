"""Training: the loop, checkpoints, optim, one recipe per chapter (``toy`` 00, ``image`` 01-02,
``world`` 05; ``video`` holds chapter 03's configs and step, its loop is in the notebook) and
:func:`train_or_load`, the notebooks' entry."""

from . import checkpoints, image, loop, optim, toy, video, world


def train_or_load(config, name: str, data=None, device=None, **options):
    """``(model in eval mode, history)`` of ``config``: loaded if saved as ``name``, else trained
    on ``data`` and saved. ``data``: uint8 images ``(N, 3, 32, 32)`` for an ``ImageJEPAConfig``,
    None for a world model."""
    if isinstance(config, world.WorldTrainConfig):
        return world.train_or_load(config, name, device, **options)
    return image.train_or_load(config, name, data, device or "cpu", **options)


__all__ = ["checkpoints", "image", "loop", "optim", "toy", "train_or_load", "video", "world"]
