"""What every checker shares: the error it raises, a test case, the comparison (values, and
gradients where the lesson needs them), :func:`diagnose`, which names a known mistake, and
:func:`exercise`, which lets a notebook run on past an exercise not yet done."""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch

Diagnosis = tuple[str, Callable]  # (the mistake in plain words, a function that makes it)


class ExerciseError(AssertionError):
    """The learner's function disagrees with the reference; the message says where."""


class NotImplementedYet(ExerciseError):
    """The learner's function still raises ``NotImplementedError`` (the student stub)."""


def not_implemented(name: str) -> NotImplementedYet:
    return NotImplementedYet(
        f"{name} is not implemented yet: replace the `raise NotImplementedError` line with your "
        "code, run that cell, then run this check again.")


def exercise(reference: Callable, mistakes: Sequence[Diagnosis] = ()) -> Callable:
    """Make ``check(fn)`` return the function the rest of the notebook should use.

    ``fn`` when it is right; ``reference`` (the course's implementation, same
    signature) when ``fn`` is still the student stub, so that "Run All" reaches
    the end of the chapter; an :class:`ExerciseError` naming the mistake when
    ``fn`` is wrong. Raised from here, the error's traceback shows the learner's
    cell, not the checker's insides (nor the answer). ``mistakes``: the typical
    wrong versions the check names, ``(words, function)``, kept as ``check.mistakes``.
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
        run.mistakes = tuple(mistakes)
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


def _numbers(value) -> torch.Tensor | None:
    """``value`` as a float64 tensor (a tensor, or a tuple of numbers), else None."""
    if isinstance(value, torch.Tensor):
        return value.detach().double()
    try:
        return torch.as_tensor(value, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        return None


def diagnose(got, diagnoses: Sequence[Diagnosis], case: Case, atol: float = 1e-5) -> str:
    """Name the known mistake that gives ``got`` on ``case``: `` Likely cause: ...`` or ``''``.

    Each diagnosis is ``(words, variant)``: ``variant`` has the exercise's
    signature and makes one typical mistake. The variant closest to ``got``
    (within a tolerance ten times tighter than the check's) names the slip; on a
    tie the first listed wins, so list the slips that change only a gradient first.
    """
    got, matches = _numbers(got), []
    for order, (words, variant) in enumerate(diagnoses if got is not None else ()):
        try:
            wrong = _numbers(variant(*case.args, **case.kwargs))
        except Exception:  # a variant may fail where its mistake makes no sense
            continue
        if (wrong is not None and wrong.shape == got.shape
                and torch.isclose(got, wrong, atol=atol / 10, rtol=1e-5, equal_nan=True).all()):
            matches.append((float((got - wrong).abs().nan_to_num(0.0).sum()), order, words))
    return f" Likely cause: {min(matches)[2]}" if matches else ""


def gradient(fn: Callable, index: int) -> Callable:
    """``fn`` returning the gradient of its 0-d output with respect to positional argument
    ``index`` instead: zeros where no gradient reaches that argument (e.g. it was detached)."""
    def run(*args, **kwargs):
        x = args[index].detach().clone().requires_grad_()
        out = fn(*args[:index], x.clone(), *args[index + 1:], **kwargs)  # clone: in place is ok
        if not isinstance(out, torch.Tensor) or not out.requires_grad:
            return torch.zeros_like(x)
        grad = torch.autograd.grad(out.sum(), x, allow_unused=True)[0]
        return torch.zeros_like(x) if grad is None else grad

    run.__name__ = getattr(fn, "__name__", "your function")
    return run


def _disagreement(got, expected, atol: float, parts: Sequence[str] | None = None) -> str:
    """``'x, but the answer is y'``, naming the first element (and output, ``parts``) that
    differs."""
    got, expected = got.detach(), expected.detach()
    if expected.numel() == 1:
        return f"{float(got):.6g}, but the answer is {float(expected):.6g}"
    bad = ~torch.isclose(got.double(), expected.double(), atol=atol, rtol=1e-4)
    first = tuple(int(i) for i in bad.nonzero()[0])
    g, e = float(got[first]), float(expected[first])
    if parts:  # dim 0 holds several outputs, e.g. (mean, std)
        right = [p for p, b in zip(parts, bad) if not b.any()]
        also = f" (your {' and '.join(right)} {'is' if len(right) == 1 else 'are'} right)"
        return (f"a wrong {parts[first[0]]}: {parts[first[0]]}{list(first[1:])} is {g:.6g}, but "
                f"the answer is {e:.6g}{also if right else ''}")
    return (f"{g:.6g} at index {list(first)}, but the answer is {e:.6g} (the first of "
            f"{int(bad.sum())} wrong elements out of {bad.numel()})")


def _check_case(fn, reference, case: Case, name: str, atol: float,
                diagnoses: Sequence[Diagnosis], parts=None) -> None:
    """Raise :class:`ExerciseError` unless ``fn`` agrees with ``reference`` on ``case``."""
    expected = reference(*case.args, **case.kwargs)
    got = _call(fn, name, case)
    if not isinstance(got, torch.Tensor):
        raise ExerciseError(f"{name} returned {_describe(got)}; expected a torch tensor.")
    if got.shape != expected.shape:
        single = " (a single number)" if expected.ndim == 0 else ""
        raise ExerciseError(
            f"{name} returned shape {tuple(got.shape)} on {case.description}; expected shape "
            f"{tuple(expected.shape)}{single}.{diagnose(got, diagnoses, case, atol)}")
    if not torch.allclose(got.double(), expected.double(), atol=atol, rtol=1e-4):
        raise ExerciseError(
            f"{name} gave {_disagreement(got, expected, atol, parts)} on {case.description}."
            f"{diagnose(got, diagnoses, case, atol)}")


def _check_gradient(fn, reference, case: Case, name: str, atol: float,
                    diagnoses: Sequence[Diagnosis], grad: tuple[int, str]) -> None:
    """Raise :class:`ExerciseError` unless ``fn``'s gradient agrees with ``reference``'s."""
    index, label = grad
    expected = gradient(reference, index)(*case.args, **case.kwargs)
    got = _call(gradient(fn, index), name, case)
    if torch.allclose(got.double(), expected.double(), atol=atol, rtol=1e-4):
        return
    why = diagnose(got, [(w, gradient(v, index)) for w, v in diagnoses], case, atol)
    if not why and not got.any():
        why = (f" Likely cause: no gradient reaches {label}: did you .detach() them, or compute "
               "with .item(), numpy or under torch.no_grad()?")
    raise ExerciseError(
        f"{name} has the right value on {case.description}, but not the right gradient with "
        f"respect to {label}: it gave {_disagreement(got, expected, atol)}.{why}")


def compare(fn: Callable, reference: Callable, cases: list[Case], atol: float = 1e-5,
            diagnoses: Sequence[Diagnosis] = (), parts: Sequence[str] | None = None,
            grad: tuple[int, str] | None = None) -> bool:
    """Check ``fn`` against ``reference`` on every case; print a verdict or raise ExerciseError.

    ``diagnoses``: known mistakes, ``(words, variant)``, named when ``fn`` makes
    one (see :func:`diagnose`). ``parts``: names of the outputs stacked along dim 0
    (say which one is wrong). ``grad``: ``(index, label)`` of a positional argument
    whose gradient must agree too, checked once every value agrees.
    """
    name = getattr(fn, "__name__", "your function")
    for case in cases:
        _check_case(fn, reference, case, name, atol, diagnoses, parts)
    for case in cases if grad is not None else ():
        _check_gradient(fn, reference, case, name, atol, diagnoses, grad)
    what = " (values and gradients)" if grad is not None else ""
    print(f"Correct: {name} matches the reference on {len(cases)} test inputs{what}.")
    return True
