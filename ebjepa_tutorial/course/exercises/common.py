"""What every checker shares: the graded hints (:func:`hint`), :class:`Comparison` of a
learner's function with the course's, which names a wrong answer in words, and :func:`exercise`,
which lets a notebook run on past an exercise not yet done."""

from __future__ import annotations

import inspect
import itertools
import sys
import textwrap
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch
import yaml

Diagnosis = tuple[str, Callable]  # (the mistake in plain words, a function that makes it)
TEXTS = yaml.safe_load(Path(__file__).with_name("hints.yaml").read_text(encoding="utf-8"))
HINTS = {name: tuple(texts["hints"]) for name, texts in TEXTS.items()}
LEVELS = ("the idea", "the formula", "an outline of the code")
_shown: dict[str, int] = {}  # exercise -> the highest hint level shown in this session


class ExerciseError(AssertionError):
    """The learner's function disagrees with the reference; the message says where."""


class NotImplementedYet(ExerciseError):
    """The learner's function still raises ``NotImplementedError`` (the student stub)."""


def slips(exercise: str, **variants) -> list[Diagnosis]:
    """``(words, variant)`` for each typical mistake of ``exercise``, in the order given (on a
    tie the first wins: list the slips that change only a gradient first). A variant has the
    exercise's signature and makes the mistake (a tuple: several ways to make it); its words
    are hints.yaml's under the same key."""
    words = TEXTS[exercise]["slips"]
    return [(words[key], f) for key, fs in variants.items()
            for f in (fs if isinstance(fs, tuple) else (fs,))]


# ------------------------------------------------------------------------------ graded hints

def hint(name, level: int | None = None) -> None:
    """Print hint ``level`` of the exercise ``name`` (its function's name, or the function):
    1 the idea, 2 the formula and the shapes, 3 an outline of the code; by default the next
    level not shown yet."""
    name = getattr(name, "__name__", name)
    if name not in HINTS:
        print(f"There is no exercise called {name!r}; the exercises with hints are "
              f"{', '.join(sorted(HINTS))}.")
        return
    level = min(_shown.get(name, 0) + 1, len(LEVELS)) if level is None else level
    if level not in range(1, len(LEVELS) + 1):
        raise ValueError(f"level is 1 (the idea), 2 (the formula) or 3 (an outline of the "
                         f"code), not {level!r}")
    _shown[name] = max(_shown.get(name, 0), level)
    print(_hint_text(name, level))


def _hint_text(name: str, level: int) -> str:
    body = HINTS[name][level - 1]  # the outline keeps its lines; the words are wrapped
    body = body if level == len(LEVELS) else textwrap.fill(body, 88)
    text = f"Hint {level} of {len(LEVELS)} for {name}, {LEVELS[level - 1]}:\n{body}"
    if level < len(LEVELS):
        text += f"\n(exercises.hint({name!r}) again gives {LEVELS[level]}.)"
    return text


def _offer(name: str) -> str:
    """What a failed check adds: the next hint without code, then how to ask for the outline."""
    level = _shown.get(name, 0) + 1
    if level < len(LEVELS):
        _shown[name] = level
        return "\n\n" + _hint_text(name, level)
    return f"\n\nStill stuck? exercises.hint({name!r}, level=3) shows an outline of the code."


# --------------------------------------------------------------- watching the learner's call

_NOT_THE_LEARNER = (str(Path(torch.__file__).parent), str(Path(__file__).parent))
_CUTS = {"detach": ".detach()", "detach_": ".detach_()", "numpy": ".numpy()",  # C methods
         "item": ".item()", "tolist": ".tolist()"}
_GRAD_OFF = {"no_grad.__enter__": "torch.no_grad()",  # Python functions, by qualified name
             "inference_mode.__enter__": "torch.inference_mode()",
             "set_grad_enabled.__init__": "torch.set_grad_enabled(False)"}
_DETACHES = "detaches a tensor from the autograd graph"
_NUMPY = "leaves torch for numpy, which has no gradients"
_WHAT_CUTS = {".detach()": _DETACHES, ".detach_()": _DETACHES, ".numpy()": _NUMPY, "numpy": _NUMPY,
              ".item()": "turns a tensor into a Python number",
              ".tolist()": "turns a tensor into Python numbers",
              **{word: "switches gradients off" for word in _GRAD_OFF.values()}}


def _learners(frame) -> bool:
    return frame is not None and not frame.f_code.co_filename.startswith(_NOT_THE_LEARNER)


class _Spy:
    """Watches one call of a learner's function (``sys.setprofile``): what in it can cut a
    gradient (``cuts``), and which of the course's own answers (``_Spy.answers``, code ->
    name, set by :func:`exercise`) it calls (``_Spy.called``, kept for the whole check)."""

    answers: dict = {}
    called: dict = {}  # used as an ordered set, as is cuts

    def __enter__(self) -> _Spy:
        self.cuts, self._previous = {}, sys.getprofile()
        sys.setprofile(self._event)
        return self

    def __exit__(self, *exc) -> None:
        sys.setprofile(self._previous)

    def _event(self, frame, event, arg) -> None:
        if event == "c_call":
            if (word := _CUTS.get(getattr(arg, "__name__", None))) and _learners(frame):
                self.cuts.setdefault(word)
        elif event == "call":
            code, learner = frame.f_code, _learners(frame.f_back)
            qualname = getattr(code, "co_qualname", code.co_name)
            # a decorator's no_grad is entered from torch's own code: count it wherever it is
            if qualname in _GRAD_OFF and (learner or code.co_name == "__enter__"):
                self.cuts.setdefault(_GRAD_OFF[qualname])
            elif code.co_name == "__array__" and learner:
                self.cuts.setdefault("numpy")
            elif code in _Spy.answers:
                _Spy.called.setdefault(_Spy.answers[code])


@dataclass
class Case:
    """One test input. ``sizes``: named sizes (``{"K": 3}``) the factor detector tries besides
    the shapes' (``dims``); ``atol``: a looser tolerance where float32 cannot do better, and
    ``why_loose`` the note printed when an answer needed it (``{diff}``: the largest gap)."""

    description: str
    args: tuple
    kwargs: dict = field(default_factory=dict)
    sizes: dict = field(default_factory=dict)
    atol: float | None = None
    why_loose: str = ""


def _run(fn: Callable, name: str, case: Case, labels: Sequence[str] = ()):
    """``fn`` on its own copy of ``case``'s inputs -> ``(output, spy)``; raises
    :class:`ExerciseError` if it crashes or changes an input in place."""
    def copy(v):
        return v.clone() if isinstance(v, torch.Tensor) else v
    args, kwargs = [copy(v) for v in case.args], {k: copy(v) for k, v in case.kwargs.items()}
    with _Spy() as spy:
        try:
            out = fn(*args, **kwargs)
        except NotImplementedError:
            raise NotImplementedYet(f"{name} is not implemented yet") from None
        except Exception as err:
            numpy = (" numpy cannot carry a gradient, so a loss computed through it cannot "
                     "train anything: compute with torch operations on the tensors you are "
                     "given.") if "numpy" in str(err) and "grad" in str(err) else ""
            raise ExerciseError(f"{name} raised {type(err).__name__}: {err} on "
                                f"{case.description}.{numpy}") from err
    for where, after in [*enumerate(args), *kwargs.items()]:
        before = case.kwargs[where] if isinstance(where, str) else case.args[where]
        if isinstance(before, torch.Tensor) and (after.shape != before.shape
                                                 or not torch.equal(after, before)):
            label = where if isinstance(where, str) else (
                labels[where] if where < len(labels) else f"argument {where + 1}")
            raise ExerciseError(
                f"{name} changed its input {label} in place on {case.description}: after the "
                f"call, {label} no longer holds what was passed in. Look for an operator such "
                "as -=, += or *=, a method whose name ends in an underscore (sub_, clamp_, ...) "
                f"or an assignment into part of {label}, and compute on a new tensor instead: "
                "in training the same tensor is still needed by the rest of the loss and by "
                "the backward pass.")
    return out, spy


# -------------------------------------------------------------- naming what went wrong

def _describe(value) -> str:
    if isinstance(value, torch.Tensor):
        return f"a tensor of shape {tuple(value.shape)}"
    if isinstance(value, (tuple, list)):
        return f"a {type(value).__name__} of {len(value)}"
    return f"a {type(value).__module__}.{type(value).__name__}".replace("builtins.", "Python ")


def _type_problem(got, name: str, case: Case, label: str = "") -> str | None:
    """Words for a non-tensor ``got`` (a Python number, numpy, a tuple, None), else None."""
    if isinstance(got, torch.Tensor):
        return None
    yours = f"{name} returned {label + ' as ' if label else ''}"
    where = f"on {case.description}, where a torch tensor is expected"
    if got is None:
        return f"{yours}None {where}: did you forget the return statement?"
    if type(got).__module__.split(".")[0] == "numpy":
        return (f"{yours}a numpy {type(got).__name__} {where}. numpy carries no gradient, so "
                "training could not use it: compute with torch operations on the tensors "
                "you are given.")
    if isinstance(got, (bool, int, float)):
        return (f"{yours}a Python {type(got).__name__} ({got:.6g}) {where}. A Python number "
                "carries no gradient, so training could not use it: look for .item(), "
                "float() or the math module, and keep the result a tensor (a 0-d tensor for "
                "a single number).")
    if isinstance(got, (tuple, list)):
        return (f"{yours}a {type(got).__name__} of {len(got)} {where}. Did you return "
                "several things (say, a loss and its parts)? Return the one tensor asked for.")
    return f"{yours}{_describe(got)} {where}."


def _numbers(value) -> torch.Tensor | None:
    """``value`` as a float64 tensor (a tuple of tensors flattened and joined), else None."""
    if isinstance(value, torch.Tensor):
        return value.detach().double()
    if isinstance(value, (tuple, list)) and value and all(
            isinstance(v, torch.Tensor) for v in value):
        return torch.cat([v.detach().double().flatten() for v in value])
    try:
        return torch.as_tensor(value, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        return None


def diagnose(got, diagnoses: Sequence[Diagnosis], case: Case, atol: float = 1e-5) -> str:
    """`` Likely cause: <words>`` of the variant closest to ``got`` on ``case`` (within a
    tolerance ten times tighter than the check's; a tie goes to the first), else ``''``."""
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


def _factors(sizes: dict) -> list[tuple[str, float, str]]:
    """``(words, value, what to look at)`` for each factor a value can be off by: for each
    named size n, n, n - 1, n/(n - 1) and its square (an unbiased estimate divided by n,
    then squared); then 2. A named size comes first: its advice is the more telling."""
    out = []
    for k, n in sizes.items():
        if n >= 2:
            out.append((k, n, f"a sum over {k} where a mean belongs (or a mean where a sum "
                              "belongs), or a division by the wrong count"))
        if n > 2:
            ratio = (f"a division by {k} where {k} - 1 belongs (the unbiased estimate divides "
                     f"by {k} - 1), or the reverse")
            out += [(f"{k} - 1", n - 1, f"a division by {k} - 1 where {k} belongs or the "
                                        "reverse, or a count that is off"),
                    (f"{k}/({k} - 1)", n / (n - 1), ratio),
                    (f"({k}/({k} - 1))²", (n / (n - 1)) ** 2, ratio)]
    return out + [("2", 2, "a sum of two things where their average belongs (or the reverse), "
                           "or a factor 2 missing or repeated")]


def _factor_off(got, expected, sizes: dict, advice: dict) -> tuple[str, str, str] | None:
    """The cause when ``got`` is ``expected`` times one of :func:`_factors` (``advice``, by the
    factor's words, replaces the general one), else None."""
    big = expected.abs() > 1e-8
    if not big.any() or not torch.isfinite(got).all():
        return None
    ratio = got[big] / expected[big]
    r = float(ratio.median())
    if r <= 0 or not torch.allclose(ratio, torch.full_like(ratio, r), rtol=1e-4, atol=0):
        return None
    for words, value, look in _factors(sizes):
        for direction, target in (("too large", value), ("too small", 1 / value)):
            if abs(r - target) < 1e-4 * target:
                shown = "" if words == "2" else f" = {value:.4g}"
                return (f"is {direction} by a factor of {words}{shown}", "",
                        "The formula is right up to a constant; look at what you divide by or "
                        f"average over: {advice.get(words, look)}")
    return None


def _transposed(got, expected, atol: float) -> bool:
    """Whether ``got`` is ``expected`` with its axes in another order."""
    if got.ndim != expected.ndim or got.ndim < 2 or got.shape == expected.shape:
        return False
    return any(tuple(expected.shape[i] for i in order) == tuple(got.shape) and torch.allclose(
        expected.permute(order).double(), got.double(), atol=atol, rtol=1e-4)
        for order in itertools.permutations(range(expected.ndim)))


def _shape_problem(got, expected, name: str, case: Case, label: str, atol: float) -> str:
    yours = f"your {label}" if label else "your output"
    if _transposed(got, expected, atol):
        return (f"{name} put the right numbers in the wrong layout on {case.description}: "
                f"{yours} has shape {tuple(got.shape)} where {tuple(expected.shape)} is "
                "expected, and holds the answer with its axes in another order. Look at the "
                "order of the axes where you build it: stacking along another dim, a transpose, "
                "or indexing that moved an axis.")
    single = " (a single number)" if expected.ndim == 0 else ""
    return (f"{name} returned shape {tuple(got.shape)} on {case.description}"
            f"{' for ' + yours if label else ''}; expected shape {tuple(expected.shape)}"
            f"{single}.")


def _disagreement(got, expected, atol: float) -> str:
    """``'x, but the answer is y'``, naming the first element that differs."""
    got, expected = got.detach(), expected.detach()
    if expected.numel() == 1:
        return f"{float(got):.6g}, but the answer is {float(expected):.6g}"
    bad = ~torch.isclose(got.double(), expected.double(), atol=atol, rtol=1e-4)
    first = tuple(int(i) for i in bad.nonzero()[0])
    g, e = float(got[first]), float(expected[first])
    return (f"{g:.6g} at index {list(first)}, but the answer is {e:.6g} (the first of "
            f"{int(bad.sum())} wrong elements out of {bad.numel()})")


def gradient(fn: Callable, index: int) -> Callable:
    """``fn`` returning the gradient of its output's sum with respect to positional argument
    ``index`` instead (zeros where none reaches it); ``.connected``, after a call: whether the
    output was connected to the autograd graph at all."""
    def run(*args, **kwargs):
        x = args[index].detach().clone().requires_grad_()
        out = fn(*args[:index], x.clone(), *args[index + 1:], **kwargs)  # clone: in place is ok
        run.connected = isinstance(out, torch.Tensor) and out.requires_grad
        grad = torch.autograd.grad(out.sum(), x, allow_unused=True)[0] if run.connected else None
        return torch.zeros_like(x) if grad is None else grad

    run.__name__ = getattr(fn, "__name__", "your function")
    run.connected = True
    return run


def _and(words: Sequence[str]) -> str:
    return words[0] if len(words) == 1 else ", ".join(words[:-1]) + " and " + words[-1]


def _no_flow(name: str, case: Case, label: str, cuts: Sequence[str], connected: bool,
             why: str = "") -> ExerciseError:
    """The error for a right value whose gradient does not reach ``label``: what cut it."""
    if cuts:
        look = (f"Found in your function: {_and([f'{c} ({_WHAT_CUTS[c]})' for c in cuts])}. "
                "Keep every step from the inputs to the output in torch, with no .detach(), "
                ".item(), numpy or torch.no_grad() on the way.")
    elif not connected:
        look = ("Its output is not connected to the inputs in autograd: look for .detach(), "
                ".item(), a detour through numpy, or torch.no_grad().")
    else:
        look = (f"The output depends on the other inputs but not on {label}: look for a "
                f".detach() on {label}, or on a part of it.")
    return ExerciseError(
        f"{name} has the right value on {case.description}, but the gradient does not flow to "
        f"{label}, so training could not change it through this term. {look}{why}")


# ---------------------------------------------------------------------- the comparison

@dataclass
class Comparison:
    """Checks a learner's function against ``reference`` on ``cases()``: every value, then the
    gradient with respect to each ``grad`` ``(argument index, its label)``; prints a verdict or
    raises :class:`ExerciseError`. A wrong answer is named by one of the exercise's own
    ``diagnoses`` (:func:`diagnose`), else by a general mistake: NaN, a sign flip, a factor off
    (the sizes of the axes ``dims`` names, ``{index: "BD"}``, ``_`` skipping one; ``factors``:
    advice by the factor's words), the wrong axis (``swap``: ``(index, a, b, what it means,
    what to look at)``, axes ``a`` and ``b`` of one argument exchanged), a transposed result,
    a non-tensor. ``parts``: the outputs' names when a tuple is returned; ``labels``: the
    arguments' (default: the reference's parameters)."""

    reference: Callable
    cases: Callable[[], list[Case]]
    diagnoses: Sequence[Diagnosis] = ()
    atol: float = 1e-5
    parts: Sequence[str] | None = None
    grad: Sequence[tuple[int, str]] = ()
    labels: Sequence[str] | None = None
    dims: dict = field(default_factory=dict)
    swap: tuple | None = None
    factors: dict = field(default_factory=dict)

    def __post_init__(self):
        self.labels = self.labels or list(inspect.signature(self.reference).parameters)

    def __call__(self, fn: Callable) -> None:
        name, cases = getattr(fn, "__name__", "your function"), self.cases()
        notes = [self._values(fn, name, case) for case in cases]
        for case in cases:
            for index, label in self.grad:
                self._gradient(fn, name, case, index, label)
        labels = [label for _, label in self.grad]
        what = f" (values, and gradients with respect to {_and(labels)})" if labels else ""
        print(f"Correct: {name} matches the reference on {len(cases)} test inputs{what}.")
        for note in dict.fromkeys(n for n in notes if n):
            print(note)

    def _values(self, fn: Callable, name: str, case: Case) -> str:
        """Raise unless ``fn`` agrees with the reference on ``case``; returns the case's note
        when it agreed only within the case's looser tolerance."""
        expected = self.reference(*case.args, **case.kwargs)
        got, _ = _run(fn, name, case, self.labels)
        atol, parts, note = self.atol if case.atol is None else case.atol, self.parts, ""
        if parts and (not isinstance(got, (tuple, list)) or len(got) != len(parts)):
            raise ExerciseError(
                f"{name} returned {_describe(got)} on {case.description}; it must return a pair "
                f"({', '.join(parts)}), {len(parts)} tensors.")
        for label, g, e in zip(parts, got, expected) if parts else [("", got, expected)]:
            if (problem := _type_problem(g, name, case, label)):
                raise ExerciseError(problem)
            if g.shape != e.shape:
                raise ExerciseError(_shape_problem(g, e, name, case, label, atol)
                                    + diagnose(got, self.diagnoses, case, atol))
            g, e = g.double(), e.double()
            if not torch.allclose(g, e, atol=atol, rtol=1e-4):
                raise ExerciseError(self._value_problem(name, got, g, e, case, label, atol))
            if not torch.allclose(g, e, atol=self.atol, rtol=1e-4):
                note = case.why_loose.format(diff=float((g - e).abs().max()))
        return note

    def _value_problem(self, name, got, g, e, case: Case, label: str, atol: float) -> str:
        """Words for a wrong output ``g`` (a part of ``got``; ``e`` the answer): one of the
        exercise's own mistakes, else a general one, else only the numbers."""
        numbers = f"{'your ' + label + ' ' if label else ''}{_disagreement(g, e, atol)}"
        why = diagnose(got, self.diagnoses, case, atol)
        if why or not (general := self._general_cause(g, e, case)):
            return f"{name} gave {numbers} on {case.description}.{why}"
        found, meaning, look = general
        where = f" (your {label})" if label else ""
        return f"{name} {found} on {case.description}{where}{meaning}. {look}. Yours: {numbers}."

    def _general_cause(self, got, expected, case: Case) -> tuple[str, str, str] | None:
        """``(what was found, ': what it means' or '', what to look at)``, or None."""
        if torch.isfinite(expected).all() and not torch.isfinite(got).all():
            return ("returned NaN or infinity", "",
                    "Look for 0/0 (exponentials that underflowed to 0, then divided by their "
                    "sum), a square root or a log of a negative number, or a division by zero")
        scale = float(expected.abs().max()) if expected.numel() else 0.0
        if scale > 10 * self.atol and torch.allclose(got, -expected, atol=self.atol, rtol=1e-4):
            return ("has the wrong sign", ": it is minus the answer",
                    "A loss that training minimises must grow with what it penalises; look for "
                    "a difference taken the wrong way round or a minus sign too many")
        sizes = {k: n for i, axes in self.dims.items()
                 for k, n in zip(axes, case.args[i].shape) if k != "_"}
        return (_factor_off(got, expected, {**sizes, **case.sizes}, self.factors)
                or self._wrong_axis(got, case))

    def _wrong_axis(self, got, case: Case) -> tuple[str, str, str] | None:
        if self.swap is None:
            return None
        index, a, b, means, look = self.swap
        args = list(case.args)
        args[index] = args[index].transpose(a, b).contiguous()
        try:
            wrong = _numbers(self.reference(*args, **case.kwargs))
        except Exception:
            return None
        if wrong is not None and wrong.shape == got.shape and torch.allclose(
                got, wrong, atol=self.atol / 10, rtol=1e-5):
            return ("worked along the wrong axis",
                    f": it gives what the answer would be with {means}", look)
        return None

    def _gradient(self, fn: Callable, name: str, case: Case, index: int, label: str) -> None:
        """Raise unless ``fn``'s gradient with respect to argument ``index`` is the reference's."""
        atol = self.atol if case.atol is None else case.atol
        expected = gradient(self.reference, index)(*case.args, **case.kwargs)
        probe = gradient(fn, index)
        try:
            got, spy = _run(probe, name, case, self.labels)
        except ExerciseError as error:  # numpy refuses a tensor that requires a gradient
            if "numpy" in str(error) and "grad" in str(error):
                raise _no_flow(name, case, label, ["numpy"], False) from None
            raise
        if torch.allclose(got.double(), expected.double(), atol=atol, rtol=1e-4):
            return
        why = diagnose(got, [(w, gradient(v, index)) for w, v in self.diagnoses], case, atol)
        if expected.abs().max() > 0 and not got.any():  # an own slip explains only a partial cut
            raise _no_flow(name, case, label, list(spy.cuts), probe.connected,
                           why if probe.connected else "")
        raise ExerciseError(
            f"{name} has the right value on {case.description}, but not the right gradient "
            f"with respect to {label}: it gave {_disagreement(got, expected, atol)}.{why}")


# -------------------------------------------------------------------------- the exercises

_REFERENCES: list[Callable] = []


def whose(fn: Callable) -> str:
    """``"the course's"`` when ``fn`` is an implementation a check handed over in place of an
    unfinished exercise, else ``"your"``: for a notebook to print whose function it runs."""
    return "the course's" if any(fn is r for r in _REFERENCES) else "your"


def exercise(name: str, reference: Callable, mistakes: Sequence[Diagnosis] = (),
             cases: Callable[[], list[Case]] | None = None, *, check: Callable | None = None,
             answers: Sequence[Callable] = (), **options) -> Callable:
    """The check of the exercise ``name``: ``check_name(fn)`` returns the function the notebook
    goes on with. That is ``fn`` when it is right; ``reference`` (the course's, same signature)
    while ``fn`` is the student stub, so that "Run All" reaches the end of the chapter; when
    ``fn`` is wrong, an :class:`ExerciseError` names the mistake and offers the next hint.
    ``check(fn)`` judges, by default a :class:`Comparison` of ``fn`` with ``reference`` on
    ``cases()`` naming ``mistakes``, with ``options``. ``answers``: the course's other
    functions that compute the answer: a right ``fn`` that only calls one is told so."""
    _REFERENCES.append(reference)
    check = check or Comparison(reference, cases, mistakes, **options)
    codes = {f.__code__: f"{f.__module__.removeprefix('ebjepa_tutorial.')}.{f.__name__}"
             for f in (reference, *answers) if hasattr(f, "__code__")}

    def run(fn: Callable) -> Callable:
        verdict = _judge(check, fn, reference, name, codes)
        if isinstance(verdict, ExerciseError):  # raised here, its traceback shows the
            raise verdict from None  # learner's cell, not the checker's insides
        return verdict

    run.reference, run.mistakes, run.exercise = reference, tuple(mistakes), name
    run.__doc__ = f"Check your {name}; returns the function the notebook goes on with."
    return run


def _judge(check: Callable, fn: Callable, reference: Callable, name: str,
           codes: dict) -> Callable | ExerciseError:
    """Run ``check(fn)``: the function the notebook goes on with, or the error to raise."""
    if fn is reference:  # this cell ran again after handing the course's one over
        print("This is still the course's implementation: run the cell with your "
              "function first, then this check.")
        return reference
    _Spy.answers, _Spy.called = codes, {}
    try:
        check(fn)
    except NotImplementedYet:
        print(f"{getattr(fn, '__name__', 'your function')} is not implemented yet: the "
              "rest of this notebook uses the course's implementation. Write yours in "
              f"the cell above, then run it and this check again (exercises.hint("
              f"{name!r}) gives a hint).")
        return reference
    except ExerciseError as error:
        return ExerciseError(str(error) + _offer(name))
    finally:
        _Spy.answers = {}
    if _Spy.called:
        print(f"Note: your {getattr(fn, '__name__', 'function')} calls the course's "
              f"own {_and(list(_Spy.called))}. The check passes, but it checked the course's "
              "code, not yours: write it from the formula to get what the exercise teaches.")
    return fn
