"""Checkpoint files: written atomically, read safely, recognised by their run's identity.

A file stores :func:`run_identity`, the fields that define its run; a file of another run is
never loaded in its place, nor overwritten (it is kept under :func:`kept_path`).
"""

from __future__ import annotations

import ast
import hashlib
import inspect
import json
import os
import pickle
import textwrap
import warnings
from dataclasses import MISSING, asdict, fields, is_dataclass
from pathlib import Path
from typing import Any

import torch

from ..data.paths import atomic_file, cache_dir, remove_stale_temporaries, temporaries_of


class CheckpointError(RuntimeError):
    """A checkpoint file that cannot be used: damaged, or holding more than weights."""


class UnsafeCheckpointError(CheckpointError):
    """A checkpoint holding objects other than tensors and plain containers: never loaded, as
    unpickling it could run code."""


STALE_AFTER_S = 3600.0  # a temp file this old belongs to a killed writer, not a live one
SHIPPED_DIR = Path(__file__).resolve().parents[2] / "checkpoints"  # beside the package


def save_checkpoint(path: str | Path, **state: Any) -> Path:
    """Write ``state`` with ``torch.save`` atomically (a temp file, synced, then a rename: a
    crash leaves the previous file intact), after removing the temp files of killed writers."""
    path = Path(path)
    remove_stale_temporaries(path.parent, [temporaries_of(path)], STALE_AFTER_S)
    with atomic_file(path) as f:
        torch.save(state, f)
    return path


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    """The dict :func:`save_checkpoint` wrote, read with ``weights_only=True`` (a crafted file
    cannot run code). Raises :class:`UnsafeCheckpointError` for a file holding more than tensors
    and plain containers, :class:`CheckpointError` for a damaged one, both naming the file."""
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


def run_identity(config: Any, always: tuple[str, ...] = (), **extra: Any) -> dict:
    """What a checkpoint stores to recognise its run: the fields of ``config`` (a dataclass)
    named in ``always``, every other field only where it differs from its default (inside
    nested dataclasses too), and the ``extra`` fields that also define the run.

    A new option with a default thus leaves every stored identity as it was. Changing a
    default not in ``always`` changes what the files mean: re-save the shipped ones
    (``python -m research.resave_checkpoints``).
    """
    return {**_changed(config, always), **extra}


def _changed(config: Any, always: tuple[str, ...] = ()) -> dict:
    out = {}
    for field in fields(config):
        value, base = getattr(config, field.name), field.default
        if field.default_factory is not MISSING:
            base = field.default_factory()
        if is_dataclass(value) and field.name not in always:  # a nested config: what changed
            value = _changed(value)
            if value or base is MISSING:
                out[field.name] = value
        elif field.name in always or base is MISSING or value != base:
            out[field.name] = asdict(value) if is_dataclass(value) else value
    return out


def code_of(function) -> str:
    """``function``'s code as a syntax tree, its docstring and comments aside; its ``repr``
    where Python cannot read its source."""
    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(function))).body[0]
    except (OSError, TypeError, SyntaxError, IndexError):
        return repr(function)
    body = tree.body
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
        tree.body = body[1:]
    return ast.dump(tree)


def step_identity(step, course_step) -> dict:
    """What an identity adds for the training ``step`` a run used: nothing for ``None`` or
    ``course_step``'s code (a notebook's unedited copy), else a hash of its code, so that a run
    of an edited step never loads, or replaces, the unedited run."""
    if step is None or code_of(step) == code_of(course_step):
        return {}
    return {"step": hashlib.sha256(code_of(step).encode()).hexdigest()[:16]}


def same_run(state: dict, identity: Any) -> bool:
    """Whether ``state`` was saved by the run of ``identity``."""
    return state.get("config") == identity


def kept_path(path: Path, config: Any) -> Path:
    """Where the run of ``config`` (a stored identity) is kept when another run takes ``path``:
    ``<stem>.run-<hash of config>.pt`` beside it."""
    key = hashlib.sha1(json.dumps(config, sort_keys=True, default=repr).encode()).hexdigest()[:8]
    return path.with_name(f"{path.stem}.run-{key}{path.suffix}")


def _move_aside(path: Path, target: Path, why: str) -> None:
    """Rename ``path`` to ``target`` and say so; only warn if the folder is read-only."""
    try:
        os.replace(path, target)
        print(f"{path} {why}; moved it to {target}.")
    except OSError as err:
        warnings.warn(f"{path} {why}, and it could not be moved aside ({err})", stacklevel=3)


def read_run(path: Path, device, movable: bool) -> dict | None:
    """The state stored at ``path``; None if there is none or it is damaged (then moved aside
    to ``<name>.damaged`` if ``movable``, a cache file, else only reported). An unsafe file
    raises :class:`UnsafeCheckpointError`: the user must see it."""
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


def save_or_warn(path: Path, **state: Any) -> bool:
    """:func:`save_checkpoint`, but a folder that cannot be written only warns (returns False)."""
    try:
        save_checkpoint(path, **state)
        return True
    except OSError as err:
        warnings.warn(f"could not save a checkpoint to {path} ({err}); training goes on "
                      "without one, so an interruption will not be resumable.", stacklevel=3)
        return False


def claim(path: Path, identity: Any, device) -> dict | None:
    """The state of the run of ``identity`` stored at ``path``, or None. Another run's file at
    ``path`` is renamed to its :func:`kept_path`; a kept file of this run is moved back."""
    state = read_run(path, device, movable=True)
    if state is not None and same_run(state, identity):
        return state
    if state is not None:
        _move_aside(path, kept_path(path, state.get("config")),
                    "belongs to a run with another configuration")
    kept = kept_path(path, identity)
    state = read_run(kept, device, movable=True)
    if state is None or not same_run(state, identity):
        return None
    os.replace(kept, path)
    print(f"Found this configuration's earlier run at {kept}; moved it back to {path}.")
    return state


def checkpoint_paths(name: str) -> tuple[Path, Path]:
    """Where a notebook's run called ``name`` is saved, ``data/cache/checkpoints/<name>.pt``
    (git-ignored), and where a shipped copy would be, ``checkpoints/<name>.pt``."""
    return cache_dir() / "checkpoints" / f"{name}.pt", SHIPPED_DIR / f"{name}.pt"
