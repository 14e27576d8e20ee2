"""Optimiser and learning-rate schedule for self-supervised training: LARS and warm-up + cosine.

LARS (You et al., 2017) scales each weight matrix's step by a "trust ratio"
``eta * ||w|| / ||g + wd * w||``, so every layer moves by about the same
*relative* amount whatever its gradient scale. That lets SSL methods train
with large batches and a large base learning rate (EB-JEPA: 0.3 at batch 256).
As in the usual SSL implementations (Barlow Twins, VICReg), biases and
normalisation parameters (every 1-D parameter) get neither weight decay nor
the trust ratio.

The schedule warms up linearly from the very first step: step 0 uses
``base_lr / warmup_steps``, step ``warmup_steps - 1`` the full ``base_lr``,
then a cosine decays to ``final_lr`` at the last step. (The paper's reference
code is off by one and spends a first warm-up period at its start value.)
"""

from __future__ import annotations

import math

import torch
from torch.optim.lr_scheduler import LambdaLR


class LARS(torch.optim.Optimizer):
    """SGD with momentum, weight decay and LARS trust ratios for parameters with ndim > 1.

    For each parameter ``w`` with gradient ``g``:

        if w.ndim > 1:  u = g + weight_decay * w
                        u = u * eta * ||w|| / ||u||   (unchanged if either norm is 0)
        else:           u = g                          (biases, BatchNorm / LayerNorm)
        m = momentum * m + u      (m starts at 0, so the first step uses m = u)
        w = w - lr * m
    """

    def __init__(
        self,
        params,
        lr: float = 0.3,
        weight_decay: float = 1e-4,
        momentum: float = 0.9,
        eta: float = 0.001,
    ):
        if lr < 0 or weight_decay < 0 or not 0 <= momentum < 1 or eta <= 0:
            raise ValueError(
                f"need lr >= 0, weight_decay >= 0, 0 <= momentum < 1, eta > 0; got lr={lr}, "
                f"weight_decay={weight_decay}, momentum={momentum}, eta={eta}"
            )
        defaults = dict(lr=lr, weight_decay=weight_decay, momentum=momentum, eta=eta)
        super().__init__(params, defaults)

    @torch.no_grad()
    def step(self, closure=None):
        loss = None
        if closure is not None:
            with torch.enable_grad():
                loss = closure()
        for group in self.param_groups:
            for w in group["params"]:
                if w.grad is None:
                    continue
                update = w.grad
                if w.ndim > 1:
                    update = update.add(w, alpha=group["weight_decay"])
                    w_norm, u_norm = torch.norm(w), torch.norm(update)
                    ratio = group["eta"] * w_norm / u_norm
                    ratio = torch.where((w_norm > 0) & (u_norm > 0), ratio, torch.ones_like(ratio))
                    update = update * ratio
                state = self.state[w]
                if "momentum_buffer" not in state:
                    state["momentum_buffer"] = torch.zeros_like(w)
                buffer = state["momentum_buffer"]
                buffer.mul_(group["momentum"]).add_(update)
                w.add_(buffer, alpha=-group["lr"])
        return loss


def warmup_cosine(
    step: int, total_steps: int, warmup_steps: int, base_lr: float, final_lr: float = 0.0
) -> float:
    """Learning rate of the update with index ``step`` (0-based) out of ``total_steps``.

    Warm-up: ``base_lr * (step + 1) / warmup_steps`` for ``step < warmup_steps``
    (never zero, and the full ``base_lr`` at the last warm-up step). Then a
    half cosine from that peak down to ``final_lr``, reached at the last step
    ``total_steps - 1``. ``warmup_steps = 0`` starts the cosine at step 0.
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


def warmup_cosine_scheduler(
    optimizer: torch.optim.Optimizer,
    total_steps: int,
    warmup_steps: int,
    final_lr_ratio: float = 0.0,
) -> LambdaLR:
    """A torch scheduler that follows :func:`warmup_cosine`; call ``.step()`` after each update.

    The optimiser's ``lr`` (per group) is the base learning rate; the final one
    is ``final_lr_ratio * lr``. Creating the scheduler already sets the step-0 value.
    """

    def factor(step: int) -> float:
        step = min(step, total_steps - 1)  # hold the final value if training runs over
        return warmup_cosine(step, total_steps, warmup_steps, 1.0, final_lr_ratio)

    return LambdaLR(optimizer, factor)


def split_decay_params(model: torch.nn.Module, weight_decay: float) -> list[dict]:
    """Parameter groups for AdamW / SGD: weight decay on matrices only, none on 1-D params."""
    decay, no_decay = [], []
    for parameter in model.parameters():
        if parameter.requires_grad:
            (decay if parameter.ndim > 1 else no_decay).append(parameter)
    return [
        {"params": decay, "weight_decay": weight_decay},
        {"params": no_decay, "weight_decay": 0.0},
    ]
