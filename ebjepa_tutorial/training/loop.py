"""The loop every training run goes through: seeded batches, a loss history, resumable runs.

A recipe passes ``update(batch, step)``, one whole training step, and ``batch_fn(step)``; the
batch depends only on ``step`` (:func:`step_generator`), so a resumed run sees exactly the
batches it would have seen. In a process group (``torchrun``) the loss is logged as its mean
over ranks, and rank 0 alone shows progress and reads and writes the files.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from .. import distributed
from .checkpoints import claim, read_run, same_run, save_or_warn


class History(dict):
    """Metrics over training, a plain ``dict`` of lists: ``history["loss"]`` holds one value
    per logged step, ``history["step"]`` the step numbers."""

    seconds: float = 0.0  # training wall time so far, summed over resumed parts (not logged)

    def log(self, step: int, **metrics: float) -> None:
        """Append one row: the step number and one value per metric."""
        self.setdefault("step", []).append(step)
        for name, value in metrics.items():
            self.setdefault(name, []).append(float(value))

    def last(self, name: str) -> float:
        """The most recent value of ``name``."""
        return self[name][-1]


def step_generator(seed: int, step: int) -> torch.Generator:
    """The generator that draws the batch of step ``step`` of a run seeded ``seed``."""
    return torch.Generator().manual_seed(seed * 1_000_003 + step)


def _logged(loss: torch.Tensor, terms: dict, step: int) -> tuple[float, dict[str, float]]:
    """The loss and terms as floats averaged over ranks (every rank gets the same, so a
    non-finite loss stops all of them together), checked to be finite."""
    numbers = [v.item() if isinstance(v, torch.Tensor) else float(v)
               for v in (loss, *terms.values())]
    value, *means = distributed.mean_of_floats(numbers)
    terms = dict(zip(terms, means))
    if not math.isfinite(value):
        detail = ", ".join(f"{k}={v:.4g}" for k, v in terms.items())
        raise FloatingPointError(
            f"the loss became {value} at step {step} ({detail}). Lower the "
            "learning rate, check the inputs for NaN, or check the loss coefficients."
        )
    return value, terms


def run_steps(update: Callable[[Any, int], tuple[torch.Tensor, Any]],
              batch_fn: Callable[[int], Any], steps: int, *, start_step: int = 0,
              history: History | None = None, log_every: int = 1, desc: str = "training",
              progress: bool = True, after: Callable[[int], Any] | None = None) -> History:
    """Steps ``start_step .. steps - 1`` of ``update(batch_fn(step), step) -> (loss, terms)``.

    ``terms``: a dict of 0-d tensors or floats, or a function giving one, called only on the
    steps logged: every ``log_every`` steps and the last, where the loss (as ``"loss"``) and
    terms are read (the one wait for a GPU) and logged. ``after(done)``, on rank 0 after each
    step, saves what the caller keeps.
    """
    history = History() if history is None else history
    bar = tqdm(range(start_step, steps), desc=desc, initial=start_step, total=steps,
               disable=not (progress and distributed.is_main()))  # one bar, not one per rank
    started = time.perf_counter() - history.seconds
    for step in bar:
        loss, terms = update(batch_fn(step), step)
        if step % log_every == 0 or step == steps - 1:
            value, terms = _logged(loss, terms() if callable(terms) else terms, step)
            history.log(step, loss=value, **terms)
            bar.set_postfix(loss=f"{value:.4f}", refresh=False)
        history.seconds = time.perf_counter() - started
        if after is not None and distributed.is_main():
            after(step + 1)
    return history


def saver(path: str | Path | None, state: Callable[[int], dict], steps: int, every: int):
    """``after(done)`` for :func:`run_steps`: ``state(done)`` saved to ``path`` every ``every``
    steps and at the last; a folder that cannot be written warns once and training goes on."""
    target = [path]

    def after(done: int) -> None:
        if target[0] is not None and (done % every == 0 or done == steps):
            target[0] = target[0] if save_or_warn(Path(target[0]), **state(done)) else None

    return after


def training_state(done: int, identity: dict[str, Any] | None, history: History,
                   model: torch.nn.Module, optimizer: torch.optim.Optimizer, scheduler=None,
                   after_step=None) -> dict[str, Any]:
    """What a resumable checkpoint of the run ``identity`` holds after ``done`` steps, as
    :func:`resume` reads it back (``after_step``: an object whose state is saved too)."""
    extra = {} if after_step is None else {"after_step": after_step.state_dict()}
    return dict(model=model.state_dict(), optimizer=optimizer.state_dict(),
                scheduler=None if scheduler is None else scheduler.state_dict(),
                history=dict(history), step=done, config=identity,
                seconds=history.seconds, **extra)


def _device(model: torch.nn.Module):
    """Where the files are read to: the CPU in a process group (rank 0 sends them on)."""
    return "cpu" if distributed.world_size() > 1 else next(model.parameters()).device


def resume(path: str | Path | None, model: torch.nn.Module, optimizer: torch.optim.Optimizer,
           scheduler: Any = None, config: dict[str, Any] | None = None,
           after_step: Any = None) -> tuple[int, History]:
    """Restore the :func:`training_state` of the run ``config`` (its identity) saved at ``path``;
    return ``(step, history)`` to continue from, ``(0, History())`` if there is none.

    Another run's file at ``path`` is kept under
    :func:`~ebjepa_tutorial.training.checkpoints.kept_path`; a damaged one is moved aside.
    """
    if path is None:
        return 0, History()
    state = distributed.from_main(lambda: claim(Path(path), config, _device(model)))
    if state is None:
        return 0, History()
    model.load_state_dict(state["model"])
    optimizer.load_state_dict(state["optimizer"])
    if scheduler is not None and state.get("scheduler") is not None:
        scheduler.load_state_dict(state["scheduler"])
    if after_step is not None:
        after_step.load_state_dict(state["after_step"])
    return state["step"], _history(state)


def _history(state: dict) -> History:
    history = History(state["history"])
    history.seconds = float(state.get("seconds") or 0.0)
    return history


def load_or_train(path: str | Path, model: torch.nn.Module, train: Callable[[], History],
                  config: dict[str, Any], shipped: str | Path | None = None,
                  partial: str | Path | None = None) -> History:
    """Load ``model`` from a checkpoint of the run ``config`` (its identity), ``shipped`` first,
    then ``path``; else ``train()`` it in place and save it to ``path``. Returns the history.

    ``partial``, the resumable checkpoint ``train()`` writes, is deleted only once the model is
    saved. Prints which happened and how long it took. In a process group every rank trains
    (or loads), and rank 0 alone reads the files, prints and saves.
    """
    start = time.perf_counter()
    found = distributed.from_main(lambda: _saved_run(Path(path), config, _device(model), shipped))
    if found is not None:
        state, source = found
        model.load_state_dict(state["model"])
        if distributed.is_main():
            print(f"Loaded a trained model from {source} (skip training).")
        return _history(state)
    history = train()
    seconds = time.perf_counter() - start
    if distributed.is_main() and save_or_warn(
            Path(path), model=model.state_dict(), history=dict(history), config=config,
            seconds=getattr(history, "seconds", 0.0)):
        print(f"Trained and saved to {path} ({seconds:.0f} s).")
        if partial is not None:  # only now: until the save, it is all there is of the run
            Path(partial).unlink(missing_ok=True)
    return history


def _saved_run(path: Path, config, device, shipped) -> tuple[dict, Path] | None:
    """The stored state of the run ``config`` and where it was: ``shipped`` first, then
    ``path`` (:func:`~ebjepa_tutorial.training.checkpoints.claim`); None if neither."""
    state = None if shipped is None else read_run(Path(shipped), device, movable=False)
    if state is not None and same_run(state, config):
        return state, shipped
    if state is not None:
        print(f"{shipped} was trained with another configuration; not using it.")
    state = claim(path, config, device)
    return None if state is None else (state, path)
