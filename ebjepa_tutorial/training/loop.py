"""A small training loop with a progress bar, a loss history and resumable runs.

The loop is deliberately plain: a notebook passes a ``loss_fn`` that computes
the loss of one batch and a ``batch_fn`` that returns batch number ``step``.
Because the batch depends only on ``step`` (draw it from
:func:`step_generator`), a run that resumes from a checkpoint sees exactly the batches
it would have seen without the interruption.

Introduced in notebook 00; every training run of the course goes through
:func:`run_steps` (a notebook's whole training step) or :func:`fit` (a loss:
backward and the optimiser's step), and :func:`load_or_train`.

In a process group (``torchrun``), :func:`run_steps` logs the mean over ranks of the
loss and its terms, shows progress and writes checkpoints on rank 0 only, and
:func:`resume` and :func:`load_or_train` read the files on rank 0 and send them
to every rank.
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
from .checkpoints import checkpoint_paths, claim, read_run, same_run, save_or_warn

LossFn = Callable[[Any], tuple[torch.Tensor, dict[str, torch.Tensor | float]]]


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

    seconds: float = 0.0  # training wall time so far, summed over resumed parts (not logged)

    def last(self, name: str) -> float:
        """The most recent value of ``name``."""
        return self[name][-1]


def step_generator(seed: int, step: int) -> torch.Generator:
    """The generator that draws the batch of optimiser step ``step`` of a run seeded ``seed``.

    Seeded by the step alone, so a resumed run sees exactly the batches it
    would have seen without the interruption.
    """
    return torch.Generator().manual_seed(seed * 1_000_003 + step)


def _check_finite(loss: float, terms: dict[str, float], step: int) -> None:
    if not math.isfinite(loss):
        detail = ", ".join(f"{k}={v:.4g}" for k, v in terms.items())
        raise FloatingPointError(
            f"the loss became {loss} at step {step} ({detail}). Lower the "
            "learning rate, check the inputs for NaN, or check the loss coefficients."
        )


def _number(value: torch.Tensor | float) -> float:
    return value.item() if isinstance(value, torch.Tensor) else float(value)


def _over_ranks(loss: torch.Tensor, terms: dict) -> tuple[float, dict[str, float]]:
    """The loss and terms averaged over ranks (as is in one process): what one device would log.

    Every rank gets the same numbers, so a non-finite loss stops all ranks together.
    Reading them makes the CPU wait for the GPU, so :func:`run_steps` does it only when it logs.
    """
    values = distributed.mean_of_floats([loss.item(), *map(_number, terms.values())])
    return values[0], dict(zip(terms, values[1:]))


def run_steps(
    update: Callable[[Any, int], tuple[torch.Tensor, Any]],
    batch_fn: Callable[[int], Any],
    steps: int,
    *,
    start_step: int = 0,
    history: History | None = None,
    log_every: int = 1,
    desc: str = "training",
    progress: bool = True,
    after: Callable[[int], Any] | None = None,
) -> History:
    """The loop every recipe shares: steps ``start_step .. steps - 1`` of ``update``.

    ``update(batch_fn(step), step) -> (loss, terms)`` takes one whole training step
    (forward, backward, the optimiser's step: a notebook writes it in a cell); ``terms`` is a
    dict of 0-d tensors or floats, or a function returning one, called only on the steps
    logged. Every ``log_every`` steps (and the last) the loss and terms are read (the one
    wait for a GPU), averaged over ranks, checked to be finite and logged, the total as
    ``"loss"``. ``after(done)``, on rank 0 after each step, saves what the caller keeps.
    """
    history = History() if history is None else history
    bar = tqdm(range(start_step, steps), desc=desc, initial=start_step, total=steps,
               disable=not (progress and distributed.is_main()))  # one bar, not one per rank
    started = time.perf_counter() - history.seconds
    for step in bar:
        loss, terms = update(batch_fn(step), step)
        if step % log_every == 0 or step == steps - 1:
            value, terms = _over_ranks(loss, terms() if callable(terms) else terms)
            _check_finite(value, terms, step)
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
    """:func:`run_steps` with :func:`backward_step`'s update; returns the :class:`History`.

    With ``checkpoint``, the model, optimiser, scheduler, history and step are saved every
    ``checkpoint_every`` steps and at the end, with ``config`` (the run's identity) for
    :func:`resume`. In a process group, ``model`` is the bare module (rank 0 saves it) and
    ``loss_fn`` calls its DDP wrapper.
    """
    history = History() if history is None else history
    model.train()

    def state(done: int) -> dict[str, Any]:
        return training_state(done, config, history, model, optimizer, scheduler)

    return run_steps(backward_step(optimizer, loss_fn, scheduler), batch_fn, steps,
                     start_step=start_step, history=history, log_every=log_every, desc=desc,
                     progress=progress, after=saver(checkpoint, state, steps, checkpoint_every))


def training_state(done: int, identity: dict[str, Any] | None, history: History,
                   model: torch.nn.Module, optimizer: torch.optim.Optimizer, scheduler=None,
                   after_step=None) -> dict[str, Any]:
    """What a resumable checkpoint holds after ``done`` steps of the run ``identity`` (what
    :func:`resume` reads back): the model's, optimiser's, scheduler's and ``after_step``'s
    states, the history and its wall time."""
    extra = {} if after_step is None else {"after_step": after_step.state_dict()}
    return dict(model=model.state_dict(), optimizer=optimizer.state_dict(),
                scheduler=None if scheduler is None else scheduler.state_dict(),
                history=dict(history), step=done, config=identity,
                seconds=history.seconds, **extra)


def backward_step(optimizer, loss_fn: LossFn, scheduler=None):
    """``update(batch, step)`` for :func:`run_steps` from a loss: ``loss_fn(batch)``, backward,
    the optimiser's and scheduler's steps. Returns the loss and its terms."""

    def update(batch, step: int):
        loss, terms = loss_fn(batch)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if scheduler is not None:
            scheduler.step()
        return loss, terms

    return update


def resume(
    path: str | Path | None,
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler: Any = None,
    config: dict[str, Any] | None = None,
    after_step: Any = None,
) -> tuple[int, History]:
    """Restore the state saved by :func:`fit`; return ``(step, history)`` to continue from.

    ``after_step``: an object saved beside the run (:func:`training_state`), whose state is
    loaded too.

    Returns ``(0, History())`` when there is no checkpoint of the run ``config``
    (its identity) yet, or no ``path`` (a run that keeps none). A file at
    ``path`` from another run is kept under
    :func:`~ebjepa_tutorial.training.checkpoints.kept_path` (and resumed from
    there when you return to that run); a damaged one is moved aside.
    """
    if path is None:
        return 0, History()
    device = "cpu" if distributed.world_size() > 1 else next(model.parameters()).device
    # rank 0 alone reads (and may move) the files; every rank gets its state, on the CPU
    state = distributed.from_main(lambda: claim(Path(path), config, device))
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


def load_or_train(
    path: str | Path,
    model: torch.nn.Module,
    train: Callable[[], History],
    config: dict[str, Any],
    shipped: str | Path | None = None,
    partial: str | Path | None = None,
) -> History:
    """Load ``model`` from a checkpoint of the run ``config``, else train it and save to ``path``.

    ``config`` is the run's identity
    (:func:`~ebjepa_tutorial.training.checkpoints.run_identity`). ``shipped`` (a
    checkpoint that comes with the course) is tried first, then ``path``.
    ``train()`` trains ``model`` in place and returns its history. A file of
    another run is not loaded; at ``path`` it is kept under another name.
    ``partial``, the resumable checkpoint ``train()`` writes, is deleted only
    once the trained model is safely saved. Prints which happened and how long
    it took, so a class knows whether it waited. In a process group every rank
    trains (or loads), and rank 0 alone reads the files, prints and saves.
    """
    start = time.perf_counter()
    device = "cpu" if distributed.world_size() > 1 else next(model.parameters()).device
    # rank 0 alone reads (and may move) the files; every rank gets the state, on the CPU
    found = distributed.from_main(lambda: _saved_run(Path(path), config, device, shipped))
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
    ``path`` (see :func:`~ebjepa_tutorial.training.checkpoints.claim`); None if neither."""
    state = None if shipped is None else read_run(Path(shipped), device, movable=False)
    if state is not None and same_run(state, config):
        return state, shipped
    if state is not None:
        print(f"{shipped} was trained with another configuration; not using it.")
    state = claim(path, config, device)
    return None if state is None else (state, path)


def load_or_fit(name: str, module: torch.nn.Module, fit_module: Callable[[], tuple],
                config: dict[str, Any]) -> torch.nn.Module:
    """``module`` loaded from ``checkpoints/<name>.pt`` or the cache if the run ``config`` (its
    identity) was saved, else ``fit_module() -> (fitted, history)`` copied into it and saved to
    the cache (:func:`load_or_train`). Returns ``module`` in eval mode."""
    cache_path, shipped = checkpoint_paths(name)

    def train() -> History:
        fitted, history = fit_module()
        module.load_state_dict(fitted.state_dict())
        return history

    load_or_train(cache_path, module, train, config, shipped)
    return module.eval()
