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

import glob
import hashlib
import json
import os
import pickle
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from tqdm.auto import tqdm

from ..data.paths import cache_dir, remove_stale_temporaries

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

    seconds: float = 0.0  # training wall time so far, summed over resumed parts (not logged)

    def last(self, name: str) -> float:
        """The most recent value of ``name``."""
        return self[name][-1]


class CheckpointError(RuntimeError):
    """A checkpoint file that cannot be used: damaged, or holding more than weights."""


class UnsafeCheckpointError(CheckpointError):
    """A checkpoint whose pickle holds objects other than tensors and plain containers.

    Such a file was not written by this course, and unpickling it could run code,
    so it is never loaded.
    """


STALE_AFTER_S = 3600.0  # a temp file this old belongs to a killed writer, not a live one


def save_checkpoint(path: str | Path, **state: Any) -> Path:
    """Write ``state`` with ``torch.save`` atomically: a temp file, synced, then a rename.

    A kernel that dies mid-write leaves the previous checkpoint intact, and a
    power loss cannot leave an empty file at ``path``. Temp files of writers that
    were killed (older than :data:`STALE_AFTER_S`) are removed first.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # the pattern of the temp names below: files of killed writers, never a live one's
    remove_stale_temporaries(path.parent, [f"{glob.escape(path.name)}*.tmp"], STALE_AFTER_S)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(state, f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)  # mkstemp makes the file private; a checkpoint is shareable
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    """Read a checkpoint written by :func:`save_checkpoint` (a dict of state).

    Loads with ``weights_only=True``: tensors and plain containers only, so a
    file that someone crafted cannot run code. Raises :class:`UnsafeCheckpointError`
    for a file holding anything else and :class:`CheckpointError` for a damaged
    one (truncated, empty, not a checkpoint), both naming the file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as err:  # how the safe loader refuses a foreign object...
        reason = [line.strip() for line in str(err).splitlines() if "Unsupported" in line]
        if reason and "Unsupported operand" in reason[0]:  # ...or bytes that are no pickle
            raise CheckpointError(f"{path} is damaged (not a checkpoint: {reason[0]}). Delete "
                                  f"it, or rerun: the course's loaders move it aside.") from None
        raise UnsafeCheckpointError(
            f"{path} holds something other than tensors and plain data, so it was not loaded "
            f"(unpickling it could run code; nothing in it was run). The course never writes "
            f"such files: delete {path}, or get the checkpoint from a source you trust."
            + (f"\nThe safe loader said: {reason[0]}" if reason else "")
        ) from None
    except Exception as err:  # the parser's many ways of meeting a damaged file
        raise CheckpointError(
            f"{path} is damaged (truncated, empty or not a checkpoint: "
            f"{type(err).__name__}: {str(err)[:120]}). Delete it, or rerun: the course's "
            f"loaders move it aside and train afresh."
        ) from None


def config_key(config: Any) -> str:
    """A short hash of a stored ``config`` (a plain dict), naming a run in file names."""
    text = json.dumps(config, sort_keys=True, default=repr)
    return hashlib.sha1(text.encode()).hexdigest()[:8]


def kept_path(path: Path, config: Any) -> Path:
    """Where the run of ``config`` is kept when another run takes ``path``:
    ``<stem>.run-<config_key>.pt`` beside it."""
    return path.with_name(f"{path.stem}.run-{config_key(config)}{path.suffix}")


def _move_aside(path: Path, target: Path, why: str) -> None:
    """Rename ``path`` to ``target`` and say so; only warn if the folder is read-only."""
    try:
        os.replace(path, target)
        print(f"{path} {why}; moved it to {target}.")
    except OSError as err:
        warnings.warn(f"{path} {why}, and it could not be moved aside ({err})", stacklevel=3)


def _read_run(path: Path, device, movable: bool) -> dict | None:
    """The state stored at ``path``; None if there is none or it is damaged.

    A damaged file is moved aside to ``<name>.damaged`` when ``movable`` (a cache
    file, so the next run does not trip on it); a shipped one is only reported.
    An unsafe file raises :class:`UnsafeCheckpointError`: the user must see it.
    """
    if not path.is_file():
        return None
    try:
        return load_checkpoint(path, map_location=device)
    except UnsafeCheckpointError:
        raise
    except CheckpointError as err:
        if movable:
            _move_aside(path, path.with_name(path.name + ".damaged"), "is damaged")
        else:
            warnings.warn(f"{err} Not using it.", stacklevel=3)
        return None


def _save_or_warn(path: Path, **state: Any) -> bool:
    """:func:`save_checkpoint`, but a folder that cannot be written only warns (returns False)."""
    try:
        save_checkpoint(path, **state)
        return True
    except OSError as err:
        warnings.warn(f"could not save a checkpoint to {path} ({err}); training goes on "
                      "without one, so an interruption will not be resumable.", stacklevel=3)
        return False


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
    started = time.perf_counter() - history.seconds
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
        history.seconds = time.perf_counter() - started
        if checkpoint is not None and (done % checkpoint_every == 0 or done == steps):
            saved = _save_or_warn(
                Path(checkpoint),
                model=model.state_dict(),
                optimizer=optimizer.state_dict(),
                scheduler=None if scheduler is None else scheduler.state_dict(),
                history=dict(history),
                step=done,
                config=config,
                seconds=history.seconds,
            )
            checkpoint = checkpoint if saved else None  # warned once; train on without
    return history


def resume(
    path: str | Path,
    model: torch.nn.Module,
    optimizer: torch.optim.Optimizer,
    scheduler: Any = None,
    config: dict[str, Any] | None = None,
) -> tuple[int, History]:
    """Restore the state saved by :func:`fit`; return ``(step, history)`` to continue from.

    Returns ``(0, History())`` when there is no checkpoint of this ``config`` yet.
    A file at ``path`` from a run with another config is kept under
    :func:`kept_path` (and resumed from there when you return to that config);
    a damaged one is moved aside.
    """
    state = _claim(Path(path), config, next(model.parameters()).device)
    if state is None:
        return 0, History()
    model.load_state_dict(state["model"])
    optimizer.load_state_dict(state["optimizer"])
    if scheduler is not None and state.get("scheduler") is not None:
        scheduler.load_state_dict(state["scheduler"])
    return state["step"], _history(state)


def _history(state: dict) -> History:
    history = History(state["history"])
    history.seconds = float(state.get("seconds") or 0.0)
    return history


def _claim(path: Path, config: Any, device) -> dict | None:
    """The state of the run of ``config`` stored at ``path``, or None if there is none.

    Another run's file at ``path`` is renamed to its own :func:`kept_path`, so
    nothing trained is ever overwritten; a kept file of this run is moved back.
    """
    state = _read_run(path, device, movable=True)
    if state is not None and state.get("config") == config:
        return state
    if state is not None:
        _move_aside(path, kept_path(path, state.get("config")),
                    "belongs to a run with another configuration")
    kept = kept_path(path, config)
    state = _read_run(kept, device, movable=True)
    if state is None or state.get("config") != config:
        return None
    os.replace(kept, path)
    print(f"Found this configuration's earlier run at {kept}; moved it back to {path}.")
    return state


SHIPPED_DIR = Path(__file__).resolve().parents[2] / "checkpoints"  # beside the package


def checkpoint_paths(name: str) -> tuple[Path, Path]:
    """Where a notebook's run called ``name`` is saved, and where a shipped copy would be.

    Runs trained on your machine go to ``data/cache/checkpoints/<name>.pt``
    (git-ignored); checkpoints that come with the course are in
    ``checkpoints/<name>.pt``, made by the command documented in checkpoints/README.md.
    """
    return cache_dir() / "checkpoints" / f"{name}.pt", SHIPPED_DIR / f"{name}.pt"


def load_or_train(
    path: str | Path,
    model: torch.nn.Module,
    train: Callable[[], History],
    config: dict[str, Any],
    shipped: str | Path | None = None,
    partial: str | Path | None = None,
) -> History:
    """Load ``model`` from a checkpoint trained with ``config``, else train it and save to ``path``.

    ``shipped`` (a checkpoint that comes with the course) is tried first, then
    ``path``. ``train()`` trains ``model`` in place and returns its history. A
    file whose stored config differs (other sizes, other coefficients) is not
    loaded; at ``path`` it is kept under :func:`kept_path`. ``partial``, the
    resumable checkpoint ``train()`` writes, is deleted only once the trained
    model is safely saved. Prints which happened, so a class knows whether it waited.
    """
    device = next(model.parameters()).device
    path, source = Path(path), shipped
    state = None if shipped is None else _read_run(Path(shipped), device, movable=False)
    if state is not None and state.get("config") != config:
        print(f"{shipped} was trained with another configuration; not using it.")
        state = None
    if state is None:
        state, source = _claim(path, config, device), path
    if state is not None:
        model.load_state_dict(state["model"])
        print(f"Loaded a trained model from {source} (skip training).")
        return _history(state)
    history = train()
    if _save_or_warn(path, model=model.state_dict(), history=dict(history), config=config,
                     seconds=getattr(history, "seconds", 0.0)):
        print(f"Trained and saved to {path}.")
        if partial is not None:  # only now: until the save, it is all there is of the run
            Path(partial).unlink(missing_ok=True)
    return history
