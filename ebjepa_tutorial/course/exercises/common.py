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
WORDS = yaml.safe_load(Path(__file__).with_name("general.yaml").read_text(encoding="utf-8"))
HINTS = {name: tuple(texts["hints"]) for name, texts in TEXTS.items()}
LEVELS = ("the idea", "the formula", "an outline of the code")
_shown: dict[str, int] = {}  # exercise -> the highest hint level shown in this session


def say(key: str, **fields) -> str:
    """general.yaml's words for ``key``, filled in with ``fields``."""
    return WORDS[key].format(**fields)


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
        print(say("no_such_exercise", name=name, names=", ".join(sorted(HINTS))))
        return
    level = min(_shown.get(name, 0) + 1, len(LEVELS)) if level is None else level
    if level not in range(1, len(LEVELS) + 1):
        raise ValueError(say("bad_level", level=level))
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
    return "\n\n" + say("still_stuck", name=name)


# --------------------------------------------------------------- watching the learner's call

_NOT_THE_LEARNER = (str(Path(torch.__file__).parent), str(Path(__file__).parent))
_CUTS = {"detach": ".detach()", "detach_": ".detach_()", "numpy": ".numpy()",  # C methods
         "item": ".item()", "tolist": ".tolist()"}
_GRAD_OFF = {"no_grad.__enter__": "torch.no_grad()",  # Python functions, by qualified name
             "inference_mode.__enter__": "torch.inference_mode()",
             "set_grad_enabled.__init__": "torch.set_grad_enabled(False)"}
_WHAT_CUTS = {".detach()": "cut_detach", ".detach_()": "cut_detach", ".numpy()": "cut_numpy",
              "numpy": "cut_numpy", ".item()": "cut_item", ".tolist()": "cut_tolist",
              **{word: "cut_grad_off" for word in _GRAD_OFF.values()}}  # -> general.yaml


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
            numpy = "numpy" in str(err) and "grad" in str(err)
            raise ExerciseError(say("raised_numpy" if numpy else "raised", name=name,
                                    case=case.description, error=f"{type(err).__name__}: {err}")
                                ) from err
    for where, after in [*enumerate(args), *kwargs.items()]:
        before = case.kwargs[where] if isinstance(where, str) else case.args[where]
        if isinstance(before, torch.Tensor) and (after.shape != before.shape
                                                 or not torch.equal(after, before)):
            label = where if isinstance(where, str) else (
                labels[where] if where < len(labels) else f"argument {where + 1}")
            raise ExerciseError(say("in_place", name=name, label=label, case=case.description))
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
    key = ("returned_none" if got is None
           else "returned_numpy" if type(got).__module__.split(".")[0] == "numpy"
           else "returned_number" if isinstance(got, (bool, int, float))
           else "returned_several" if isinstance(got, (tuple, list)) else "returned_other")
    return say(key, yours=f"{name} returned {label + ' as ' if label else ''}", value=got,
               where=f"on {case.description}, where a torch tensor is expected",
               kind=_describe(got) if key == "returned_other" else type(got).__name__,
               n=len(got) if isinstance(got, (tuple, list)) else 0)


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
            out.append((k, n, say("factor_n", k=k)))
        if n > 2:
            ratio = say("factor_ratio", k=k)
            out += [(f"{k} - 1", n - 1, say("factor_n_1", k=k)),
                    (f"{k}/({k} - 1)", n / (n - 1), ratio),
                    (f"({k}/({k} - 1))²", (n / (n - 1)) ** 2, ratio)]
    return out + [("2", 2, say("factor_2"))]


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
                return (say("factor", direction=direction, words=words, shown=shown), "",
                        say("factor_look", look=advice.get(words, look)))
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
    return say("transposed" if _transposed(got, expected, atol) else "wrong_shape", name=name,
               case=case.description, yours=yours, got=tuple(got.shape),
               expected=tuple(expected.shape), label=" for " + yours if label else "",
               single=" (a single number)" if expected.ndim == 0 else "")


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
    look = say("no_flow_cuts" if cuts else "no_flow_one" if connected else "no_flow_unconnected",
               cuts=_and([f"{c} ({say(_WHAT_CUTS[c])})" for c in cuts]) if cuts else "",
               label=label)
    return ExerciseError(say("no_flow", name=name, case=case.description, label=label,
                             look=look, why=why))


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
        print(say("correct", name=name, n=len(cases), what=what))
        for note in dict.fromkeys(n for n in notes if n):
            print(note)

    def _values(self, fn: Callable, name: str, case: Case) -> str:
        """Raise unless ``fn`` agrees with the reference on ``case``; returns the case's note
        when it agreed only within the case's looser tolerance."""
        expected = self.reference(*case.args, **case.kwargs)
        got, _ = _run(fn, name, case, self.labels)
        atol, parts, note = self.atol if case.atol is None else case.atol, self.parts, ""
        if parts and (not isinstance(got, (tuple, list)) or len(got) != len(parts)):
            raise ExerciseError(say("not_a_pair", name=name, kind=_describe(got), n=len(parts),
                                    case=case.description, parts=", ".join(parts)))
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
            return say("wrong_value", name=name, numbers=numbers, case=case.description, why=why)
        found, means, look = general
        return say("general_cause", name=name, found=found, case=case.description, means=means,
                   where=f" (your {label})" if label else "", look=look, numbers=numbers)

    def _general_cause(self, got, expected, case: Case) -> tuple[str, str, str] | None:
        """``(what was found, ': what it means' or '', what to look at)``, or None."""
        if torch.isfinite(expected).all() and not torch.isfinite(got).all():
            return say("nan"), "", say("nan_look")
        scale = float(expected.abs().max()) if expected.numel() else 0.0
        if scale > 10 * self.atol and torch.allclose(got, -expected, atol=self.atol, rtol=1e-4):
            return say("sign"), say("sign_means"), say("sign_look")
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
            return say("axis"), say("axis_means", means=means), look
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
        raise ExerciseError(say("wrong_gradient", name=name, case=case.description, label=label,
                                numbers=_disagreement(got, expected, atol), why=why))


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
        print(say("still_the_course"))
        return reference
    _Spy.answers, _Spy.called = codes, {}
    try:
        check(fn)
    except NotImplementedYet:
        print(say("not_yet", name=getattr(fn, "__name__", "your function"), exercise=name))
        return reference
    except ExerciseError as error:
        return ExerciseError(str(error) + _offer(name))
    finally:
        _Spy.answers = {}
    if _Spy.called:
        print(say("calls_the_course", name=getattr(fn, "__name__", "function"),
                  answers=_and(list(_Spy.called))))
    return fn
