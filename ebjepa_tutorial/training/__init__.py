"""Training: the loop (``loop``: seeded batches, history, resumable runs), ``checkpoints``,
``optim``, one recipe per chapter (``toy`` 00, ``image`` 01-02, ``video`` 03, ``world`` 05;
``fits``: chapter 07's shipped fits) and :func:`train_or_load`, the notebooks' one entry.
"""

from . import checkpoints, fits, image, loop, optim, toy, video, world
from .runs import train_or_load

__all__ = ["checkpoints", "fits", "image", "loop", "optim", "toy", "train_or_load", "video",
           "world"]
