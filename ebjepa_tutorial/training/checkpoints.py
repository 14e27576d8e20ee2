"""Checkpoint files: written atomically, read with ``weights_only=True``, recognised by their
run's identity; another run's file is never loaded in its place, nor overwritten."""

from __future__ import annotations

import ast
import dis
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

from ..data.paths import atomic_file, cache_dir

SHIPPED_DIR = Path(__file__).resolve().parents[2] / "checkpoints"  # beside the package


class CheckpointError(RuntimeError):
    """A checkpoint file that cannot be used: damaged, or holding more than weights."""


class UnsafeCheckpointError(CheckpointError):
    """A file holding objects other than tensors and plain containers: never unpickled."""


def checkpoint_paths(name: str) -> tuple[Path, Path]:
    """The run ``name``'s cache file ``<cache_dir()>/checkpoints/<name>.pt`` and shipped file
    ``checkpoints/<name>.pt``."""
    return cache_dir() / "checkpoints" / f"{name}.pt", SHIPPED_DIR / f"{name}.pt"


def save_checkpoint(path: str | Path, **state: Any) -> Path:
    """Write ``state`` with ``torch.save`` atomically (a crash leaves the previous file whole)."""
    path = Path(path)
    with atomic_file(path) as f:
        torch.save(state, f)
    return path


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    """The dict :func:`save_checkpoint` wrote. Raises :class:`UnsafeCheckpointError` for a file
    holding more than tensors and plain data, :class:`CheckpointError` for a damaged one."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no checkpoint at {path}")
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as err:  # how the safe loader refuses a foreign object...
        why = next((s.strip() for s in str(err).splitlines() if "Unsupported" in s), "")
        if "Unsupported operand" not in why:  # ...or meets bytes that are no pickle
            raise UnsafeCheckpointError(
                f"{path} holds something other than tensors and plain data, so it was not "
                f"loaded (unpickling it could run code). Delete it, or get the checkpoint "
                f"from a source you trust. {why}") from None
    except Exception as err:  # the parser's many ways of meeting a damaged file
        why = f"{type(err).__name__}: {str(err)[:120]}"
    raise CheckpointError(f"{path} is damaged (truncated, empty or not a checkpoint: {why}). "
                          "Delete it.")


def load_made_by(path: str | Path, made_by: str) -> dict:
    """:func:`load_checkpoint`, naming the command ``made_by`` if the file is missing or damaged."""
    try:
        return load_checkpoint(path)
    except (FileNotFoundError, CheckpointError) as error:
        raise type(error)(f"{error}\nIt is made by: {made_by}") from None


def run_identity(config: Any, always: tuple[str, ...] = (), **extra: Any) -> dict:
    """The fields of the dataclass ``config`` named in ``always``, every other only where it
    differs from its default (in nested dataclasses too), and ``extra``: so a new option with a
    default leaves every stored identity as it was."""
    out = {}
    for field in fields(config):
        value, base = getattr(config, field.name), field.default
        if field.default_factory is not MISSING:
            base = field.default_factory()
        if is_dataclass(value) and field.name not in always:  # a nested config: what changed
            value = run_identity(value)
            if value or base is MISSING:
                out[field.name] = value
        elif field.name in always or base is MISSING or value != base:
            out[field.name] = asdict(value) if is_dataclass(value) else value
    return {**out, **extra}


def code_of(function) -> str:
    """``function``'s syntax tree without docstring and comments (its ``repr`` if no source)."""
    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(function))).body[0]
    except (OSError, TypeError, SyntaxError, IndexError):
        return repr(function)
    body = tree.body
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
        tree.body = body[1:]
    return ast.dump(tree)


CHECKED = "exercise_check"  # the course's checkers mark a learner's function "passed" or "failed"


def _digest(function) -> str:
    return hashlib.sha256(code_of(function).encode()).hexdigest()[:16]


def nested_codes(function) -> list:
    """``function``'s code object and those of the functions and lambdas inside it."""
    codes, found = [function.__code__], []
    while codes:
        found.append(codes.pop())
        codes += [c for c in found[-1].co_consts if inspect.iscode(c)]
    return found


def _unchecked_calls(function, seen: set) -> dict:
    """``{name: hash}`` of the notebook's own functions (``__main__``) that ``function`` reads,
    and of theirs, save those that passed a check; one that failed it is refused."""
    if not inspect.isfunction(function):  # a partial or a callable object: its code is hidden
        return {}
    names, found = {i.argval for code in nested_codes(function)
                    for i in dis.get_instructions(code) if i.opname == "LOAD_GLOBAL"}, {}
    for name in sorted(names):
        called = function.__globals__.get(name)
        verdict = getattr(called, CHECKED, None)
        if (not inspect.isfunction(called) or called.__module__ != "__main__" or called in seen
                or verdict == "passed"):
            continue
        if verdict == "failed":
            raise ValueError(f"{name} failed its exercise's check, so no run trains with it: "
                             "correct it and rerun its check cell (a body of `raise "
                             "NotImplementedError` hands over the course's)")
        seen.add(called)
        found |= {name: _digest(called), **_unchecked_calls(called, seen)}
    return found


def step_identity(step, course_step) -> dict:
    """``{}`` for ``step`` None or a copy of ``course_step``'s code, else ``{"step": hash}``;
    and ``{"calls": ...}`` (:func:`_unchecked_calls`): an unchecked edit is a run of its own."""
    if step is None:
        return {}
    calls = _unchecked_calls(step, set())
    edited = {} if code_of(step) == code_of(course_step) else {"step": _digest(step)}
    return {**edited, **({"calls": calls} if calls else {})}


def kept_path(path: Path, config: Any) -> Path:
    """Where the run ``config`` is kept when another takes ``path``: ``<stem>.run-<hash>.pt``."""
    key = hashlib.sha1(json.dumps(config, sort_keys=True, default=repr).encode()).hexdigest()[:8]
    return path.with_name(f"{path.stem}.run-{key}{path.suffix}")


def _move(path: Path, target: Path, why: str) -> None:
    """Rename ``path`` to ``target`` and say so; only warn if the folder is read-only."""
    try:
        os.replace(path, target)
        print(f"{path} {why}; moved it to {target}.")
    except OSError as err:
        warnings.warn(f"{path} {why}, and it could not be moved aside ({err})", stacklevel=3)


def read_run(path: Path, device, movable: bool = True) -> dict | None:
    """The state at ``path``; None if none or damaged (moved to ``<name>.damaged`` if movable)."""
    try:
        return load_checkpoint(path, map_location=device) if path.is_file() else None
    except UnsafeCheckpointError:
        raise
    except CheckpointError as err:
        if movable:
            _move(path, path.with_name(path.name + ".damaged"), "is damaged")
        else:  # a shipped file: the repository has the good one
            warnings.warn(f"{err} Not using it; restore it with `git checkout -- {path}`.",
                          stacklevel=3)
        return None


def find_run(path: Path, identity: Any, device, shipped: Path | None = None):
    """``(state, file)`` of the run ``identity``, from ``shipped`` (only read) or ``path``, else
    None. Another run's file at ``path`` moves to its :func:`kept_path`; this run's moves back."""
    state = None if shipped is None else read_run(Path(shipped), device, movable=False)
    if state is not None and state.get("config") == identity:
        return state, shipped
    if state is not None:
        print(f"{shipped} was trained with another configuration; not using it.")
    state = read_run(path, device)
    if state is not None and state.get("config") == identity:
        return state, path
    if state is not None:
        _move(path, kept_path(path, state.get("config")), "belongs to another configuration")
    kept = kept_path(path, identity)
    state = read_run(kept, device)
    if state is None or state.get("config") != identity:
        return None
    os.replace(kept, path)
    print(f"Found this configuration's earlier run at {kept}; moved it back to {path}.")
    return state, path


def save_or_warn(path: Path, final: bool = False, **state: Any) -> bool:
    """:func:`save_checkpoint`, but a folder that cannot be written only warns (returns False);
    ``final``: the trained model, else a resumable partial state."""
    try:
        save_checkpoint(path, **state)
        return True
    except OSError as err:
        lost = ("the trained model lives only in this session, and the next run trains it again"
                if final else "training goes on, but an interruption will not be resumable")
        warnings.warn(f"could not save to {path} ({err}): {lost}. Set EBJEPA_CACHE to a "
                      "folder you can write to.", stacklevel=3)
        return False
