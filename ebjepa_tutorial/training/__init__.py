"""Training: the loop with its checkpoints, the optimisers, and one recipe per chapter.

- ``loop``: :func:`fit`, resumable checkpoints, :func:`load_or_train`, seeded batches
- ``optim``: LARS and the warm-up-then-cosine schedule
- ``toy`` (chapter 00), ``image`` (01-02), ``video`` (03), ``world`` (05, with the refit)
"""

from . import image, loop, optim, toy, video, world

__all__ = ["image", "loop", "optim", "toy", "video", "world"]
