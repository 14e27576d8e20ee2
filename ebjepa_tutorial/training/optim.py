"""The learning-rate schedule of self-supervised training, warm-up then cosine, and AdamW's
parameter groups (no weight decay on biases and normalisation parameters, the 1-D ones)."""

from __future__ import annotations

import math

import torch
from torch.optim.lr_scheduler import LambdaLR


def warmup_cosine(
    step: int, total_steps: int, warmup_steps: int, base_lr: float, final_lr: float = 0.0
) -> float:
    """Learning rate of the update with index ``step`` (0-based) out of ``total_steps``.

    Warm-up: ``base_lr * (step + 1) / warmup_steps`` for ``step < warmup_steps`` (never zero,
    and the full ``base_lr`` at the last warm-up step; the paper's code spends a first step at
    its start value). Then a half cosine from that peak down to ``final_lr``, reached at the
    last step ``total_steps - 1``. ``warmup_steps = 0`` starts the cosine at step 0.
    """
    if not 0 <= warmup_steps < total_steps:
        raise ValueError(f"need 0 <= warmup_steps < total_steps, got {warmup_steps}, {total_steps}")
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
    ``.step()`` after each update (creating it sets the step-0 rate)."""

    def factor(step: int) -> float:
        step = min(step, total_steps - 1)  # hold the final value if training runs over
        return warmup_cosine(step, total_steps, warmup_steps, 1.0)

    return LambdaLR(optimizer, factor)


def split_decay_params(model: torch.nn.Module, weight_decay: float) -> list[dict]:
    """Parameter groups for AdamW / SGD: weight decay on matrices only, none on 1-D params."""
    decay, no_decay = [], []
    for parameter in model.parameters():
        if parameter.requires_grad:
            (decay if parameter.ndim > 1 else no_decay).append(parameter)
    return [{"params": decay, "weight_decay": weight_decay},
            {"params": no_decay, "weight_decay": 0.0}]
