"""What every checker shares: the error it raises, a test case, the comparison, and
:func:`exercise`, which lets a notebook run on past an exercise not yet done."""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field

import torch


class ExerciseError(AssertionError):
    """The learner's function disagrees with the reference; the message says where."""


class NotImplementedYet(ExerciseError):
    """The learner's function still raises ``NotImplementedError`` (the student stub)."""


def not_implemented(name: str) -> NotImplementedYet:
    return NotImplementedYet(
        f"{name} is not implemented yet: replace the `raise NotImplementedError` line with your "
        "code, run that cell, then run this check again.")


def exercise(reference: Callable) -> Callable:
    """Make ``check(fn)`` return the function the rest of the notebook should use.

    ``fn`` when it is right; ``reference`` (the course's implementation, same
    signature) when ``fn`` is still the student stub, so that "Run All" reaches
    the end of the chapter; an :class:`ExerciseError` naming the mistake when
    ``fn`` is wrong. Raised from here, the error's traceback shows the learner's
    cell, not the checker's insides (nor the answer).
    """
    def decorate(check: Callable) -> Callable:
        @functools.wraps(check)
        def run(fn: Callable, *args, **kwargs) -> Callable:
            if fn is reference:  # this cell ran again after handing the course's one over
                print("This is still the course's implementation: run the cell with your "
                      "function first, then this check.")
                return reference
            try:
                check(fn, *args, **kwargs)
            except NotImplementedYet:
                print(f"{getattr(fn, '__name__', 'your function')} is not implemented yet: the "
                      "rest of this notebook uses the course's implementation. Write yours in "
                      "the cell above, then run it and this check again.")
                return reference
            except ExerciseError as error:
                raise ExerciseError(str(error)) from None
            return fn
        run.__annotations__ = {"fn": "Callable", "return": "Callable"}  # not check's bool
        run.reference = reference
        return run
    return decorate


@dataclass
class Case:
    """One test input: a description for the learner and the arguments to call with."""

    description: str
    args: tuple
    kwargs: dict = field(default_factory=dict)


def _describe(value) -> str:
    if isinstance(value, torch.Tensor):
        return f"a tensor of shape {tuple(value.shape)}"
    return f"a {type(value).__name__}"


def _call(fn: Callable, name: str, case: Case):
    try:
        return fn(*case.args, **case.kwargs)
    except NotImplementedError:
        raise not_implemented(name) from None
    except Exception as err:
        message = f"{name} raised {type(err).__name__}: {err} on {case.description}."
        raise ExerciseError(message) from err


def compare(fn: Callable, reference: Callable, cases: list[Case], atol: float = 1e-5) -> bool:
    """Check ``fn`` against ``reference`` on every case; print a verdict or raise ExerciseError."""
    name = getattr(fn, "__name__", "your function")
    for case in cases:
        expected = reference(*case.args, **case.kwargs)
        got = _call(fn, name, case)
        if not isinstance(got, torch.Tensor):
            raise ExerciseError(f"{name} returned {_describe(got)}; expected a torch tensor.")
        if got.shape != expected.shape:
            single = " (a single number)" if expected.ndim == 0 else ""
            raise ExerciseError(
                f"{name} returned shape {tuple(got.shape)} on {case.description}; "
                f"expected shape {tuple(expected.shape)}{single}."
            )
        if not torch.allclose(got.double(), expected.double(), atol=atol, rtol=1e-4):
            raise ExerciseError(
                f"{name} gave {got.detach().flatten()[:4].tolist()} on {case.description}, "
                f"but the answer is {expected.detach().flatten()[:4].tolist()}."
            )
    print(f"Correct: {name} matches the reference on {len(cases)} test inputs.")
    return True


