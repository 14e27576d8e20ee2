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
    of the run ``identity`` saved at ``checkpoint`` (every ``every`` steps and at the last; it
    resumes only with ``parts``).
    ``terms``: a dict of floats or 0-d tensors, or a function giving one, called only every
    ``log_every`` steps (reading a number waits for a GPU); then ``after(done, history)``."""
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


PARTS = ("model", "optimizer", "scheduler", "extra")  # the parts of a resumable run, in order


def training_state(done: int, identity: Any, history: History, *parts) -> dict:
    """A resumable checkpoint of the run ``identity`` after ``done`` steps: the state dicts of
    ``parts``, named as in :data:`PARTS` (``extra``: such as a replay buffer; None: left out)."""
    states = {key: part.state_dict() for key, part in zip(PARTS, parts) if part is not None}
    return dict(states, history=dict(history), step=done, config=identity, seconds=history.seconds)


def _found(path: Path, config: Any, model: torch.nn.Module, shipped=None):
    """:func:`find_run` on process 0, read to the CPU in a process group and sent on."""
    device = "cpu" if distributed.world_size() > 1 else next(model.parameters()).device
    found = distributed.from_main(lambda: find_run(path, config, device, shipped))
    if found is None:
        return None, None
    history = History(found[0]["history"])
    history.seconds = float(found[0].get("seconds") or 0.0)
    return found, history


def resume(path: str | Path | None, *parts, config: Any = None) -> tuple[int, History]:
    """Restore ``parts`` (see :func:`training_state`) from the run ``config`` saved at ``path``:
    ``(step, history)`` to continue from, ``(0, History())`` if there is none."""
    found, history = (None, None) if path is None else _found(Path(path), config, parts[0])
    if found is None:
        return 0, History()
    for key, part in zip(PARTS, parts):
        if part is not None:  # a part the run has must be in its file: never resume without it
            part.load_state_dict(found[0][key])
    return found[0]["step"], history


def load_or_train(path: str | Path, model: torch.nn.Module, train: Callable, config: Any,
                  shipped: str | Path | None = None) -> tuple[torch.nn.Module, History]:
    """``(model in eval mode, history)`` of the run ``config``: loaded from ``shipped`` or
    ``path``, else given the weights of ``train(partial) -> (trained model, history)`` (a run
    resumable from the file ``partial``) and saved to ``path``; ``train`` None: only loaded."""
    start, path = time.perf_counter(), Path(path)
    found, history = _found(path, config, model, shipped)
    if found is not None:
        model.load_state_dict(found[0]["model"])
        if distributed.is_main():
            print(f"Loaded a trained model from {found[1]} (skip training).")
        return model.eval(), history
    if train is None:  # a run that is only loaded
        raise FileNotFoundError(f"no saved run of this configuration at {shipped} or {path} (a "
                                "file of another configuration is not used: pass the preset's "
                                "config, or train this one in its notebook)")
    trained, history = train(path.with_suffix(".partial"))
    model.load_state_dict(trained.state_dict())
    if distributed.is_main() and save_or_warn(path, final=True, model=model.state_dict(),
                                              config=config, history=dict(history),
                                              seconds=history.seconds):
        print(f"Trained and saved to {path} ({time.perf_counter() - start:.0f} s).")
        path.with_suffix(".partial").unlink(missing_ok=True)  # only now: it was all of the run
    return model.eval(), history
