"""Checkers of chapter 04: the wall collision for one step, in two checked steps:
``slab_crossing(x0, x1, x_lo, x_hi) -> (t_in, t_out)``, all ``(B,)``, the fractions of a move
spent inside the wall's slab; then ``wall_collision(positions, moves, layouts)`` -> new positions
``(B, 2)``. For the second, the checker says in plain words what went wrong first (leaving the
arena, passing through the wall, ending inside it, stopping at an open door), or names the
typical wrong rule that gives the learner's positions.
"""

from __future__ import annotations

import torch

from ...envs import two_rooms as rooms
from ...envs.two_rooms import HIGH, LOW, stop_at_wall, wall_bounds, wall_collision
from .common import Case, ExerciseError, _run, _transposed, _type_problem, diagnose, exercise, slips


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


def _crossing_cases(n: int = 64) -> list[Case]:
    g = torch.Generator().manual_seed(1)

    def rand(n):
        return torch.rand(n, generator=g)

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


check_slab_crossing = exercise(
    "slab_crossing", _slab_crossing, slips(
        "slab_crossing", unordered=_crossing_slip(order=False),
        unclamped=_crossing_slip(clamp=False), division_by_zero=_crossing_slip(still=False),
        closed_slab=_crossing_slip(strict=False)),
    _crossing_cases, parts=("t_in", "t_out"))


def _wall_cases(n: int = 512) -> list[Case]:
    """``n`` moves of each kind: positions (n, 2), moves (n, 2), layouts (n, 2)."""
    g = torch.Generator().manual_seed(0)

    def rand(*shape):
        return torch.rand(*shape, generator=g)

    layouts = rooms.random_layouts(n, g)
    x_lo, x_hi, y_lo, y_hi = wall_bounds(layouts)
    wall_x, door_y = layouts.float().unbind(-1)
    side = torch.randint(0, 2, (n,), generator=g).float() * 2 - 1  # -1 left, +1 right
    face, gap = torch.where(side < 0, x_lo, x_hi), 1.5 * rand(n)
    in_door = door_y + 6.8 * rand(n) - 3.4
    above = y_lo - 1 - (y_lo - LOW - 1) * rand(n)  # rows above the door
    toward = -side[:, None] * torch.stack([1.2 + rand(n), torch.zeros(n)], -1)
    free = torch.stack([LOW + 2 + (x_lo - LOW - 4) * rand(n), LOW + 2 + 50 * rand(n)], -1)
    corridor = torch.stack([wall_x + 4.8 * rand(n) - 2.4, in_door], -1)
    random_pos = rooms.sample_positions(layouts, g)
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


_WALL_SLIPS = slips(  # the wall rules on the unclamped target, clamped at the end or never
    "wall_collision",
    not_clamped_first=(lambda p, m, walls: stop_at_wall(p, p + m, walls).clamp(LOW, HIGH),
                       lambda p, m, walls: stop_at_wall(p, p + m, walls)),
    stay_put=_stay_put, stop_at_contact=_stop_at_contact, no_door_sides=_no_door_sides)


def _check_wall_collision(fn) -> None:
    name = getattr(fn, "__name__", "your function")
    cases = _wall_cases()
    for case in cases:
        expected, desc = wall_collision(*case.args), case.description
        got, _ = _run(fn, name, case, ("positions", "moves", "layouts"))
        if (problem := _type_problem(got, name, case)):
            raise ExerciseError(problem)
        if got.shape != expected.shape and _transposed(got, expected, 1e-4):
            raise ExerciseError(
                f"{name} put the right positions in the wrong layout on {desc}: shape "
                f"{tuple(got.shape)}, where {tuple(expected.shape)} is expected, one row (x, y) "
                "per world. Look at the axis along which you stack x and y: the last one.")
        if got.shape != expected.shape:
            raise ExerciseError(
                f"{name} returned a tensor of shape {tuple(got.shape)} on {desc}; it should "
                f"return new positions of shape {tuple(expected.shape)}, one (x, y) per world.")
        got = got.detach().float()
        why = diagnose(got, _WALL_SLIPS, case, atol=1e-3)
        if (problem := _first_problem(name, case, got, expected, bool(why))):
            raise ExerciseError(problem + why)
    moves = sum(len(case.args[0]) for case in cases)
    print(f"Correct: {name} matches the reference wall collision on {moves} moves.")


check_wall_collision = exercise("wall_collision", wall_collision, _WALL_SLIPS,
                                check=_check_wall_collision, answers=(stop_at_wall,))
