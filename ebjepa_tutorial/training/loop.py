"""The loop of every training run: seeded batches (a batch depends only on its step, so a
resumed run sees the batches it would have seen), a loss history, resumable runs. Under
``torchrun``, the history holds the mean over processes; process 0 alone reads and writes."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from .. import distributed
from .checkpoints import find_run, save_or_warn


class History(dict):
    """``history["loss"]``: one value per logged step, ``history["step"]``: its step numbers;
    ``seconds``: the training time."""

    seconds: float = 0.0

    def log(self, step: int, **metrics: float) -> None:
        self.setdefault("step", []).append(step)
        for name, value in metrics.items():
            self.setdefault(name, []).append(float(value))

    def last(self, name: str) -> float:
        return self[name][-1]


def step_generator(seed: int, step: int) -> torch.Generator:
    """The generator that draws the batch of step ``step`` of a run seeded ``seed``."""
    return torch.Generator().manual_seed(seed * 1_000_003 + step)


def _logged(loss, terms: dict, step: int) -> tuple[float, dict[str, float]]:
    """The loss and terms as floats (their mean over processes), checked to be finite."""
    value, *means = distributed.mean_of_floats(
        [v.item() if isinstance(v, torch.Tensor) else float(v) for v in (loss, *terms.values())])
    terms = dict(zip(terms, means))
    if not math.isfinite(value):
        detail = ", ".join(f"{k}={v:.4g}" for k, v in terms.items())
        raise FloatingPointError(
            f"the loss became {value} at step {step} ({detail}). Lower the learning rate, "
            "check the inputs for NaN, or check the loss coefficients.")
    return value, terms


def run_steps(update: Callable[[Any, int], tuple[torch.Tensor, Any]],
              batch_fn: Callable[[int], Any], steps: int, *, log_every: int = 1,
              desc: str = "training", progress: bool = True, checkpoint: str | Path | None = None,
              parts: tuple = (), identity: Any = None, every: int = 250,
              after: Callable[[int, History], Any] | None = None) -> History:
    """Steps ``0 .. steps - 1`` of ``update(batch_fn(step), step) -> (loss, terms)``, or the rest
    of the run ``identity`` saved at ``checkpoint`` (saved there every ``every`` steps and at
    the last). ``terms``: a dict of floats or 0-d tensors, or a function giving one, called
    only every ``log_every`` steps (reading a number waits for a GPU). ``after(done, history)``
    runs after each step and its save."""
    start, history = resume(checkpoint, *parts, config=identity) if parts else (0, History())
    bar = tqdm(range(start, steps), desc=desc, initial=start, total=steps,
               disable=not (progress and distributed.is_main()))
    started = time.perf_counter() - history.seconds
    for step in bar:
        loss, terms = update(batch_fn(step), step)
        if step % log_every == 0 or step == steps - 1:
            value, terms = _logged(loss, terms() if callable(terms) else terms, step)
            history.log(step, loss=value, **terms)
            bar.set_postfix(loss=f"{value:.4f}", refresh=False)
        history.seconds = time.perf_counter() - started
        done = step + 1
        if checkpoint is not None and distributed.is_main() and (done % every == 0 or
                                                                  done == steps):
            state = training_state(done, identity, history, *parts)
            checkpoint = checkpoint if save_or_warn(Path(checkpoint), **state) else None
        if after is not None and distributed.is_main():
            after(done, history)
    return history


def training_state(done: int, identity: Any, history: History, model: torch.nn.Module,
                   optimizer: torch.optim.Optimizer, scheduler=None, extra=None) -> dict:
    """A resumable checkpoint of the run ``identity`` after ``done`` steps (``extra``: another
    object with a state dict, such as a replay buffer)."""
    return dict(model=model.state_dict(), optimizer=optimizer.state_dict(),
                scheduler=None if scheduler is None else scheduler.state_dict(),
                history=dict(history), step=done, config=identity, seconds=history.seconds,
                **({} if extra is None else {"extra": extra.state_dict()}))


def _device(model: torch.nn.Module):
    """Where files are read to: the CPU in a process group (process 0 sends them on)."""
    return "cpu" if distributed.world_size() > 1 else next(model.parameters()).device


def _history(state: dict) -> History:
    history = History(state["history"])
    history.seconds = float(state.get("seconds") or 0.0)
    return history


def resume(path: str | Path | None, model: torch.nn.Module, optimizer: torch.optim.Optimizer,
           scheduler: Any = None, extra: Any = None, config: Any = None) -> tuple[int, History]:
    """Restore the :func:`training_state` of the run ``config`` saved at ``path``: ``(step,
    history)`` to continue from, ``(0, History())`` if there is none."""
    found = None if path is None else distributed.from_main(
        lambda: find_run(Path(path), config, _device(model)))
    if found is None:
        return 0, History()
    state = found[0]
    model.load_state_dict(state["model"])
    optimizer.load_state_dict(state["optimizer"])
    if scheduler is not None and state.get("scheduler") is not None:
        scheduler.load_state_dict(state["scheduler"])
    if extra is not None:
        extra.load_state_dict(state["extra"])
    return state["step"], _history(state)


def load_or_train(path: str | Path, model: torch.nn.Module, train: Callable[[], History],
                  config: Any, shipped: str | Path | None = None) -> History:
    """Load ``model`` with the run ``config`` from ``shipped`` or ``path``, else ``train()`` it in
    place, save it to ``path`` and delete ``<path>.partial``. Returns the history."""
    start, path = time.perf_counter(), Path(path)
    found = distributed.from_main(lambda: find_run(path, config, _device(model), shipped))
    if found is not None:
        model.load_state_dict(found[0]["model"])
        if distributed.is_main():
            print(f"Loaded a trained model from {found[1]} (skip training).")
        return _history(found[0])
    history = train()
    if distributed.is_main() and save_or_warn(path, model=model.state_dict(), config=config,
                                              history=dict(history), seconds=history.seconds):
        print(f"Trained and saved to {path} ({time.perf_counter() - start:.0f} s).")
        path.with_suffix(".partial").unlink(missing_ok=True)  # only now: it was all of the run
    return history
