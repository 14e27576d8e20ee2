"""Checkers of chapter 04: the wall collision for one step, in two checked steps.

1. ``check_slab_crossing(fn)``: ``fn(x0, x1, x_lo, x_hi) -> (t_in, t_out)``, all ``(B,)``,
   the fractions of a move at which the dot is inside the wall's slab.
2. ``check_wall_collision(fn)``: ``fn(positions, moves, layouts) -> new positions (B, 2)``,
   on moves through the door, into the wall, into the door's side, into the border, free,
   random and huge ones. It says in plain words what went wrong first (leaving the arena,
   passing through the wall, ending inside it, stopping at an open door), or names the
   typical wrong rule that gives the learner's positions.
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


def _crossing_slip(order=True, clamp=True, still=True, strict=True):
    """The fractions ``t_in <= t_out`` of the move ``x0 -> x1`` (all ``(B,)``) spent inside the
    slab ``x_lo < x < x_hi``, equal when the move never enters it; each keyword, set False,
    makes one mistake."""
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


_slab_crossing = _crossing_slip()  # the reference: no mistake
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


def _cases(seed: int, n: int) -> list[Case]:
    """Each kind of move: positions (n, 2), moves (n, 2), layouts (n, 2)."""
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
    cases = [
        ("a move far from every wall (it should not change)", free, 2 * rand(n, 2) - 1),
        ("a move into the border", free, torch.tensor([-70.0, 70.0]).expand(n, 2)),
        ("a move straight through the door", torch.stack([face + side * gap, in_door], -1),
         toward),
        ("a move into the wall above the door", torch.stack([face + side * gap, above], -1),
         toward),
        ("a move from inside the doorway out to the other room", corridor,
         torch.stack([1.8 * side, 0.4 * rand(n) - 0.2], -1)),
        ("a slanted move from the doorway into the door's side", corridor,
         torch.stack([side, 1.8 + rand(n)], -1)),
        ("a random move", random_pos, 1.8 * torch.randn(n, 2, generator=g)),
        ("a huge random move", random_pos, 40 * torch.randn(n, 2, generator=g)),
    ]
    return [Case(desc, (pos, move, layouts)) for desc, pos, move in cases]


_WALL_PROBLEMS = {  # what can go wrong, in the order it is looked for -> its words
    "nan": "returned NaN or infinity {at}.",
    "arena": f"moved the dot to {{got}}, outside the arena (the dot centre must stay in "
             f"[{LOW}, {HIGH}] in x and y), {{at}}: rule 1 clamps the target to the arena "
             "before anything else.",
    "through": "let the dot pass through the wall at y={y_cross:.1f} where {door}; {at} it "
               "ended at {got}.",
    "inside": "left the dot centre inside the wall at {got} (the slab {x_lo:.1f} < x < "
              "{x_hi:.1f} is open only for {y_lo:.1f} <= y <= {y_hi:.1f}), {at}.",
    "door": "stopped the dot at the wall, but the door is open there: {door}; {at} the "
            "reference goes on to {expected}, yours stopped at {got}.",
    "other": "gave {got} but the reference gives {expected}, {at}.{rule}",
}
_RULE = (" The rule: clamp the target to the arena first; stop only the blocked coordinate (x "
         "at the wall's face, or y at the door's edge) and let the other one move.")


def _symptoms(pos, layouts, got, expected) -> tuple[dict, torch.Tensor]:
    """Masks ``(n,)`` of what went wrong with the new positions ``got``, by the keys of
    ``_WALL_PROBLEMS``, and the height at which each move crosses the wall's line."""
    x_lo, x_hi, y_lo, y_hi = wall_bounds(layouts)
    wall_x, tol = layouts[:, 0].float(), 1e-4
    (x0, y0), (x1, y1) = pos.unbind(-1), got.unbind(-1)
    crossed = (x0 < wall_x) != (x1 < wall_x)
    ref_crossed = (x0 < wall_x) != (expected[:, 0] < wall_x)
    face = torch.where(x0 <= x_lo, x_lo, torch.where(x0 >= x_hi, x_hi, torch.nan))
    t = ((wall_x - x0) / torch.where(x1 == x0, torch.ones_like(x1), x1 - x0)).clamp(0, 1)
    y_cross = y0 + t * (y1 - y0)

    def shut(y):  # outside the doorway's span
        return (y < y_lo - tol) | (y > y_hi + tol)

    return {"nan": ~torch.isfinite(got).all(-1),
            "arena": ((got < LOW - tol) | (got > HIGH + tol)).any(-1),
            "through": crossed & ~ref_crossed & shut(y_cross),
            "inside": (x1 > x_lo + tol) & (x1 < x_hi - tol) & shut(y1),
            "door": ((x1 - face).abs() < tol) & ((expected[:, 0] - face).abs() > tol),
            "other": ~torch.isclose(got, expected, atol=1e-4, rtol=0).all(-1)}, y_cross


def _first_problem(name: str, case: Case, got, expected, diagnosed: bool) -> str | None:
    """Words for the first wrong position, or None if all agree. When a typical wrong rule
    explains the output (``diagnosed``), only the positions are given: the symptom could
    mislead (an unclamped target can look like a dot stopped at an open door), and the
    rule, named after this, says what to change."""
    pos, move, layouts = case.args
    masks, y_cross = _symptoms(pos, layouts, got, expected)
    kind = next((k for k in (["other"] if diagnosed else _WALL_PROBLEMS) if masks[k].any()), None)
    if kind is None:
        return None
    i = int(masks[kind].nonzero()[0])
    (x, y), (dx, dy), (wall_x, door_y) = pos[i].tolist(), move[i].tolist(), layouts[i].tolist()
    x_lo, x_hi, y_lo, y_hi = (float(b[i]) for b in wall_bounds(layouts))
    words = _WALL_PROBLEMS[kind].format(
        at=f"from (x={x:.2f}, y={y:.2f}) moving by ({dx:.2f}, {dy:.2f}) with wall_x={wall_x}, "
           f"door_y={door_y} ({case.description})",
        door=f"the door spans rows {door_y - 4}..{door_y + 4}, so the dot centre may cross "
             f"only for {y_lo:.1f} <= y <= {y_hi:.1f}",
        got="({:.2f}, {:.2f})".format(*got[i].tolist()),
        expected="({:.2f}, {:.2f})".format(*expected[i].tolist()),
        y_cross=float(y_cross[i]), x_lo=x_lo, x_hi=x_hi, y_lo=y_lo, y_hi=y_hi,
        rule="" if diagnosed else _RULE)
    return f"{name} {words}"


def _stay_put(positions, moves, layouts):
    """Cancel the whole move whenever a wall blocks it."""
    target = (positions + moves).clamp(LOW, HIGH)
    expected = wall_collision(positions, moves, layouts)
    return torch.where(~torch.isclose(expected, target).all(-1, keepdim=True), positions, expected)


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

_WALL_SLIPS = [  # the wall rules on the unclamped target, clamped at the end or never
    (_NOT_CLAMPED_FIRST, lambda p, m, walls: stop_at_wall(p, p + m, walls).clamp(LOW, HIGH)),
    (_NOT_CLAMPED_FIRST, lambda p, m, walls: stop_at_wall(p, p + m, walls)),
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
    """Compare ``fn(positions, moves, layouts)`` with the reference on ``n`` moves of each
    kind; print a verdict or raise :class:`ExerciseError` saying which failed and how."""
    name = getattr(fn, "__name__", "your function")
    cases = _cases(seed, n)
    for case in cases:
        expected, desc = wall_collision(*case.args), case.description
        got, _ = _run(fn, name, case, ("positions", "moves", "layouts"))
        if (problem := _type_problem(got, name, case)):
            raise ExerciseError(problem)
        if got.shape != expected.shape and _transposition(got, expected, 1e-4) is not None:
            raise ExerciseError(
                f"{name} put the right positions in the wrong layout on {desc}: shape "
                f"{tuple(got.shape)}, where {tuple(expected.shape)} is expected, one row (x, y) "
                "per world. Look at the axis along which you stack x and y: the last one.")
        if got.shape != expected.shape:
            raise ExerciseError(
                f"{name} returned {_describe(got)} on {desc}; it should return new positions "
                f"of shape {tuple(expected.shape)}, one (x, y) per world.")
        got = got.detach().float()
        why = diagnose(got, _WALL_SLIPS, case, atol=1e-3)
        if (problem := _first_problem(name, case, got, expected, bool(why))):
            raise ExerciseError(problem + why)
    print(f"Correct: {name} matches the reference wall collision on {n * len(cases)} moves.")
    return True
