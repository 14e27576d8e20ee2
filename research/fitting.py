"""``fit``: the package's loop on a loss, for research's fits on frozen latents (chapter 05's
predictor refit, chapter 07's cost head and coarse model)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from ebjepa_tutorial.models.world import encode_trajectories
from ebjepa_tutorial.training.loop import History, run_steps


def fit(model: torch.nn.Module, optimizer: torch.optim.Optimizer,
        loss_fn: Callable[[Any], tuple[torch.Tensor, dict]], batch_fn: Callable[[int], Any],
        steps: int, *, scheduler: Any = None, log_every: int = 1, desc: str = "training",
        progress: bool = True) -> History:
    """Train ``model`` for ``steps`` steps, each ``loss_fn(batch_fn(step)) -> (loss, terms)``,
    its backward, the optimiser's step and the scheduler's; returns the history."""
    model.train()

    def update(batch, step: int):
        loss, terms = loss_fn(batch)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if scheduler is not None:
            scheduler.step()
        return loss, terms

    return run_steps(update, batch_fn, steps, log_every=log_every, desc=desc, progress=progress)


def trajectory_latents(model, trajectories) -> torch.Tensor:
    """Every frame's latent, trajectory by trajectory, without gradients: ``(N, T+1, D)``."""
    latents = encode_trajectories(model, trajectories, 200)[0]
    return latents.view(len(trajectories), -1, latents.shape[-1])
