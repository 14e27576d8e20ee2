"""Evaluation on frozen features: ``classify`` (linear probe, kNN: 01-02), ``detection``
(AP per horizon: 03), ``position`` (probes, wall tests: 05-06), ``cost`` (07), ``metrics``
(AP, intervals), ``sweeps`` (02's sweep file)."""

from . import classify, cost, detection, metrics, position, sweeps

__all__ = ["classify", "cost", "detection", "metrics", "position", "sweeps"]
