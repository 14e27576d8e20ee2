"""Evaluation on frozen features.

- ``classify``: the linear probe and kNN of chapters 01-02
- ``cost``: chapter 07's distances between latents against the shortest way round the walls
- ``detection``: chapter 03's detection probe and AP per horizon
- ``position``: chapter 05's position probes and the middle-wall test
- ``metrics``: average precision and confidence intervals
- ``sweeps``: chapter 02's class-scale sweeps, read back from their file
"""

from . import classify, cost, detection, metrics, position, sweeps

__all__ = ["classify", "cost", "detection", "metrics", "position", "sweeps"]
