"""The learning-rate schedule of self-supervised training, warm-up then cosine, and AdamW's
parameter groups (no weight decay on biases and normalisation parameters, the 1-D ones)."""

from __future__ import annotations

import math

import torch
from torch.optim.lr_scheduler import LambdaLR


def warmup_cosine(step: int, total_steps: int, warmup_steps: int, base_lr: float,
                  final_lr: float = 0.0) -> float:
    """Learning rate of the update with index ``step`` (0-based) out of ``total_steps``.

    Warm-up: ``base_lr * (step + 1) / warmup_steps`` for ``step < warmup_steps`` (the full
    ``base_lr`` at the last warm-up step). Then a half cosine from that peak down to
    ``final_lr``, reached at the last step ``total_steps - 1``.
    """
    if not 0 <= step < total_steps:
        raise ValueError(f"step {step} is outside the schedule's 0..{total_steps - 1}")
    if step < warmup_steps:
        return base_lr * (step + 1) / warmup_steps
    peak = max(warmup_steps - 1, 0)  # the step that uses the full base_lr
    if total_steps - 1 == peak:
        return base_lr
    progress = (step - peak) / (total_steps - 1 - peak)  # 0 at the peak, 1 at the last step
    return final_lr + (base_lr - final_lr) * 0.5 * (1 + math.cos(math.pi * progress))


def warmup_cosine_scheduler(optimizer: torch.optim.Optimizer, total_steps: int,
                            warmup_steps: int) -> LambdaLR:
    """A scheduler following :func:`warmup_cosine` from each group's ``lr`` to 0; call
    ``.step()`` after each update (creating it sets the step-0 rate). Past the last step it
    holds the final rate."""
    return LambdaLR(optimizer, lambda step: warmup_cosine(
        min(step, total_steps - 1), total_steps, warmup_steps, 1.0))


def split_decay_params(model: torch.nn.Module, weight_decay: float) -> list[dict]:
    """Parameter groups for AdamW / SGD: weight decay on matrices only, none on 1-D params."""
    decay = [p for p in model.parameters() if p.requires_grad and p.ndim > 1]
    no_decay = [p for p in model.parameters() if p.requires_grad and p.ndim <= 1]
    return [{"params": decay, "weight_decay": weight_decay},
            {"params": no_decay, "weight_decay": 0.0}]
