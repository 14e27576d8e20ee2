"""Checkpoint files: written atomically, read safely, recognised by their run's identity.

- :func:`save_checkpoint` writes a temp file, syncs it and renames it, so a
  crash leaves the previous file intact; :func:`load_checkpoint` reads with
  ``weights_only=True``, so a crafted file cannot run code.
- :func:`run_identity` is what a file stores to say which run made it (the
  fields that define the run); a file of another run is never loaded in its
  place, nor overwritten (it is kept under :func:`kept_path`).
- :func:`checkpoint_paths`: where a notebook's run is cached, and where a
  shipped copy would be.
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
from dataclasses import MISSING, Field, asdict, fields, is_dataclass
from pathlib import Path
from typing import Any

import torch

from ..data.paths import atomic_file, cache_dir, remove_stale_temporaries, temporaries_of


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
    remove_stale_temporaries(path.parent, [temporaries_of(path)], STALE_AFTER_S)
    with atomic_file(path) as f:
        torch.save(state, f)
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


def float16_state(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    """``module``'s state on the CPU with floating tensors in float16: half the file.

    For files the course ships: ``load_state_dict`` casts them back to the
    model's float32, and the rounding (about 3 significant digits) barely moves
    a probe. Integer buffers (batch norm's counters) are kept as they are.
    """
    return {name: (value.half() if value.is_floating_point() else value).cpu()
            for name, value in module.state_dict().items()}


def run_identity(config: Any, always: tuple[str, ...] = (), **extra: Any) -> dict:
    """What a checkpoint stores to recognise its run: the fields of ``config`` (a dataclass)
    named in ``always``, every other field only where it differs from its default (inside
    nested dataclasses too), and the ``extra`` fields that also define the run.

    Two files hold the same run exactly when their identities are equal. A new option with
    a default leaves every stored identity as it was; a run that sets it is another run.
    Changing a default that is not in ``always`` changes what the files mean: re-save the
    shipped ones (``python -m research.resave_checkpoints``, checkpoints/README.md).
    """
    return {**_changed(config, always), **extra}


def _changed(config: Any, always: tuple[str, ...] = ()) -> dict:
    out = {}
    for field in fields(config):
        value, base = getattr(config, field.name), _default(field)
        if is_dataclass(value) and field.name not in always:  # a nested config: what changed
            value = _changed(value)
            if value or base is MISSING:
                out[field.name] = value
        elif field.name in always or base is MISSING or value != base:
            out[field.name] = asdict(value) if is_dataclass(value) else value
    return out


def _default(field: Field) -> Any:
    if field.default is not MISSING:
        return field.default
    return field.default_factory() if field.default_factory is not MISSING else MISSING


def code_of(function) -> str:
    """``function``'s code as a syntax tree, its docstring and comments aside (a notebook's
    copy of a step explains in markdown what the package's says in its docstring); its
    ``repr``, never another function's code, where Python cannot read its source."""
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
    for ``course_step`` in code (a notebook's unedited copy of it), else a hash of the step's
    code. A run with an edited step (a learner's cell) is thus a run of its own: it never
    loads, or replaces, the shipped or cached unedited run, and is cached and resumed as itself.
    """
    if step is None or code_of(step) == code_of(course_step):
        return {}
    return {"step": hashlib.sha256(code_of(step).encode()).hexdigest()[:16]}


def same_run(state: dict, identity: Any) -> bool:
    """Whether ``state`` was saved by the run of ``identity``."""
    return state.get("config") == identity


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


def read_run(path: Path, device, movable: bool) -> dict | None:
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
    """The state of the run of ``identity`` stored at ``path``, or None if there is none.

    Another run's file at ``path`` is renamed to its own :func:`kept_path`, so
    nothing trained is ever overwritten; a kept file of this run is moved back.
    """
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


SHIPPED_DIR = Path(__file__).resolve().parents[2] / "checkpoints"  # beside the package


def checkpoint_paths(name: str) -> tuple[Path, Path]:
    """Where a notebook's run called ``name`` is saved, and where a shipped copy would be.

    Runs trained on your machine go to ``data/cache/checkpoints/<name>.pt``
    (git-ignored); checkpoints that come with the course are in
    ``checkpoints/<name>.pt``, made by the command documented in checkpoints/README.md.
    """
    return cache_dir() / "checkpoints" / f"{name}.pt", SHIPPED_DIR / f"{name}.pt"
