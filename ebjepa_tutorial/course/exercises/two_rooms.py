"""Checkers of chapter 04: the wall collision for one step, in two checked steps.

1. ``check_slab_crossing(fn)``: ``fn(x0, x1, x_lo, x_hi) -> (t_in, t_out)``, the
   fractions of a move at which the dot is inside the wall's slab.
2. ``check_wall_collision(fn)``: ``fn(positions, moves, layouts) -> new positions``,
   compared with the reference :func:`wall_collision` on the same cases (through the door,
   into the wall, into the door's side, into the border, free moves, random ones, huge
   ones). It says in plain words what went wrong first: leaving the arena, passing through
   the wall, ending inside it, stopping at an open door, or any other disagreement; and, if
   the learner's positions match a typical wrong rule on that case (a target not clamped
   first, cancelling the whole move, no sliding along the wall, no door sides), it names
   that rule instead.
"""

from __future__ import annotations

import torch

from ...envs.two_rooms import (
    HIGH,
    LOW,
    random_layouts,
    sample_positions,
    stop_at_wall,
    wall_bounds,
    wall_collision,
)
from .common import (
    Case,
    ExerciseError,
    _describe,
    _run,
    _transposition,
    _type_problem,
    compare,
    diagnose,
    exercise,
)


def _slab_crossing(x0, x1, x_lo, x_hi):
    """Reference: the fractions ``t_in <= t_out`` of the move ``x0 -> x1`` (all ``(B,)``) spent
    inside the slab ``x_lo < x < x_hi``; equal when the move never enters it."""
    moving = x1 != x0
    dx = torch.where(moving, x1 - x0, torch.ones_like(x0))
    t_a, t_b = (x_lo - x0) / dx, (x_hi - x0) / dx
    t_in = torch.where(moving, torch.minimum(t_a, t_b).clamp(0, 1), 0.0)
    inside = ((x0 > x_lo) & (x0 < x_hi)).to(x0.dtype)
    t_out = torch.where(moving, torch.maximum(t_a, t_b).clamp(0, 1), inside)
    return t_in, t_out


def _crossing_slip(order=True, clamp=True, still=True, strict=True):
    """:func:`_slab_crossing` with one mistake (each keyword undoes one step)."""
    def slab_crossing(x0, x1, x_lo, x_hi):
        moving = x1 != x0
        dx = torch.where(moving, x1 - x0, torch.ones_like(x0)) if still else x1 - x0
        t_a, t_b = (x_lo - x0) / dx, (x_hi - x0) / dx
        t_in, t_out = (torch.minimum(t_a, t_b), torch.maximum(t_a, t_b)) if order else (t_a, t_b)
        if clamp:
            t_in, t_out = t_in.clamp(0, 1), t_out.clamp(0, 1)
        if still:
            inside = ((x0 > x_lo) & (x0 < x_hi)) if strict else ((x0 >= x_lo) & (x0 <= x_hi))
            t_in = torch.where(moving, t_in, 0.0)
            t_out = torch.where(moving, t_out, inside.to(x0.dtype))
        return t_in, t_out

    return slab_crossing


_CROSSING_HINTS = (
    "Follow the move as a straight segment: x goes from x0 to x1 while a fraction t goes "
    "from 0 to 1. The slab is an interval of x; find the range of t for which x is inside "
    "it. A move may enter from either side, or not move in x at all.",
    "x(t) = x0 + t (x1 - x0). It reaches the slab's two faces at t_a = (x_lo - x0) / "
    "(x1 - x0) and t_b = (x_hi - x0) / (x1 - x0); t_in is the smaller of the two and t_out "
    "the larger, each clamped to [0, 1] (a move that stops short, or starts inside, uses "
    "only part of the slab). If x1 equals x0 there is nothing to divide by: the dot is then "
    "inside for the whole move (t_in = 0, t_out = 1) if x_lo < x0 < x_hi, and never "
    "(t_in = t_out = 0) otherwise. All four inputs are (B,): decide per move with "
    "torch.where, not with if.",
    "moving = <x1 differs from x0>\n"
    "dx = <x1 - x0 where moving, else 1, so that nothing divides by zero>\n"
    "t_a, t_b = <the fractions at which x reaches x_lo and x_hi>\n"
    "t_in = torch.where(moving, <the smaller of t_a, t_b, clamped to [0, 1]>, 0.0)\n"
    "t_out = torch.where(moving, <the larger, clamped>, <1.0 if x0 is strictly inside the "
    "slab, else 0.0>)\n"
    "return t_in, t_out",
)

_CROSSING_SLIPS = [
    ("a move to the left reaches x_hi first: t_in is the smaller of the two fractions and "
     "t_out the larger, whichever face each belongs to.", _crossing_slip(order=False)),
    ("you did not clamp the fractions to [0, 1]: a move that stops before the slab, or "
     "starts inside it, uses only the part of the slab between its start and its end.",
     _crossing_slip(clamp=False)),
    ("a move with no change in x divides by zero: handle it apart (inside for the whole move "
     "if x_lo < x0 < x_hi, never otherwise).", _crossing_slip(still=False)),
    ("a dot exactly on a face (x0 = x_lo or x0 = x_hi) is not inside the slab: the slab is "
     "the open interval x_lo < x < x_hi.", _crossing_slip(strict=False)),
]


def _crossing_cases(seed: int = 1, n: int = 64) -> list[Case]:
    g = torch.Generator().manual_seed(seed)

    def rand(*shape, dtype=torch.float32):
        return torch.rand(*shape, generator=g, dtype=dtype)

    wall_x = 14.0 + torch.randint(0, 36, (n,), generator=g).float()
    x_lo, x_hi = wall_x - 2.5, wall_x + 2.5
    left, right = x_lo - 0.5 - 6 * rand(n), x_hi + 0.5 + 6 * rand(n)
    inside = x_lo + 0.2 + 4.6 * rand(n)
    mixed = LOW + (HIGH - LOW) * rand(n)
    still = torch.where(rand(n) < 0.5, inside, left)
    return [
        Case("moves to the right across the whole slab", (left, right, x_lo, x_hi)),
        Case("moves to the left across the whole slab", (right, left, x_lo, x_hi)),
        Case("moves that stop inside the slab", (left, inside, x_lo, x_hi)),
        Case("moves that start inside the slab and leave it", (inside, right, x_lo, x_hi)),
        Case("moves that never reach the slab", (left, left - 1.0, x_lo, x_hi)),
        Case("moves with no change in x, some inside the slab, some not",
             (still, still.clone(), x_lo, x_hi)),
        Case("moves from exactly on a face", (x_lo.clone(), right, x_lo, x_hi)),
        Case("moves standing still exactly on a face", (x_hi.clone(), x_hi.clone(), x_lo, x_hi)),
        Case("random moves", (mixed, LOW + (HIGH - LOW) * rand(n), x_lo, x_hi)),
        Case("random moves in float64", (mixed.double(), right.double(), x_lo.double(),
                                         x_hi.double())),
    ]


@exercise(_slab_crossing, _CROSSING_SLIPS, name="slab_crossing", hints=_CROSSING_HINTS)
def check_slab_crossing(fn) -> bool:
    """Notebook 04, step 1: ``slab_crossing(x0, x1, x_lo, x_hi) -> (t_in, t_out)``, all
    ``(B,)``."""
    return compare(fn, _slab_crossing, _crossing_cases(), atol=1e-5, parts=("t_in", "t_out"),
                   diagnoses=_CROSSING_SLIPS)


def _cases(seed: int, n: int) -> list[tuple[str, torch.Tensor, torch.Tensor, torch.Tensor]]:
    """(description, positions (n, 2), moves (n, 2), layouts (n, 2)) for each kind of case."""
    g = torch.Generator().manual_seed(seed)
    layouts = random_layouts(n, g)
    x_lo, x_hi, y_lo, y_hi = wall_bounds(layouts)
    wall_x, door_y = layouts.float().unbind(-1)
    side = torch.randint(0, 2, (n,), generator=g).float() * 2 - 1  # -1 left, +1 right
    face = torch.where(side < 0, x_lo, x_hi)
    gap = 1.5 * torch.rand(n, generator=g)
    in_door = door_y + 6.8 * torch.rand(n, generator=g) - 3.4
    above = y_lo - 1 - (y_lo - LOW - 1) * torch.rand(n, generator=g)  # rows above the door
    toward = -side[:, None] * torch.stack([1.2 + torch.rand(n, generator=g), torch.zeros(n)], -1)

    def rand(*shape):
        return torch.rand(*shape, generator=g)

    free = torch.stack([LOW + 2 + (x_lo - LOW - 4) * rand(n), LOW + 2 + 50 * rand(n)], -1)
    corridor = torch.stack([wall_x + 4.8 * rand(n) - 2.4, in_door], -1)
    random_pos = sample_positions(layouts, g)
    random_pos[: n // 4] = corridor[: n // 4]
    return [
        ("a move far from every wall (it should not change)", free, 2 * rand(n, 2) - 1, layouts),
        ("a move into the border", free, torch.tensor([-70.0, 70.0]).expand(n, 2), layouts),
        ("a move straight through the door", torch.stack([face + side * gap, in_door], -1),
         toward, layouts),
        ("a move into the wall above the door", torch.stack([face + side * gap, above], -1),
         toward, layouts),
        ("a move from inside the doorway out to the other room", corridor,
         torch.stack([1.8 * side, 0.4 * rand(n) - 0.2], -1), layouts),
        ("a slanted move from the doorway into the door's side", corridor,
         torch.stack([side, 1.8 + rand(n)], -1), layouts),
        ("a random move", random_pos, 1.8 * torch.randn(n, 2, generator=g), layouts),
        ("a huge random move", random_pos, 40 * torch.randn(n, 2, generator=g), layouts),
    ]


def _where(p, move, layout) -> str:
    return (
        f"from (x={p[0]:.2f}, y={p[1]:.2f}) moving by ({move[0]:.2f}, {move[1]:.2f}) "
        f"with wall_x={int(layout[0])}, door_y={int(layout[1])}"
    )


def _first_problem(desc, pos, move, layouts, got, expected, diagnosed: bool) -> str | None:
    """A plain-words message about the first wrong output, or None if all agree. When a
    typical wrong rule explains the output (``diagnosed``), only the positions are given:
    the symptom could mislead (an unclamped target can look like a dot stopped at an open
    door), and the rule, named after this, says what to change."""
    x_lo, x_hi, y_lo, y_hi = wall_bounds(layouts)
    wall_x = layouts[:, 0].float()
    x0, y0 = pos.unbind(-1)
    x1, y1 = got.unbind(-1)
    crossed = (x0 < wall_x) != (x1 < wall_x)
    ref_crossed = (x0 < wall_x) != (expected[:, 0] < wall_x)
    face = torch.where(x0 <= x_lo, x_lo, torch.where(x0 >= x_hi, x_hi, torch.nan))
    stopped_at_door = ((x1 - face).abs() < 1e-4) & ((expected[:, 0] - face).abs() > 1e-4)
    t = ((wall_x - x0) / torch.where(x1 == x0, torch.ones_like(x1), x1 - x0)).clamp(0, 1)
    y_cross = y0 + t * (y1 - y0)
    tol = 1e-4
    wrong = ~torch.isclose(got, expected, atol=1e-4, rtol=0).all(-1)
    checks = [
        ~torch.isfinite(got).all(-1),
        ((got < LOW - tol) | (got > HIGH + tol)).any(-1),
        crossed & ~ref_crossed & ((y_cross < y_lo - tol) | (y_cross > y_hi + tol)),
        (x1 > x_lo + tol) & (x1 < x_hi - tol) & ((y1 < y_lo - tol) | (y1 > y_hi + tol)),
        stopped_at_door,
        wrong,
    ]
    if diagnosed:
        checks = [torch.zeros_like(wrong)] * 5 + [wrong]
    for k, mask in enumerate(checks):
        if not mask.any():
            continue
        i = int(mask.nonzero()[0])
        at = f"{_where(pos[i], move[i], layouts[i])} ({desc})"
        door = (
            f"the door spans rows {int(layouts[i, 1]) - 4}..{int(layouts[i, 1]) + 4}, so the dot "
            f"centre may cross only for {y_lo[i]:.1f} <= y <= {y_hi[i]:.1f}"
        )
        got_i, exp_i = [f"({v[i, 0]:.2f}, {v[i, 1]:.2f})" for v in (got, expected)]
        return [
            f"your function returned NaN or infinity {at}.",
            f"your function moved the dot to {got_i}, outside the arena (the dot centre must "
            f"stay in [{LOW}, {HIGH}] in x and y), {at}: rule 1 clamps the target to the "
            "arena before anything else.",
            f"your function let the dot pass through the wall at y={y_cross[i]:.1f} where {door}; "
            f"{at} it ended at {got_i}.",
            f"your function left the dot centre inside the wall at {got_i} (the slab "
            f"{x_lo[i]:.1f} < x < {x_hi[i]:.1f} is open only for {y_lo[i]:.1f} <= y <= "
            f"{y_hi[i]:.1f}), {at}.",
            f"your function stopped the dot at the wall, but the door is open there: {door}; "
            f"{at} the reference goes on to {exp_i}, yours stopped at {got_i}.",
            f"your function gave {got_i} but the reference gives {exp_i}, {at}."
            + ("" if diagnosed else " The rule: clamp the target to the arena first; stop "
               "only the blocked coordinate (x at the wall's face, or y at the door's edge) "
               "and let the other one move."),
        ][k]
    return None


def _stay_put(positions, moves, layouts):
    """Cancel the whole move whenever a wall blocks it."""
    target = (positions + moves).clamp(LOW, HIGH)
    expected = wall_collision(positions, moves, layouts)
    blocked = ~torch.isclose(expected, target).all(-1, keepdim=True)
    return torch.where(blocked, positions, expected)


def _stop_at_contact(positions, moves, layouts):
    """Stop both coordinates where the path meets the wall's face (no sliding along it)."""
    target = (positions + moves).clamp(LOW, HIGH)
    expected = wall_collision(positions, moves, layouts)
    x0, y0 = positions.unbind(-1)
    x1, y1 = target.unbind(-1)
    at_face = ~torch.isclose(expected[:, 0], x1)
    t = (expected[:, 0] - x0) / torch.where(at_face, x1 - x0, torch.ones_like(x0))
    y = torch.where(at_face, y0 + t * (y1 - y0), expected[:, 1])
    return torch.stack([expected[:, 0], y], -1)


def _no_door_sides(positions, moves, layouts):
    """Stop at the wall's faces but let y leave the doorway inside the slab."""
    target = (positions + moves).clamp(LOW, HIGH)
    return torch.stack([wall_collision(positions, moves, layouts)[:, 0], target[:, 1]], -1)


def _clamped_last(positions, moves, layouts):
    """The wall rules on the unclamped target, clamped to the arena only at the end."""
    return stop_at_wall(positions, positions + moves, layouts).clamp(LOW, HIGH)


def _never_clamped(positions, moves, layouts):
    """The wall rules on the unclamped target, never clamped."""
    return stop_at_wall(positions, positions + moves, layouts)


_NOT_CLAMPED_FIRST = (
    "the target was not clamped to the arena first. Rule 1 comes before the walls: the wall "
    "rules follow the segment from the start to the clamped target; from an unclamped one "
    "the segment meets the wall's line at another height, so the dot can stop where the door "
    "is open, or pass where it is shut. Clamp positions + moves to [LOW, HIGH] before the "
    "slab and the door are looked at.")

_WALL_HINTS = (
    "Three rules, in order. First keep the target in the arena. Then the slab decides: if "
    "the dot enters it at a height outside the doorway, the wall's face stops x; if it "
    "enters through the doorway but would leave the door's span while still inside the "
    "slab, the door's edge stops y. Only the blocked coordinate stops; the other one moves "
    "on. slab_crossing gives the fractions of the move spent inside the slab.",
    "Target (x1, y1): positions + moves, each coordinate clamped to [LOW, HIGH]. With t_in, "
    "t_out from slab_crossing, the segment enters the slab if t_out > t_in, at height y_in "
    "= y(t_in), and leaves it at y_out = y(t_out), where y(t) = y0 + t (y1 - y0). Rule 2 "
    "(face): it enters and y_in is outside [y_lo, y_hi]: x becomes the face it came from "
    "(x_lo if x0 <= x_lo, else x_hi). Rule 3 (door side): it enters, rule 2 does not apply, "
    "and y_out is outside [y_lo, y_hi]: y becomes y1 clamped to [y_lo, y_hi]. Otherwise "
    "(x1, y1). Decide per row with torch.where; return (B, 2).",
    "step 1: x1, y1 = <positions + moves clamped to [LOW, HIGH], split into its columns>\n"
    "step 2: enters = t_out > t_in\n"
    "        hits_face = enters & <y_in outside [y_lo, y_hi]>\n"
    "        hits_side = enters & ~hits_face & <y_out outside [y_lo, y_hi]>\n"
    "        x = torch.where(hits_face, <the face the dot came from>, x1)\n"
    "        y = torch.where(hits_side, <y1 clamped to the doorway>, y1)\n"
    "        return <x and y stacked as the last axis>",
)

_WALL_SLIPS = [
    (_NOT_CLAMPED_FIRST, _clamped_last),
    (_NOT_CLAMPED_FIRST, _never_clamped),
    ("you cancel the whole move when the wall blocks it; stop only the blocked coordinate "
     "(x at the wall's face) and let the other one (y) slide on.", _stay_put),
    ("you stop the dot where its path meets the wall's face, y included; only x stops there: "
     "y still moves the whole way (the dot slides along the wall).", _stop_at_contact),
    ("you handled the wall's faces but not the door's sides: a move that enters the doorway "
     "and would leave its span inside the slab must stop y at the door's edge (y_lo or y_hi).",
     _no_door_sides),
]


@exercise(wall_collision, _WALL_SLIPS, name="wall_collision", hints=_WALL_HINTS,
          answers=(stop_at_wall,))
def check_wall_collision(fn, n: int = 512, seed: int = 0) -> bool:
    """Compare ``fn(positions, moves, layouts)`` with the reference; print a verdict or raise
    :class:`~ebjepa_tutorial.course.exercises.ExerciseError` (an AssertionError) saying
    which case failed and how."""
    name = getattr(fn, "__name__", "your function")
    cases = _cases(seed, n)
    labels = ("positions", "moves", "layouts")
    for desc, pos, move, layouts in cases:
        case = Case(desc, (pos, move, layouts))
        expected = wall_collision(pos, move, layouts)
        got, _ = _run(fn, name, case, labels)
        if (problem := _type_problem(got, name, case)):
            raise ExerciseError(problem)
        if got.shape != expected.shape:
            if _transposition(got, expected, 1e-4) is not None:
                raise ExerciseError(
                    f"{name} put the right positions in the wrong layout on {desc}: shape "
                    f"{tuple(got.shape)}, where {tuple(expected.shape)} is expected, one row "
                    "(x, y) per world. Look at the axis along which you stack x and y: the "
                    "last one.")
            raise ExerciseError(
                f"{name} returned {_describe(got)} on {desc}; it should return new positions "
                f"of shape {tuple(expected.shape)}, one (x, y) per world.")
        got = got.detach().float()
        why = diagnose(got, _WALL_SLIPS, case, atol=1e-3)
        problem = _first_problem(desc, pos, move, layouts, got, expected, bool(why))
        if problem:
            raise ExerciseError(problem.replace("your function", name, 1) + why)
    print(f"Correct: {name} matches the reference wall collision on {n * len(cases)} moves.")
    return True
