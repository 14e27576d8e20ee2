"""Helpers for the EB-JEPA course: short, readable functions the notebooks call.

Tensor layout, everywhere: images ``(B, C, H, W)``, float32 in ``[0, 1]`` before normalisation
(stored data sets: uint8 ``(N, C, H, W)``); videos and trajectories ``(B, T, C, H, W)``, actions
``(B, T-1, A)``, one between consecutive frames; embeddings ``(B, D)``, or ``(B, T, D)`` along
time. Every random function takes a ``seed`` or a ``torch.Generator``."""
