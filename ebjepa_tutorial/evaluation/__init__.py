"""Evaluation on frozen features: linear probe and kNN (01-02), detection AP (03), position
probes and wall tests (05-06), AP and intervals, 02's sweep file."""

from . import classify, detection, metrics, position, sweeps

__all__ = ["classify", "detection", "metrics", "position", "sweeps"]
