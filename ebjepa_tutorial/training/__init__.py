"""Training: the loop (``loop``: seeded batches, history, resumable runs), ``checkpoints``,
``optim``, one recipe per chapter (``toy`` 00, ``image`` 01-02, ``video`` 03, ``world`` 05;
``fits``: chapter 07's shipped fits) and :func:`train_or_load`, the notebooks' one entry."""

from . import checkpoints, fits, image, loop, optim, toy, video, world


def train_or_load(config, name: str, data=None, device=None, **options):
    """``(model in eval mode, history)`` of the run ``config``, loaded from
    ``checkpoints/<name>.pt`` (shipped) or ``data/cache/checkpoints/`` when this exact run was
    saved, else trained on ``data`` and saved: uint8 images ``(N, 3, 32, 32)`` for an
    ``ImageJEPAConfig``, the training digits ``(D, 1, 28, 28)`` for a ``VideoJEPAConfig``,
    nothing for a ``WorldTrainConfig``. ``options``: those of the recipe's ``train_or_load``."""
    if isinstance(config, world.WorldTrainConfig):
        return world.train_or_load(config, name, device, **options)
    if isinstance(config, video.VideoJEPAConfig):
        return video.train_or_load(config, name, data, device, **options)
    return image.train_or_load(config, name, data, device or "cpu", **options)


__all__ = ["checkpoints", "fits", "image", "loop", "optim", "toy", "train_or_load", "video",
           "world"]
