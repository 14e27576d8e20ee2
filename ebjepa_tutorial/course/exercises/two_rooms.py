"""Checker of chapter 04: "write the wall-collision check for one step".

``check_wall_collision(fn)`` runs the learner's ``fn(positions, moves,
layouts) -> new positions`` and the reference :func:`wall_collision` on the
same cases (through the door, into the wall, into the door's side, into the
border, free moves, random ones, huge ones) and says in plain words what went
wrong first: leaving the arena, passing through the wall, ending inside it,
stopping at an open door, or any other disagreement with the reference rule;
then, if the learner's positions match a typical wrong rule on that case
(cancelling the whole move, no sliding along the wall, no door sides), it
names that rule.
"""

from __future__ import annotations

import torch

from ...envs.two_rooms import (
    HIGH,
    LOW,
    random_layouts,
    sample_positions,
    wall_bounds,
    wall_collision,
)
from .common import Case, ExerciseError, diagnose, exercise, not_implemented


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


def _first_problem(desc, pos, move, layouts, got, expected) -> str | None:
    """A plain-words message about the first wrong output, or None if all agree."""
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
    checks = [
        ~torch.isfinite(got).all(-1),
        ((got < LOW - tol) | (got > HIGH + tol)).any(-1),
        crossed & ~ref_crossed & ((y_cross < y_lo - tol) | (y_cross > y_hi + tol)),
        (x1 > x_lo + tol) & (x1 < x_hi - tol) & ((y1 < y_lo - tol) | (y1 > y_hi + tol)),
        stopped_at_door,
        ~torch.isclose(got, expected, atol=1e-4, rtol=0).all(-1),
    ]
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
            f"stay in [{LOW}, {HIGH}] in x and y), {at}.",
            f"your function let the dot pass through the wall at y={y_cross[i]:.1f} where {door}; "
            f"{at} it ended at {got_i}.",
            f"your function left the dot centre inside the wall at {got_i} (the slab "
            f"{x_lo[i]:.1f} < x < {x_hi[i]:.1f} is open only for {y_lo[i]:.1f} <= y <= "
            f"{y_hi[i]:.1f}), {at}.",
            f"your function stopped the dot at the wall, but the door is open there: {door}; "
            f"{at} the reference goes on to {exp_i}, yours stopped at {got_i}.",
            f"your function gave {got_i} but the reference gives {exp_i}, {at}. The rule: clamp "
            "the target to the arena; stop only the blocked coordinate (x at the wall's face, "
            "or y at the door's edge) and let the other one move.",
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


_WALL_SLIPS = [
    ("you cancel the whole move when the wall blocks it; stop only the blocked coordinate "
     "(x at the wall's face) and let the other one (y) slide on.", _stay_put),
    ("you stop the dot where its path meets the wall's face, y included; only x stops there: "
     "y still moves the whole way (the dot slides along the wall).", _stop_at_contact),
    ("you handled the wall's faces but not the door's sides: a move that enters the doorway "
     "and would leave its span inside the slab must stop y at the door's edge (y_lo or y_hi).",
     _no_door_sides),
]


@exercise(wall_collision, _WALL_SLIPS)
def check_wall_collision(fn, n: int = 512, seed: int = 0) -> bool:
    """Compare ``fn(positions, moves, layouts)`` with the reference; print a verdict or raise
    :class:`~ebjepa_tutorial.course.exercises.ExerciseError` (an AssertionError) saying
    which case failed and how."""
    name = getattr(fn, "__name__", "your function")
    cases = _cases(seed, n)
    for desc, pos, move, layouts in cases:
        expected = wall_collision(pos, move, layouts)
        try:
            got = fn(pos.clone(), move.clone(), layouts.clone())
        except NotImplementedError:
            raise not_implemented(name) from None
        except Exception as err:
            raise ExerciseError(f"{name} raised {type(err).__name__}: {err} on {desc}.") from err
        if not isinstance(got, torch.Tensor) or got.shape != expected.shape:
            shape = tuple(got.shape) if isinstance(got, torch.Tensor) else type(got).__name__
            raise ExerciseError(
                f"{name} returned {shape} on {desc}; it should return new positions of shape "
                f"{tuple(expected.shape)}, one (x, y) per world."
            )
        problem = _first_problem(desc, pos, move, layouts, got.detach().float(), expected)
        if problem:
            why = diagnose(got.detach().float(), _WALL_SLIPS, Case(desc, (pos, move, layouts)),
                           atol=1e-3)
            raise ExerciseError(problem.replace("your function", name, 1) + why)
    print(f"Correct: {name} matches the reference wall collision on {n * len(cases)} moves.")
    return True
