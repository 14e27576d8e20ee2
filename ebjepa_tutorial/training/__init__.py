"""Training: the loop with its checkpoints, the optimisers, and one recipe per chapter.

- ``loop``: :func:`fit`, resuming, :func:`load_or_train`, seeded batches
- ``optim``: the warm-up-then-cosine schedule and AdamW's parameter groups
- ``checkpoints``: safe files, run identities, where runs are cached and shipped
- ``toy`` (chapter 00), ``image`` (01-02), ``video`` (03), ``world`` (05, with the refit)
- ``cost`` and ``hierarchy`` (07): a cost head and a coarse model on frozen latents
- ``runs``: :func:`train_or_load`, the one entry the notebooks call
"""

from . import checkpoints, cost, hierarchy, image, loop, optim, toy, video, world
from .runs import train_or_load

__all__ = ["checkpoints", "cost", "hierarchy", "image", "loop", "optim", "toy", "train_or_load",
           "video", "world"]
