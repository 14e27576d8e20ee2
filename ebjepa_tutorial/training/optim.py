"""The learning-rate schedule of self-supervised training, warm-up then cosine, and AdamW's
parameter groups (no weight decay on biases and normalisation parameters, the 1-D ones)."""

from __future__ import annotations

import math

import torch
from torch.optim.lr_scheduler import LambdaLR


def warmup_cosine(step: int, total_steps: int, warmup_steps: int) -> float:
    """The share of the peak rate that update ``step`` (0-based, of ``total_steps``) uses:
    ``(step + 1) / warmup_steps`` during the warm-up (1 at its last step), then a half cosine
    from 1 down to 0 at the last step ``total_steps - 1``."""
    if step < warmup_steps:
        return (step + 1) / warmup_steps
    peak = max(warmup_steps - 1, 0)  # the step that uses the full rate
    if total_steps - 1 == peak:
        return 1.0
    progress = (step - peak) / (total_steps - 1 - peak)  # 0 at the peak, 1 at the last step
    return 0.5 * (1 + math.cos(math.pi * progress))


def warmup_cosine_scheduler(optimizer: torch.optim.Optimizer, total_steps: int,
                            warmup_steps: int) -> LambdaLR:
    """A scheduler following :func:`warmup_cosine` from each group's ``lr``, held past the end."""
    return LambdaLR(optimizer, lambda step: warmup_cosine(
        min(step, total_steps - 1), total_steps, warmup_steps))


def split_decay_params(model: torch.nn.Module, weight_decay: float) -> list[dict]:
    """Parameter groups for AdamW / SGD: weight decay on matrices only, none on 1-D params."""
    decay = [p for p in model.parameters() if p.requires_grad and p.ndim > 1]
    no_decay = [p for p in model.parameters() if p.requires_grad and p.ndim <= 1]
    return [{"params": decay, "weight_decay": weight_decay},
            {"params": no_decay, "weight_decay": 0.0}]
