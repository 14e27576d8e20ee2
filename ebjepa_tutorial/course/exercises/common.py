"""What every checker shares: the graded hints (:func:`hint`) and :class:`Exercise`, which
compares a learner's function with the course's and names a wrong answer in words."""

import dis
import inspect
import textwrap
import traceback
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch
import yaml

from ...training.checkpoints import CHECKED, nested_codes
from ...utils import is_int_at_least

TEXTS = yaml.safe_load(Path(__file__).with_name("hints.yaml").read_text(encoding="utf-8"))
WORDS = yaml.safe_load(Path(__file__).with_name("general.yaml").read_text(encoding="utf-8"))
HINTS = {name: tuple(texts["hints"]) for name, texts in TEXTS.items()}
LEVELS = ("the idea", "the formula", "an outline of the code")
_shown: dict[str, int] = {}  # exercise -> the highest hint level shown in this session
_REFERENCES: dict[Callable, str] = {}  # the course's functions a check may hand over -> exercise
_LIBRARIES = (str(Path(torch.__file__).parent), str(Path(__file__).parents[2]))  # not the learner's


def say(key: str, **fields) -> str:
    """general.yaml's words for ``key``, filled in with ``fields``."""
    return WORDS[key].format(**fields)


class ExerciseError(AssertionError):
    """The learner's function disagrees with the reference; the message says where."""


def whose(fn: Callable) -> str:
    """``"the course's"`` if a check handed ``fn`` over for an unfinished one, else ``"your"``."""
    return "the course's" if any(fn is r for r in _REFERENCES) else "your"


def hint(name, level: int | None = None) -> None:
    """Print hint ``level`` (1 the idea, 2 the formula and the shapes, 3 an outline of the code;
    by default the next not shown yet) of the exercise ``name``, or of that function."""
    # an Exercise, the course's function a check handed over (its name may differ), or a name
    name = (getattr(name, "exercise", None) or _REFERENCES.get(name)
            or getattr(name, "__name__", name))
    if name not in HINTS:
        print(say("no_such_exercise", name=name, names=", ".join(sorted(HINTS))))
        return
    level = min(_shown.get(name, 0) + 1, len(LEVELS)) if level is None else level
    if not is_int_at_least(1)(level) or level > len(LEVELS):  # 2.0 or True: not a level
        raise ValueError(say("bad_level", level=level))
    _shown[name] = max(_shown.get(name, 0), level)
    print(_hint_text(name, level))


def _hint_text(name: str, level: int) -> str:
    body, last = HINTS[name][level - 1], level == len(LEVELS)
    text = f"Hint {level} of {len(LEVELS)} for {name}, {LEVELS[level - 1]}:\n"
    text += body if last else textwrap.fill(body, 88)  # the outline keeps its lines
    return text if last else text + f"\n(exercises.hint({name!r}) again gives {LEVELS[level]}.)"


def checked(fn: Callable | None, course: Callable) -> Callable:
    """``fn`` once it passed its exercise's check, else ``course``: what a run trains with."""
    return fn if getattr(fn, CHECKED, None) == "passed" else course


def _mark(fn: Callable, verdict: str) -> None:
    """Record the check's ``verdict`` on ``fn``, for the training runs (``checkpoints``)."""
    try:
        setattr(fn, CHECKED, verdict)
    except (AttributeError, TypeError):  # a callable that takes no attributes stays unmarked
        pass


@dataclass
class Case:
    """One test input. ``sizes``: named sizes (``{"K": 3}``) a factor may be off by; ``atol``: a
    looser tolerance where float32 cannot do better (the exercise's ``float32`` words say why)."""

    description: str
    args: tuple
    kwargs: dict = field(default_factory=dict)
    sizes: dict = field(default_factory=dict)
    atol: float | None = None


def gradient(fn: Callable, index: int) -> Callable:
    """``fn`` returning the gradient of its output's sum with respect to argument ``index``
    (zeros where none reaches it; None when the output is not connected to autograd at all)."""
    def run(*args, **kwargs):
        x = args[index].detach().clone().requires_grad_()
        out = fn(*args[:index], x.clone(), *args[index + 1:], **kwargs)  # clone: in place is ok
        if not (isinstance(out, torch.Tensor) and out.requires_grad):
            return None
        grad = torch.autograd.grad(out.sum(), x, allow_unused=True)[0]
        return torch.zeros_like(x) if grad is None else grad

    return run


def _numbers(value) -> torch.Tensor | None:
    """``value`` as a float64 tensor (a tuple of tensors flattened and joined), else None."""
    if isinstance(value, (tuple, list)) and value and all(torch.is_tensor(v) for v in value):
        return torch.cat([v.detach().double().flatten() for v in value])
    try:
        return torch.as_tensor(value).detach().double()
    except (TypeError, ValueError, RuntimeError):
        return None


def _describe(value) -> str:
    if isinstance(value, torch.Tensor):
        return f"a tensor of shape {tuple(value.shape)}"
    if isinstance(value, (tuple, list)):
        return f"a {type(value).__name__} of {len(value)}"
    return f"a {type(value).__module__.replace('builtins', 'Python')} {type(value).__name__}"


def diagnose(got, variants: Sequence[tuple[str, Callable]], case: Case, atol: float) -> str:
    """`` Likely cause: <words>`` of the variant closest to ``got`` on ``case`` (within a tenth
    of ``atol``; a tie goes to the first), else ``''``."""
    got, matches = _numbers(got), []
    for order, (words, variant) in enumerate(variants if got is not None else ()):
        try:
            with warnings.catch_warnings():  # a slip's own warnings are not the learner's
                warnings.simplefilter("ignore")
                wrong = _numbers(variant(*case.args, **case.kwargs))
        except Exception:  # a variant may fail where its mistake makes no sense
            continue
        if (wrong is not None and wrong.shape == got.shape
                and torch.isclose(got, wrong, atol=atol / 10, rtol=1e-5, equal_nan=True).all()):
            matches.append((float((got - wrong).abs().nan_to_num(0.0).sum()), order, words))
    return f" Likely cause: {min(matches)[2]}" if matches else ""


def _general_cause(got, expected, atol: float, sizes: dict, advice: dict):
    """``(what was found, what it means, what to look at)`` when float64 ``got`` is NaN, minus
    ``expected``, or off by a factor: a named size n, n - 1, n/(n - 1), the square of either of
    the last two, or 2 (what to look at: ``advice[factor]``). Else None."""
    if torch.isfinite(expected).all() and not torch.isfinite(got).all():
        return say("nan"), "", say("nan_look")
    if expected.abs().max() > 10 * atol and torch.allclose(got, -expected, atol=atol, rtol=1e-4):
        return say("sign"), say("sign_means"), say("sign_look")
    big = expected.abs() > 1e-8
    if not big.any() or not torch.isfinite(got).all():
        return None
    ratio = got[big] / expected[big]
    r = float(ratio.median())
    if r <= 0 or not torch.allclose(ratio, torch.full_like(ratio, r), rtol=1e-4, atol=0):
        return None
    factors = [(k, n) for k, n in sizes.items() if n >= 2] + [
        (words, value) for k, n in sizes.items() if n > 2 for words, value in
        [(f"{k} - 1", n - 1), (f"({k} - 1)²", (n - 1) ** 2), (f"{k}/({k} - 1)", n / (n - 1)),
         (f"({k}/({k} - 1))²", (n / (n - 1)) ** 2)]] + [("2", 2)]
    for words, value in factors:
        for direction, target in (("too large", value), ("too small", 1 / value)):
            if abs(r - target) < 1e-4 * target:
                shown = "" if words == "2" else f" = {value:.4g}"
                return (say("factor", direction=direction, words=words, shown=shown), "",
                        say("factor_look", look=advice.get(words, say("factor_any"))))
    return None


def _disagreement(got, expected, atol: float) -> str:
    """``'x, but the answer is y'`` (float64 tensors), naming the first element that differs."""
    if expected.numel() == 1:
        return f"{float(got):.6g}, but the answer is {float(expected):.6g}"
    bad = ~torch.isclose(got, expected, atol=atol, rtol=1e-4)
    first = tuple(int(i) for i in bad.nonzero()[0])
    return (f"{float(got[first]):.6g} at index {list(first)}, but the answer is "
            f"{float(expected[first]):.6g} (the first of {int(bad.sum())} wrong elements out "
            f"of {bad.numel()})")


def _reads(fn: Callable, target: Callable, seen: set | None = None) -> bool:
    """Whether the notebook's (``__main__``) function ``fn``, or a function inside it, reads
    ``target``: by a global name (``from ... import variance_term as v``), a module's attribute
    (``losses.variance_term``), a closure, or through another notebook function it reads (a
    helper). A partial or a callable object is not looked into."""
    seen = set() if seen is None else seen
    if not inspect.isfunction(fn) or fn.__module__ != "__main__" or fn in seen:
        return False
    seen.add(fn)
    cells = inspect.getclosurevars(fn).nonlocals.values()  # a closure's variables
    if any(cell is target or _reads(cell, target, seen) for cell in cells):
        return True
    for code in nested_codes(fn):
        found = None
        for step in dis.get_instructions(code):
            if step.opname == "LOAD_GLOBAL":
                found = fn.__globals__.get(step.argval)
            elif step.opname in ("LOAD_ATTR", "LOAD_METHOD") and inspect.ismodule(found):
                found = getattr(found, step.argval, None)
            else:
                found = None
            if found is target or _reads(found, target, seen):
                return True
    return False


@dataclass
class Exercise:
    """``check(fn)`` returns ``fn`` when it agrees with ``reference`` on ``cases()``, in value and
    in the gradient with respect to each ``grad`` ``(argument index, label)``, or ``reference``
    while ``fn`` is the student stub (so "Run All" goes on). Else it raises an
    :class:`ExerciseError` naming the mistake (a typical one, ``explain``'s words or a general
    one; ``dims``: the inputs' axes, ``{index: "BD"}``, ``_`` for none) with the next hint.
    ``parts``: a tuple's outputs; ``adapt``: turns a function into what the cases call."""

    exercise: str
    reference: Callable
    mistakes: dict  # hints.yaml's key -> a function making that slip (a tuple: several ways)
    cases: Callable[[], list[Case]]
    atol: float = 1e-5
    parts: Sequence[str] | None = None
    grad: Sequence[tuple[int, str]] = ()
    dims: dict = field(default_factory=dict)
    explain: Callable | None = None  # (case, got, expected, diagnosed) -> words or None
    adapt: Callable = lambda f: f

    def __post_init__(self):
        _REFERENCES[self.reference] = self.exercise
        words = TEXTS[self.exercise]["slips"]  # in order: on a tie the first is named
        self.slips = [(words[key], f) for key, fs in self.mistakes.items()
                      for f in (fs if isinstance(fs, tuple) else (fs,))]
        self._reference = self.adapt(self.reference)
        self._mistakes = [(words, self.adapt(v)) for words, v in self.slips]
        self._labels = list(inspect.signature(self._reference).parameters)

    def __call__(self, fn: Callable) -> Callable:
        if fn is self.reference:  # this cell ran again after handing the course's one over
            print(say("still_the_course"))
            return fn
        name, run, cases = getattr(fn, "__name__", "your function"), self.adapt(fn), self.cases()
        try:
            if _reads(fn, self.reference):  # a wrapper of the answer would pass every case
                raise ExerciseError(say("calls_the_course", name=name,
                                        answer=self.reference.__name__))
            gap = max(self._values(run, name, case) for case in cases)
            for case in cases:
                for index, label in self.grad:
                    self._gradient(run, name, case, index, label)
        except NotImplementedError:  # the student stub
            print(say("not_yet", name=name, exercise=self.exercise))
            return self.reference
        except ExerciseError as error:  # raised from here, it shows the learner's cell only
            _mark(fn, "failed")  # so that no training run takes it up
            level = _shown.get(self.exercise, 0) + 1  # offer the next hint short of the code
            if level < len(LEVELS):
                _shown[self.exercise] = level
                raise ExerciseError(f"{error}\n\n{_hint_text(self.exercise, level)}") from None
            raise ExerciseError(f"{error}\n\n{say('still_stuck', name=self.exercise)}") from None
        *labels, last = [label for _, label in self.grad] or [""]
        what = f"{', '.join(labels)} and {last}" if labels else last
        print(say("correct", name=name, n=len(cases),
                  what=f" (values, and gradients with respect to {what})" if what else ""))
        if gap:  # a right answer that needed a case's looser tolerance
            print(TEXTS[self.exercise]["float32"].format(diff=gap))
        _mark(fn, "passed")  # a run with it is the course's run
        return fn

    def _run(self, fn: Callable, name: str, case: Case):
        """``fn``'s output on a copy of ``case``'s inputs; raise if it crashes or edits one."""
        args = [v.clone() if isinstance(v, torch.Tensor) else v for v in case.args]
        try:
            out = fn(*args, **case.kwargs)  # keyword arguments are numbers
        except NotImplementedError:
            raise
        except Exception as err:  # where in the learner's code, and advice for a tensor's `if`
            mine = [f for f in traceback.extract_tb(err.__traceback__)
                    if not f.filename.startswith(_LIBRARIES) and f.line]
            where = say("where", line=mine[-1].lineno, source=mine[-1].line) if mine else ""
            advice = " " + say("tensor_if") if "Boolean value of Tensor" in str(err) else ""
            raise ExerciseError(say("raised", name=name, case=case.description, where=where,
                                    error=f"{type(err).__name__}: {str(err).rstrip('.')}",
                                    advice=advice)) from err
        for label, before, after in zip(self._labels, case.args, args):
            if isinstance(before, torch.Tensor) and not torch.equal(after, before):
                raise ExerciseError(say("in_place", name=name, label=label,
                                        case=case.description))
        return out

    def _values(self, fn: Callable, name: str, case: Case) -> float:
        """Raise unless ``fn`` agrees with the reference on ``case``; return the gap if only the
        case's looser ``atol`` holds, else 0."""
        expected = self._reference(*case.args, **case.kwargs)
        got = self._run(fn, name, case)
        atol, gap = self.atol if case.atol is None else case.atol, 0.0
        parts = self.parts if got is not None else None  # None: the missing return's words
        if parts and (not isinstance(got, (tuple, list)) or len(got) != len(parts)):
            raise ExerciseError(say("not_a_tuple", name=name, n=len(parts), case=case.description,
                                    parts=", ".join(parts), kind=_describe(got)))
        for label, g, e in zip(parts, got, expected) if parts else [("", got, expected)]:
            if (torch.is_tensor(e) and not torch.is_tensor(g)) or _numbers(g) is None:
                key = ("returned_none" if g is None else "returned_several"
                       if isinstance(g, (tuple, list)) else "returned_other")
                raise ExerciseError(say(key, name=name, label=f"{label} as " if label else "",
                                        kind=_describe(g), case=case.description, what="a torch "
                                        "tensor" if torch.is_tensor(e) else "a number"))
            # a loss may compute in float64 (autograd promotes it); an answer the course feeds
            # back (a plan, a position) must keep its inputs' dtype
            if torch.is_tensor(e) and not self.grad and g.dtype != e.dtype and g.shape == e.shape:
                raise ExerciseError(say("wrong_dtype", name=name, case=case.description,
                                        label=f"{label} as " if label else "", got=g.dtype,
                                        expected=e.dtype))
            g, e = _numbers(g), _numbers(e)
            if g.shape != e.shape:
                raise ExerciseError(say("wrong_shape", name=name, case=case.description,
                                        got=tuple(g.shape), expected=tuple(e.shape),
                                        label=f" for your {label}" if label else "",
                                        single=" (a single number)" if e.ndim == 0 else "")
                                    + ("" if parts else diagnose(got, self._mistakes, case, atol)))
            if not torch.allclose(g, e, atol=atol, rtol=1e-4):
                raise ExerciseError(self._value_problem(name, got, g, e, case, label, atol))
            if not torch.allclose(g, e, atol=self.atol, rtol=1e-4):
                gap = max(gap, float((g - e).abs().max()))  # the largest over the parts
        return gap

    def _value_problem(self, name, got, g, e, case: Case, label: str, atol: float) -> str:
        """Words for a wrong output ``g`` (a part of ``got``; ``e`` the answer): one of the
        exercise's own mistakes, else a general one, else only the numbers."""
        plain = _disagreement(g, e, atol)
        numbers = f"{'your ' + label + ' ' if label else ''}{plain}"
        why = diagnose(got, self._mistakes, case, atol)
        if self.explain and (words := self.explain(case, g, e, bool(why))):
            return f"{name} {words}{why}"
        sizes = {k: n for i, axes in self.dims.items()
                 for k, n in zip(axes, case.args[i].shape) if k != "_"}
        if why or not (general := _general_cause(g, e, atol, {**sizes, **case.sizes},
                                                 TEXTS[self.exercise].get("factors", {}))):
            return say("wrong_value", name=name, numbers=numbers, case=case.description, why=why)
        found, means, look = general
        return say("general_cause", name=name, found=found, case=case.description, means=means,
                   where=f" (your {label})" if label else "", look=look, numbers=plain)

    def _gradient(self, fn: Callable, name: str, case: Case, index: int, label: str) -> None:
        """Raise unless ``fn``'s gradient with respect to argument ``index`` is the reference's."""
        atol = self.atol if case.atol is None else case.atol
        zeros = torch.zeros_like(case.args[index], dtype=torch.float64)  # for an unused input
        expected = gradient(self._reference, index)(*case.args, **case.kwargs)
        expected = zeros if expected is None else expected.double()
        try:
            got = self._run(gradient(fn, index), name, case)
        except ExerciseError as error:  # numpy refuses a tensor that requires a gradient
            if "numpy" not in str(error) or "grad" not in str(error):
                raise
            got = None
        connected = got is not None
        got = got.double() if connected else zeros
        if torch.allclose(got, expected, atol=atol, rtol=1e-4):
            return
        right = _numbers(self._reference(*case.args, **case.kwargs))

        def same_value(slip):  # a slip explains a wrong gradient only if its value is right too
            try:
                value = _numbers(slip(*case.args, **case.kwargs))
            except Exception:
                return False
            return value is not None and value.shape == right.shape and torch.allclose(
                value, right, atol=atol, rtol=1e-4)
        slips = [(w, gradient(v, index)) for w, v in self._mistakes if same_value(v)]
        why = diagnose(got, slips, case, atol) if connected else ""  # own slips: partial cuts
        key = "no_flow" if expected.abs().max() > 0 and not got.any() else "wrong_gradient"
        raise ExerciseError(say(key, name=name, case=case.description, label=label, why=why,
                                numbers=_disagreement(got, expected, atol)))
