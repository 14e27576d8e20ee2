"""A small training loop with a progress bar, a loss history and resumable checkpoints.

The loop is deliberately plain: a notebook passes a ``loss_fn`` that computes
the loss of one batch and a ``batch_fn`` that returns batch number ``step``.
Because the batch depends only on ``step`` (draw it from a generator seeded
with the step), a run that resumes from a checkpoint sees exactly the batches
it would have seen without the interruption.

Introduced in notebook 00; every training cell of the course goes through
:func:`fit` or :func:`load_or_train`.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

LossFn = Callable[[Any], tuple[torch.Tensor, dict[str, float]]]


class History(dict):
    """Metrics over training: ``history["loss"]`` is a list with one value per logged step.

    A plain ``dict`` of lists, so it pickles, prints and plots without ceremony.
    ``history["step"]`` holds the step number of each row.
    """

    def log(self, step: int, **metrics: float) -> None:
        """Append one row: the step number and one value per metric."""
        self.setdefault("step", []).append(step)
        for name, value in metrics.items():
            self.setdefault(name, []).append(float(value))

    def last(self, name: str) -> float:
        """The most recent value of ``name``."""
        return self[name][-1]


def save_checkpoint(path: str | Path, **state: Any) -> Path:
    """Write ``state`` with ``torch.save`` atomically: a temp file, then a rename.

    A kernel that dies mid-write leaves the previous checkpoint intact.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(state, f)
        os.chmod(tmp, 0o644)  # mkstemp makes the file private; a checkpoint is shareable
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    """Read a checkpoint written by :func:`save_checkpoint` (a dict of state)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    return torch.load(path, map_location=map_location, weights_only=False)


def _check_finite(loss: torch.Tensor, terms: dict[str, float], step: int) -> None:
    if not torch.isfinite(loss):
        detail = ", ".join(f"{k}={v:.4g}" for k, v in terms.items())
        raise FloatingPointError(
            f"the loss became {loss.item()} at step {step} ({detail}). Lower the "
            "learning rate, check the inputs for NaN, or check the loss coefficients."
        )


def fit(
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    loss_fn: LossFn,
    batch_fn: Callable[[int], Any],
    steps: int,
    *,
    scheduler: Any = None,
    history: History | None = None,
    start_step: int = 0,
    checkpoint: str | Path | None = None,
    checkpoint_every: int = 100,
    log_every: int = 1,
    desc: str = "training",
    progress: bool = True,
    config: dict[str, Any] | None = None,
) -> History:
    """Train for ``steps`` optimiser steps; return the :class:`History` of logged terms.

    ``loss_fn(batch) -> (loss, terms)`` where ``loss`` is a 0-d tensor and
    ``terms`` a dict of floats to log (the total is logged as ``"loss"``).
    ``batch_fn(step)`` returns the batch for optimiser step ``step``.
    With ``checkpoint``, the model, optimiser, scheduler, history and step are
    saved every ``checkpoint_every`` steps and at the end, with ``config`` (a
    plain dict describing the run) so that :func:`resume` recognises its own runs.
    """
    history = History() if history is None else history
    model.train()
    bar = tqdm(range(start_step, steps), desc=desc, disable=not progress,
               initial=start_step, total=steps)
    for step in bar:
        loss, terms = loss_fn(batch_fn(step))
        _check_finite(loss, terms, step)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if scheduler is not None:
            scheduler.step()
        if step % log_every == 0 or step == steps - 1:
            history.log(step, loss=loss.item(), **terms)
            bar.set_postfix(loss=f"{loss.item():.4f}", refresh=False)
        done = step + 1
        if checkpoint is not None and (done % checkpoint_every == 0 or done == steps):
            save_checkpoint(
                checkpoint,
                model=model.state_dict(),
                optimizer=optimizer.state_dict(),
                scheduler=None if scheduler is None else scheduler.state_dict(),
                history=dict(history),
                step=done,
                config=config,
            )
    return history


def resume(
    path: str | Path,
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler: Any = None,
    config: dict[str, Any] | None = None,
) -> tuple[int, History]:
    """Restore the state saved by :func:`fit`; return ``(step, history)`` to continue from.

    Returns ``(0, History())`` when there is no checkpoint yet, or when the
    file was written by a run with another ``config`` (it is then left alone
    and overwritten by the new run's first checkpoint).
    """
    if not Path(path).is_file():
        return 0, History()
    state = load_checkpoint(path, map_location=next(model.parameters()).device)
    if state.get("config") != config:
        print(f"{path} belongs to a run with another configuration; starting afresh.")
        return 0, History()
    model.load_state_dict(state["model"])
    optimizer.load_state_dict(state["optimizer"])
    if scheduler is not None and state.get("scheduler") is not None:
        scheduler.load_state_dict(state["scheduler"])
    return state["step"], History(state["history"])


SHIPPED_DIR = Path(__file__).resolve().parents[1] / "checkpoints"


def checkpoint_paths(name: str) -> tuple[Path, Path]:
    """Where a notebook's run called ``name`` is saved, and where a shipped copy would be.

    Runs trained on your machine go to ``data/cache/checkpoints/<name>.pt``
    (git-ignored); checkpoints that come with the course are in
    ``checkpoints/<name>.pt``, made by the command documented in checkpoints/README.md.
    """
    from .data.paths import cache_dir  # the data package owns the cache location

    return cache_dir() / "checkpoints" / f"{name}.pt", SHIPPED_DIR / f"{name}.pt"


def load_or_train(
    path: str | Path,
    model: torch.nn.Module,
    train: Callable[[], History],
    config: dict[str, Any],
    shipped: str | Path | None = None,
) -> History:
    """Load ``model`` from a checkpoint trained with ``config``, else train it and save to ``path``.

    ``shipped`` (a checkpoint that comes with the course) is tried first, then
    ``path``. ``train()`` trains ``model`` in place and returns its history. A
    file whose stored config differs (other sizes, other coefficients) is not
    loaded. Prints which of the two happened, so a class knows whether it waited.
    """
    device = next(model.parameters()).device
    for candidate in (shipped, path):
        if candidate is None or not Path(candidate).is_file():
            continue
        state = load_checkpoint(candidate, map_location=device)
        if state.get("config") == config:
            model.load_state_dict(state["model"])
            print(f"Loaded a trained model from {candidate} (skip training).")
            return History(state["history"])
        print(f"{candidate} was trained with another configuration; not using it.")
    history = train()
    save_checkpoint(path, model=model.state_dict(), history=dict(history), config=config)
    print(f"Trained and saved to {path}.")
    return history
