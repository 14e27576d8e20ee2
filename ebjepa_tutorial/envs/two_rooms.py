"""The Two Rooms world: geometry, the one transition function, rendering.

A batch of B worlds, each a 65x65 arena cut in two by a vertical wall with a
door, after the Two Rooms environment of PLDM (Sobal et al., 2025) that the
EB-JEPA paper plans in.

Coordinates. A position is ``(x, y)`` in pixels, float32: ``x`` is the column
and ``y`` the row of the image (``y`` grows downwards). Pixel ``(row i, column
j)`` has its centre at ``(x=j, y=i)`` and covers ``[j-0.5, j+0.5] x [i-0.5, i+0.5]``.

Walls (image channel 1, value 1 on a wall pixel):

- border: rows and columns 0 and 64;
- the middle wall: columns ``wall_x-1, wall_x, wall_x+1`` (3 px), ``wall_x`` an
  integer in 20..44;
- the door: rows ``door_y-4 .. door_y+4`` (9 px) of the middle wall are open,
  ``door_y`` an integer in 10..54.

A layout is the pair ``(wall_x, door_y)``; a batch of layouts is a long
tensor ``(B, 2)``. The agent (channel 0) is a Gaussian dot of std 1.3 px and
peak 1 at its centre.

Where the dot centre may be: at least ``DOT_MARGIN`` = 1 px from every wall
pixel's edge, so the centre never sits on a wall pixel:

- the arena ``1.5 <= x, y <= 62.5``;
- outside the wall's slab ``wall_x-2.5 < x < wall_x+2.5``, except in the
  doorway, ``door_y-3.5 <= y <= door_y+3.5`` (the 9 px door less the margin).

The rule of motion is :func:`wall_collision`; :func:`transition` adds the
action bound and is the ONE transition function that both the offline data
(``trajectories.py``) and the evaluation environment (``episodes.py``) use.
"""

from __future__ import annotations

import torch

IMAGE_SIZE = 65
BORDER = 1  # border wall thickness, px
WALL_WIDTH = 3  # middle wall thickness, px
DOOR_HEIGHT = 9  # door opening, px
WALL_X_RANGE = (20, 44)  # inclusive range of the wall's centre column
DOOR_Y_RANGE = (10, 54)  # inclusive range of the door's centre row
DOT_STD = 1.3
DOT_MARGIN = 1.0  # gap kept between the dot centre and any wall pixel, px
MAX_STEP = 1.8  # action bound: the longest step of the data policy, px
LOW = BORDER - 0.5 + DOT_MARGIN  # 1.5, smallest x or y of the dot centre
HIGH = IMAGE_SIZE - BORDER - 0.5 - DOT_MARGIN  # 62.5, largest


def wall_bounds(layouts: torch.Tensor, dtype=torch.float32):
    """Where the dot centre is blocked. layouts (B, 2) -> four (B,) tensors.

    ``x_lo < x < x_hi`` is the wall's slab; inside it the centre must keep
    ``y_lo <= y <= y_hi`` (the doorway).
    """
    wall_x, door_y = layouts.to(dtype).unbind(-1)
    half_wall = WALL_WIDTH / 2 + DOT_MARGIN  # 2.5
    half_door = DOOR_HEIGHT / 2 - DOT_MARGIN  # 3.5
    return wall_x - half_wall, wall_x + half_wall, door_y - half_door, door_y + half_door


def wall_collision(positions: torch.Tensor, moves: torch.Tensor, layouts: torch.Tensor):
    """Move each dot by its displacement, stopping at walls.

    positions (B, 2) allowed dot centres, moves (B, 2), layouts (B, 2) -> (B, 2).

    1. Border: each coordinate of ``positions + moves`` is clamped to the arena
       (the dot slides along the border).
    2. Middle wall: follow the segment to that target. If it enters the slab
       outside the doorway, x stops at the wall's face and y still moves. If it
       is in the doorway and would leave the door's span inside the slab (hit
       the door's side), y stops at the span's edge and x still moves.
    The blocked coordinate is clamped, the other one moves freely: a move
    never gets longer, and a move that touches no wall is unchanged.
    """
    target = (positions + moves).clamp(LOW, HIGH)
    x0, y0 = positions.unbind(-1)
    x1, y1 = target.unbind(-1)
    x_lo, x_hi, y_lo, y_hi = wall_bounds(layouts, positions.dtype)
    # times t in [0, 1] at which x0 + t * (x1 - x0) is inside the slab
    dx = x1 - x0
    still = dx == 0
    safe_dx = torch.where(still, torch.ones_like(dx), dx)
    t_a, t_b = (x_lo - x0) / safe_dx, (x_hi - x0) / safe_dx
    t_in = torch.where(still, 0.0, torch.minimum(t_a, t_b).clamp(0, 1))
    in_slab = ((x0 > x_lo) & (x0 < x_hi)).to(dx.dtype)
    t_out = torch.where(still, in_slab, torch.maximum(t_a, t_b).clamp(0, 1))
    y_in, y_out = y0 + t_in * (y1 - y0), y0 + t_out * (y1 - y0)
    touches = t_out > t_in
    hits_face = touches & ((y_in < y_lo) | (y_in > y_hi))
    hits_side = touches & ~hits_face & ((y_out < y_lo) | (y_out > y_hi))
    x = torch.where(hits_face, torch.where(x0 <= x_lo, x_lo, x_hi), x1)
    y = torch.where(hits_side, torch.clamp(y1, y_lo, y_hi), y1)
    # rounding must never leave the centre inside the wall
    y = torch.where((x > x_lo) & (x < x_hi), torch.clamp(y, y_lo, y_hi), y)
    return torch.stack([x, y], dim=-1)


def clip_actions(actions: torch.Tensor, bound: float = MAX_STEP) -> torch.Tensor:
    """Shrink every action longer than ``bound`` to length ``bound``, same direction.

    actions (..., 2) -> (..., 2). Clipping is on the Euclidean norm (a disc),
    because the data policy's steps fill exactly that disc; a planner that
    samples in a box should clip with this too, to stay where the data was.
    A finite action whose length overflows the dtype (its squares are infinite)
    still becomes a step of length ``bound`` in its direction.
    """
    norm = actions.norm(dim=-1, keepdim=True)
    scale = (bound / norm.clamp_min(1e-12)).clamp(max=1.0)
    # Only rows whose length overflowed take the slower rescaled path, so every
    # other action is clipped exactly as before.
    return torch.where(norm.isinf(), _step_of_length(actions, bound), actions * scale)


def _step_of_length(actions: torch.Tensor, length: float) -> torch.Tensor:
    """Each action (..., 2) rescaled to ``length``, safe for huge finite components.

    Dividing by the largest component first keeps the norm in [1, sqrt(2)], so
    squaring cannot overflow; the clamp keeps a zero action from giving 0 / 0.
    """
    largest = actions.abs().amax(dim=-1, keepdim=True)
    unit = actions / largest.clamp_min(torch.finfo(actions.dtype).tiny)
    return unit * (length / unit.norm(dim=-1, keepdim=True).clamp_min(1e-12))


def transition(positions: torch.Tensor, actions: torch.Tensor, layouts: torch.Tensor):
    """THE transition of Two Rooms: clip the action to ``MAX_STEP``, then move.

    positions (B, 2), actions (B, 2), layouts (B, 2) -> next positions (B, 2).
    No input checks (the data generator calls it in a loop); see :func:`step`.
    """
    return wall_collision(positions, clip_actions(actions), layouts)


def step(positions: torch.Tensor, actions: torch.Tensor, layouts: torch.Tensor):
    """:func:`transition` with checked inputs: clear errors for wrong shapes or NaN."""
    check_layouts(layouts)
    check_positions(positions, layouts)
    check_actions(actions, len(positions), positions.dtype)
    return transition(positions, actions.to(positions.dtype), layouts)


def room_of(positions: torch.Tensor, layouts: torch.Tensor) -> torch.Tensor:
    """Which room each dot is in, 0 left, 1 right (a dot in the doorway counts by x > wall_x).

    positions (B, 2) or (B, T, 2), layouts (B, 2) -> long (B,) or (B, T).
    """
    wall_x = layouts[:, 0].to(positions.dtype)
    wall_x = wall_x.view(-1, *([1] * (positions.dim() - 2)))
    return (positions[..., 0] > wall_x).long()


def wall_images(layouts: torch.Tensor) -> torch.Tensor:
    """The wall channel: layouts (B, 2) -> (B, 65, 65) float32, 1 on walls."""
    idx = torch.arange(IMAGE_SIZE, device=layouts.device)
    edge = (idx < BORDER) | (idx >= IMAGE_SIZE - BORDER)
    border = edge[:, None] | edge[None, :]  # (H, W)
    wall_x, door_y = layouts.long().unbind(-1)
    wall_cols = (idx[None, :] - wall_x[:, None]).abs() <= WALL_WIDTH // 2  # (B, W)
    door_rows = (idx[None, :] - door_y[:, None]).abs() <= DOOR_HEIGHT // 2  # (B, H)
    middle = wall_cols[:, None, :] & ~door_rows[:, :, None]
    return (border | middle).float()


def render(positions: torch.Tensor, layouts: torch.Tensor, out: torch.Tensor | None = None):
    """Images of dots and walls, float32 in [0, 1].

    positions (B, 2) -> (B, 2, 65, 65), or (B, T, 2) -> (B, T, 2, 65, 65);
    layouts (B, 2). Channel 0: the dot, ``exp(-d^2 / (2 * 1.3^2))`` with ``d``
    the distance from pixel centre to dot centre. Channel 1: the walls.
    ``out``: an optional float32 tensor of the result's shape to write into;
    reusing one buffer per batch is about 3x faster than fresh memory.
    """
    single = positions.dim() == 2
    pos = positions[:, None] if single else positions
    shape = (*pos.shape[:2], 2, IMAGE_SIZE, IMAGE_SIZE)
    wanted = shape[:1] + shape[2:] if single else shape
    if out is None:
        out = torch.empty(wanted, device=pos.device)
    elif tuple(out.shape) != wanted or out.dtype != torch.float32:
        raise ValueError(f"out is {out.dtype} {tuple(out.shape)}; render needs float32 {wanted}")
    frames = out[:, None] if single else out
    grid = torch.arange(IMAGE_SIZE, dtype=torch.float32, device=pos.device)
    # the Gaussian is separable: an outer product of a column and a row profile
    gx = torch.exp(-((grid - pos[..., 0:1].float()) ** 2) / (2 * DOT_STD**2))  # (B, T, W)
    gy = torch.exp(-((grid - pos[..., 1:2].float()) ** 2) / (2 * DOT_STD**2))  # (B, T, H)
    torch.matmul(gy[..., :, None], gx[..., None, :], out=frames[:, :, 0])
    frames[:, :, 1] = wall_images(layouts.to(pos.device))[:, None]
    return out


def as_generator(seed) -> torch.Generator:
    """A ``torch.Generator`` from an int seed, or the generator itself."""
    if isinstance(seed, torch.Generator):
        return seed
    if not isinstance(seed, int) or isinstance(seed, bool):
        raise TypeError(
            f"seed must be an int (or a torch.Generator), got {type(seed).__name__} {seed!r}"
        )
    return torch.Generator().manual_seed(seed)


def random_layouts(n: int, generator: torch.Generator) -> torch.Tensor:
    """``n`` fresh layouts, uniform over wall_x in 20..44 and door_y in 10..54: (n, 2) long."""
    wall_x = torch.randint(WALL_X_RANGE[0], WALL_X_RANGE[1] + 1, (n,), generator=generator)
    door_y = torch.randint(DOOR_Y_RANGE[0], DOOR_Y_RANGE[1] + 1, (n,), generator=generator)
    return torch.stack([wall_x, door_y], dim=-1)


def sample_positions(layouts: torch.Tensor, generator: torch.Generator, rooms=None):
    """Dot centres uniform over the free floor: layouts (B, 2) -> (B, 2) float32.

    ``rooms`` (B,) of 0 (left) / 1 (right) picks the room; None draws uniformly
    over both rooms (by area). Never in the doorway.
    """
    x_lo, x_hi, _, _ = wall_bounds(layouts.cpu())
    width_left, width_right = x_lo - LOW, HIGH - x_hi
    u = torch.rand(len(layouts), generator=generator)
    y = LOW + (HIGH - LOW) * torch.rand(len(layouts), generator=generator)
    if rooms is None:
        u = u * (width_left + width_right)
        x = torch.where(u < width_left, LOW + u, x_hi + (u - width_left))
    else:
        right = torch.as_tensor(rooms).cpu().bool()
        x = torch.where(right, x_hi + u * width_right, LOW + u * width_left)
    return torch.stack([x, y], dim=-1).to(layouts.device)


def check_layouts(layouts) -> None:
    """Raise a clear error unless ``layouts`` is a (B, 2) tensor of allowed (wall_x, door_y)."""
    if not isinstance(layouts, torch.Tensor):
        raise TypeError(f"layouts must be a torch tensor (B, 2), got {type(layouts).__name__}")
    if layouts.dim() != 2 or layouts.shape[1] != 2:
        raise ValueError(
            f"layouts must have shape (B, 2) = (wall_x, door_y), got {tuple(layouts.shape)}"
        )
    if layouts.is_floating_point() and not torch.equal(layouts, layouts.round()):
        raise ValueError("layouts must hold whole pixel numbers; use random_layouts(n, generator)")
    for column, name, (lo, hi) in ((0, "wall_x", WALL_X_RANGE), (1, "door_y", DOOR_Y_RANGE)):
        values = layouts[:, column]
        if len(values) and (values.min() < lo or values.max() > hi):
            bad = values[(values < lo) | (values > hi)][0].item()
            raise ValueError(f"{name}={bad} is outside the allowed range {lo}..{hi}")


def check_positions(positions, layouts: torch.Tensor) -> None:
    """Raise a clear error unless ``positions`` (B, 2) are allowed dot centres for ``layouts``."""
    if not isinstance(positions, torch.Tensor) or positions.shape != (len(layouts), 2):
        shape = tuple(positions.shape) if isinstance(positions, torch.Tensor) else type(positions)
        raise ValueError(f"positions must be a tensor of shape ({len(layouts)}, 2), got {shape}")
    x, y = positions.unbind(-1)
    x_lo, x_hi, y_lo, y_hi = wall_bounds(layouts.to(positions.device), positions.dtype)
    outside = ~torch.isfinite(positions).all(-1) | (x < LOW) | (x > HIGH) | (y < LOW) | (y > HIGH)
    in_wall = (x > x_lo) & (x < x_hi) & ((y < y_lo) | (y > y_hi))
    problems = ((outside, f"outside the arena [{LOW}, {HIGH}]"), (in_wall, "inside the wall"))
    for mask, where in problems:
        if mask.any():
            i = int(mask.nonzero()[0])
            raise ValueError(f"position {i} = {positions[i].tolist()} is {where}")


def check_actions(actions, batch: int, dtype: torch.dtype | None = None) -> None:
    """Raise a clear error unless ``actions`` is a finite (batch, 2) tensor.

    ``dtype``: the type the world will move in (the positions'). Finiteness is
    checked after the cast to it, because a float64 action can be finite and
    still overflow to infinity in float32.
    """
    if not isinstance(actions, torch.Tensor):
        kind = type(actions).__name__
        raise TypeError(f"actions must be a torch tensor ({batch}, 2), got {kind}")
    if actions.shape != (batch, 2):
        raise ValueError(
            f"actions must have shape ({batch}, 2), one (dx, dy) per world; "
            f"got {tuple(actions.shape)}"
        )
    if not torch.isfinite(actions).all():
        raise ValueError("actions contain NaN or infinite values; check the planner's output")
    overflow = ~torch.isfinite(actions.to(dtype)).all(-1) if dtype is not None else None
    if overflow is not None and overflow.any():
        i = int(overflow.nonzero()[0])
        raise ValueError(
            f"action {i} = {actions[i].tolist()} is too large for {dtype} (largest "
            f"{torch.finfo(dtype).max:.3g}) and would become infinite; any step longer than "
            f"{MAX_STEP} px is clipped to it, so send a smaller action in the same direction"
        )
