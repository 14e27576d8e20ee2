"""Checkers of chapter 04: ``slab_crossing(x0, x1, x_lo, x_hi) -> (t_in, t_out)``, all ``(B,)``,
and ``wall_collision(positions, moves, layouts)`` -> new positions ``(B, 2)``."""

from functools import partial, wraps

import torch

from ...envs import two_rooms as rooms
from ...envs.two_rooms import HIGH, LOW, stop_at_wall, wall_bounds, wall_collision
from .common import TEXTS, Case, Exercise


def _crossing_slip(order=True, clamp=True, still=True, strict=True):
    """The fractions ``t_in <= t_out`` (B,) of the move ``x0 -> x1`` spent inside the slab
    ``x_lo < x < x_hi``, equal when it never enters; each keyword, False, makes one mistake."""
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
    slab_crossing.__qualname__ = "slab_crossing"  # as a learner sees the course's
    return slab_crossing


def _empty_as_zero(fn):
    """``fn`` with each empty crossing (``t_in == t_out``) read as ``(0, 0)``: the exercise asks
    only that the two be equal when the move never enters the slab."""
    @wraps(fn)
    def run(*args):
        out = fn(*args)
        if not (isinstance(out, (tuple, list)) and len(out) == 2
                and all(torch.is_tensor(t) and t.shape == out[0].shape for t in out)):
            return out  # the check's own words for a wrong kind of answer
        empty = out[0] == out[1]
        return tuple(torch.where(empty, torch.zeros_like(t), t) for t in out)
    return run


def _crossing_cases(n: int = 64) -> list[Case]:
    g = torch.Generator().manual_seed(1)
    rand = partial(torch.rand, generator=g)
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
        Case("moves from anywhere to the right of the slab, in float64",
             (mixed.double(), right.double(), x_lo.double(), x_hi.double())),
    ]


check_slab_crossing = Exercise(
    "slab_crossing", _crossing_slip(), dict(  # the reference: no mistake
        unordered=_crossing_slip(order=False), unclamped=_crossing_slip(clamp=False),
        division_by_zero=_crossing_slip(still=False), closed_slab=_crossing_slip(strict=False)),
    _crossing_cases, parts=("t_in", "t_out"), adapt=_empty_as_zero)


def _wall_cases(n: int = 512) -> list[Case]:
    """``n`` moves of each kind: positions (n, 2), moves (n, 2), layouts (n, 2)."""
    g = torch.Generator().manual_seed(0)
    rand = partial(torch.rand, generator=g)
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
        ("a short move out of the doorway, left or right", corridor,
         torch.stack([1.8 * side, 0.4 * rand(n) - 0.2], -1)),
        ("a slanted move from the doorway into the door's side", corridor,
         torch.stack([side, 1.8 + rand(n)], -1)),
        ("a random move", random_pos, 1.8 * torch.randn(n, 2, generator=g)),
        ("a huge random move", random_pos, 40 * torch.randn(n, 2, generator=g)),
    ]
    edge = torch.where(rand(n) < 0.5, y_lo, y_hi)  # a door-side stop leaves the dot on it
    cases.append(("a move along the door's edge, from inside the wall",
                  torch.stack([wall_x + 4.8 * rand(n) - 2.4, edge], -1),
                  torch.stack([1.8 * side, torch.zeros(n)], -1)))
    return [Case(desc, (pos, move, layouts)) for desc, pos, move in cases]


def _first_problem(case: Case, got, expected, diagnosed: bool) -> str | None:
    """Words for the first wrong new position in ``got`` ``(n, 2)``: the first of the ``symptoms``
    found, or ``other`` when a typical mistake explains ``got`` (it may look like another)."""
    pos, move, layouts = case.args
    x_lo, x_hi, y_lo, y_hi = wall_bounds(layouts)
    wall_x, tol = layouts[:, 0].float(), 1e-4
    (x0, y0), (x1, y1) = pos.unbind(-1), got.unbind(-1)
    target = (x0 + move[:, 0]).clamp(LOW, HIGH)  # the move's x, were there no wall
    in_slab = (x1 > x_lo + tol) & (x1 < x_hi - tol)
    face = torch.where(x0 <= x_lo, x_lo, torch.where(x0 >= x_hi, x_hi, torch.nan))
    t = ((wall_x - x0) / torch.where(x1 == x0, torch.ones_like(x1), x1 - x0)).clamp(0, 1)
    y_cross = y0 + t * (y1 - y0)  # where the move crosses the wall's line
    shut = [(y < y_lo - tol) | (y > y_hi + tol) for y in (y_cross, y1)]  # not in the doorway
    found = {"arena": ((got < LOW - tol) | (got > HIGH + tol)).any(-1),
             "through": ((x0 < wall_x) != (x1 < wall_x)) & shut[0] & ~in_slab
             & ((x0 < wall_x) == (expected[:, 0] < wall_x)),
             "inside": in_slab & shut[1],
             "door": ((x1 - face).abs() < tol) & ((expected[:, 0] - face).abs() > tol)
             & torch.where(x0 <= x_lo, target > x_lo, target < x_hi),  # it reached the face
             "other": ~torch.isclose(got, expected, atol=1e-4, rtol=0).all(-1)}
    kind = next(k for k in (["other"] if diagnosed else found) if found[k].any())
    i = int(found[kind].nonzero()[0])
    x, y, dx, dy, wall, door = *pos[i].tolist(), *move[i].tolist(), *layouts[i].tolist()
    return TEXTS["wall_collision"]["symptoms"][kind].format(
        at=f"from (x={x:.2f}, y={y:.2f}) moving by ({dx:.2f}, {dy:.2f}) with wall_x={wall}, "
           f"door_y={door} ({case.description})", low=LOW, high=HIGH,
        door=f"the door spans rows {door - 4}..{door + 4}, so the dot centre may cross only "
             f"for {y_lo[i]:.1f} <= y <= {y_hi[i]:.1f}", y_cross=y_cross[i], x_lo=x_lo[i],
        x_hi=x_hi[i], y_lo=y_lo[i], y_hi=y_hi[i], got="({:.2f}, {:.2f})".format(*got[i]),
        expected="({:.2f}, {:.2f})".format(*expected[i]),
        rule="" if diagnosed else " " + TEXTS["wall_collision"]["symptoms"]["rule"])


def _wall_slip(positions, moves, layouts, rule):
    """The course's new positions ``(B, 2)`` with one wrong ``rule`` at the wall."""
    target = (positions + moves).clamp(LOW, HIGH)
    expected = wall_collision(positions, moves, layouts)
    if rule == "stay_put":  # cancel the whole move whenever a wall blocks it
        blocked = ~torch.isclose(expected, target).all(-1, keepdim=True)
        return torch.where(blocked, positions, expected)
    if rule == "no_door_sides":  # stop at the wall's faces, but y may leave the doorway
        return torch.stack([expected[:, 0], target[:, 1]], -1)
    (x0, y0), (x1, y1) = positions.unbind(-1), target.unbind(-1)
    if rule == "side_by_target":  # rule 3 read off the target's y, not where it leaves the slab
        x_lo, x_hi, y_lo, y_hi = wall_bounds(layouts)
        t_in, t_out = _crossing_slip()(x0, x1, x_lo, x_hi)
        doorway = (t_out > t_in) & torch.isclose(expected[:, 0], x1)  # entered, not at a face
        return torch.stack([expected[:, 0], torch.where(doorway, y1.clamp(y_lo, y_hi),
                                                        expected[:, 1])], -1)
    at_face = ~torch.isclose(expected[:, 0], x1)
    t = (expected[:, 0] - x0) / torch.where(at_face, x1 - x0, torch.ones_like(x0))
    y = torch.where(at_face, y0 + t * (y1 - y0), expected[:, 1])
    return torch.stack([expected[:, 0], y], -1)


check_wall_collision = Exercise(
    "wall_collision", wall_collision, dict(
        not_clamped_first=(  # the wall rules on the unclamped target, clamped last or never
            lambda p, m, walls: stop_at_wall(p, p + m, walls).clamp(LOW, HIGH),
            lambda p, m, walls: stop_at_wall(p, p + m, walls)),
        stay_put=partial(_wall_slip, rule="stay_put"),
        stop_at_contact=partial(_wall_slip, rule="stop_at_contact"),  # y stopped at the face
        side_by_target=partial(_wall_slip, rule="side_by_target"),
        no_door_sides=partial(_wall_slip, rule="no_door_sides")),
    _wall_cases, atol=1e-4, explain=_first_problem)
