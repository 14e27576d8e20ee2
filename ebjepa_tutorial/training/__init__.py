"""Training: the loop, checkpoints, optim, one recipe per chapter (``toy`` 00, ``image`` 01-02;
``video`` 03 and ``world`` 05 hold their configs and steps, their loops are in the notebooks)
and :func:`train_or_load`, notebooks 01 and 02's entry."""

from . import checkpoints, image, loop, optim, toy, video, world
from .image import train_or_load

__all__ = ["checkpoints", "image", "loop", "optim", "toy", "train_or_load", "video", "world"]
