"""The Two Rooms world (after PLDM, Sobal et al., 2025): 65x65-px arenas cut by W walls with a
door (W=1: Two Rooms, 2: Three Rooms); layouts ``(B, 2W)`` long, ``(wall_x, door_y)`` per wall
left to right; positions ``(x, y)`` float32 px, pixel (row i, column j) centred at (x=j, y=i)."""

from __future__ import annotations

import torch

IMAGE_SIZE = 65
BORDER = 1  # border wall thickness, px
WALL_WIDTH = 3  # middle wall thickness, px: columns wall_x-1 .. wall_x+1
DOOR_HEIGHT = 9  # door opening, px: rows door_y-4 .. door_y+4
DOT_STD = 1.3
DOT_MARGIN = 1.0  # gap kept between the dot centre and any wall pixel, px
MAX_STEP = 1.8  # action bound: the longest step of the data policy, px
LOW = BORDER - 0.5 + DOT_MARGIN  # 1.5, smallest x or y of the dot centre
HIGH = IMAGE_SIZE - BORDER - 0.5 - DOT_MARGIN  # 62.5, largest
WALL_X_RANGES = {1: ((20, 44),), 2: ((14, 25), (39, 50))}  # each wall's centre column, by W


def walls_of(layouts: torch.Tensor) -> torch.Tensor:
    """One ``(wall_x, door_y)`` row per wall, left to right: layouts (B, 2W) -> (B, W, 2)."""
    return layouts.reshape(len(layouts), -1, 2)


def _all_wall_bounds(layouts: torch.Tensor, dtype=torch.float32):
    """:func:`wall_bounds` of every wall: layouts (B, 2W) -> four (B, W) tensors."""
    walls = walls_of(layouts.to(dtype))
    wall_x, door_y = walls[..., 0], walls[..., 1]
    half_wall = WALL_WIDTH / 2 + DOT_MARGIN  # 2.5
    half_door = DOOR_HEIGHT / 2 - DOT_MARGIN  # 3.5
    return wall_x - half_wall, wall_x + half_wall, door_y - half_door, door_y + half_door


def wall_bounds(layouts: torch.Tensor, dtype=torch.float32):
    """Where one wall blocks the dot centre: layouts (B, 2) -> ``x_lo, x_hi, y_lo, y_hi`` (B,).
    ``x_lo < x < x_hi`` is the wall's slab; inside it the centre keeps ``y_lo <= y <= y_hi``."""
    return tuple(b[:, 0] for b in _all_wall_bounds(layouts, dtype))


def in_wall(positions: torch.Tensor, layouts: torch.Tensor) -> torch.Tensor:
    """Whether each dot centre is inside a wall (not the border): (B, 2), (B, 2W) -> (B,) bool."""
    x, y = positions[:, None, 0], positions[:, None, 1]
    x_lo, x_hi, y_lo, y_hi = _all_wall_bounds(layouts.to(positions.device), positions.dtype)
    return ((x > x_lo) & (x < x_hi) & ((y < y_lo) | (y > y_hi))).any(-1)


def wall_collision(positions: torch.Tensor, moves: torch.Tensor, layouts: torch.Tensor):
    """Each dot moved by its displacement, stopped by walls: positions (B, 2), moves (B, 2),
    layouts (B, 2W) -> (B, 2). Exact for moves of x-extent up to 9 px, so for every step of
    :func:`transition`; a longer one is approximated, but never ends in a wall."""
    target = (positions + moves).clamp(LOW, HIGH)
    walls = walls_of(layouts)  # (B, W, 2)
    n = walls.shape[1]
    leftward = (target[:, 0] < positions[:, 0])[:, None]
    for k in range(n):
        wall = torch.where(leftward, walls[:, n - 1 - k], walls[:, k])  # (B, 2)
        target = stop_at_wall(positions, target, wall)
    return target


def stop_at_wall(positions: torch.Tensor, target: torch.Tensor, wall: torch.Tensor):
    """The segment start -> target (B, 2), cut by one wall ``(wall_x, door_y)`` (B, 2): entering
    the slab outside the doorway, x stops at the wall's face and y still moves; leaving the
    door's span inside the slab, y stops at its edge and x still moves."""
    x0, y0 = positions.unbind(-1)
    x1, y1 = target.unbind(-1)
    x_lo, x_hi, y_lo, y_hi = wall_bounds(wall, positions.dtype)
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
    """Actions (..., 2), each longer than ``bound`` shrunk to length ``bound`` in its direction,
    even one whose length overflows the dtype."""
    norm = actions.norm(dim=-1, keepdim=True)
    scale = (bound / norm.clamp_min(1e-12)).clamp(max=1.0)
    largest = actions.abs().amax(dim=-1, keepdim=True)  # an overflowing norm: divide by it first
    unit = actions / largest.clamp_min(torch.finfo(actions.dtype).tiny)
    overflowed = unit * (bound / unit.norm(dim=-1, keepdim=True).clamp_min(1e-12))
    return torch.where(norm.isinf(), overflowed, actions * scale)


def transition(positions: torch.Tensor, actions: torch.Tensor, layouts: torch.Tensor):
    """THE transition of both the offline data and the environment: clip the action to
    ``MAX_STEP``, then move. positions (B, 2), actions (B, 2), layouts (B, 2W) -> (B, 2)."""
    return wall_collision(positions, clip_actions(actions), layouts)


def shortest_path_length(starts: torch.Tensor, goals: torch.Tensor,
                         layouts: torch.Tensor) -> torch.Tensor:
    """Length in px of the dot centre's shortest way: starts, goals (B, 2), layouts (B, 2W) -> (B,)
    Rooms and doorways are convex, so the way is straight between gates, one at each face of
    each slab, tried at 29 rows of the doorway (dynamic programming, gate by gate)."""
    flip = goals[:, 0] < starts[:, 0]  # mirror x so that every way runs left to right
    sign = torch.where(flip, -1.0, 1.0)[:, None]
    x_lo, x_hi, y_lo, y_hi = _all_wall_bounds(layouts.to(starts.device), starts.dtype)
    gate_x = torch.stack([x_lo, x_hi], dim=-1).flatten(1) * sign  # (B, 2W)
    gate_lo, gate_hi = (y.repeat_interleave(2, dim=1) for y in (y_lo, y_hi))
    order = gate_x.argsort(dim=1)  # left to right after the mirror
    gate_x, gate_lo, gate_hi = (g.gather(1, order) for g in (gate_x, gate_lo, gate_hi))
    mirror = torch.cat([sign, torch.ones_like(sign)], 1)
    start, goal = starts * mirror, goals * mirror
    rows = gate_lo[..., None] + (gate_hi - gate_lo)[..., None] * torch.linspace(
        0, 1, 29, device=starts.device, dtype=starts.dtype)  # (B, 2W, P = 29)
    gate = torch.stack([gate_x[..., None].expand_as(rows), rows], dim=-1)  # (B, 2W, P, 2)
    before = (gate_x < start[:, :1])[..., None, None]  # a dot on a face has that gate ahead
    after = (gate_x > goal[:, :1])[..., None, None]
    gate = torch.where(before, start[:, None, None], torch.where(after, goal[:, None, None], gate))
    length = torch.zeros(len(starts), 1, device=starts.device, dtype=starts.dtype)
    here = start[:, None]  # (B, 1, 2): the points reached so far
    for there in [*gate.unbind(1), goal[:, None]]:  # (B, P, 2), then the goal (B, 1, 2)
        step = (here[:, :, None] - there[:, None]).norm(dim=-1)  # (B, here, there)
        length, here = (length[..., None] + step).min(dim=1).values, there
    return length[:, 0]


def room_of(positions: torch.Tensor, layouts: torch.Tensor) -> torch.Tensor:
    """Which room each dot is in, 0 (leftmost) .. W, the walls with ``wall_x < x``: positions
    (B, 2) or (B, T, 2), layouts (B, 2W) -> long (B,) or (B, T)."""
    wall_x = walls_of(layouts)[..., 0].to(positions.dtype)  # (B, W)
    wall_x = wall_x.reshape(len(layouts), *([1] * (positions.dim() - 2)), -1)
    return (positions[..., 0:1] > wall_x).sum(-1)


def wall_images(layouts: torch.Tensor) -> torch.Tensor:
    """The wall channel: layouts (B, 2W) -> (B, 65, 65) float32, 1 on the border and walls."""
    idx = torch.arange(IMAGE_SIZE, device=layouts.device)
    edge = (idx < BORDER) | (idx >= IMAGE_SIZE - BORDER)
    border = edge[:, None] | edge[None, :]  # (H, W)
    walls = walls_of(layouts.long())
    wall_x, door_y = walls[..., 0], walls[..., 1]  # (B, n) each, n walls
    wall_cols = (idx - wall_x[..., None]).abs() <= WALL_WIDTH // 2  # (B, n, W)
    door_rows = (idx - door_y[..., None]).abs() <= DOOR_HEIGHT // 2  # (B, n, H)
    middle = (wall_cols[:, :, None, :] & ~door_rows[:, :, :, None]).any(1)  # (B, H, W)
    return (border | middle).float()


def render(positions: torch.Tensor, layouts: torch.Tensor, out: torch.Tensor | None = None):
    """Images, float32 in [0, 1]: positions (B, 2) -> (B, 2, 65, 65), or (B, T, 2) -> (B, T, 2,
    65, 65), layouts (B, 2W); channel 0 the dot, ``exp(-d^2 / (2 * 1.3^2))`` at distance ``d``
    from the pixel's centre, channel 1 the walls. ``out``: a buffer of that shape to reuse."""
    single = positions.dim() == 2
    pos = positions[:, None] if single else positions
    if out is None:
        out = torch.empty(*positions.shape[:-1], 2, IMAGE_SIZE, IMAGE_SIZE, device=pos.device)
    frames = out[:, None] if single else out
    grid = torch.arange(IMAGE_SIZE, dtype=torch.float32, device=pos.device)
    # the Gaussian is separable: an outer product of a column and a row profile
    gx = torch.exp(-((grid - pos[..., 0:1].float()) ** 2) / (2 * DOT_STD**2))  # (B, T, W)
    gy = torch.exp(-((grid - pos[..., 1:2].float()) ** 2) / (2 * DOT_STD**2))  # (B, T, H)
    torch.matmul(gy[..., :, None], gx[..., None, :], out=frames[:, :, 0])
    frames[:, :, 1] = wall_images(layouts.to(pos.device))[:, None]
    return out


def random_layouts(n: int, generator: torch.Generator, walls: int = 1) -> torch.Tensor:
    """``n`` fresh layouts of ``walls`` walls: (n, 2 * walls) long, each column and door row
    uniform over its range, drawn wall by wall."""
    if walls not in WALL_X_RANGES:
        raise ValueError(f"walls must be 1 (Two Rooms) or 2 (Three Rooms), got {walls!r}")
    columns = []
    for lo, hi in WALL_X_RANGES[walls]:
        columns.append(torch.randint(lo, hi + 1, (n,), generator=generator))
        columns.append(torch.randint(10, 55, (n,), generator=generator))  # door_y in 10..54
    return torch.stack(columns, dim=-1)


def room_floors(layouts: torch.Tensor):
    """Each room's span of dot-centre x: layouts (B, 2W) -> left (B, W+1), width (B, W+1)."""
    x_lo, x_hi, _, _ = _all_wall_bounds(layouts)
    left = torch.cat([torch.full_like(x_hi[:, :1], LOW), x_hi], dim=1)
    right = torch.cat([x_lo, torch.full_like(x_lo[:, :1], HIGH)], dim=1)
    return left, right - left


def sample_positions(layouts: torch.Tensor, generator: torch.Generator, rooms=None):
    """Dot centres uniform over the free floor, never in a doorway: layouts (B, 2W) -> (B, 2);
    ``rooms`` (B,) of 0..W picks each room; None draws over all rooms, by area."""
    left, width = room_floors(layouts.cpu())
    rows = torch.arange(len(layouts))
    u = torch.rand(len(layouts), generator=generator)
    y = LOW + (HIGH - LOW) * torch.rand(len(layouts), generator=generator)
    if rooms is None:
        ends = width.cumsum(dim=1)  # right end of each room on the floor laid end to end
        u = u * ends[:, -1]
        room = (u[:, None] >= ends[:, :-1]).sum(dim=1)
        before = torch.cat([torch.zeros_like(ends[:, :1]), ends[:, :-1]], dim=1)
        x = left[rows, room] + (u - before[rows, room])
    else:
        room = torch.as_tensor(rooms).cpu().long()
        x = left[rows, room] + u * width[rows, room]
    return torch.stack([x, y], dim=-1).to(layouts.device)


def check_world(layouts: torch.Tensor, positions: torch.Tensor) -> None:
    """Raise a clear error unless ``layouts`` are (B, 2W), W = 1 or 2, and ``positions`` (B, 2)
    are dot centres allowed in them."""
    if layouts.shape[1:] not in ((2,), (4,)) or positions.shape != (len(layouts), 2):
        raise ValueError("layouts must have shape (B, 2W), (wall_x, door_y) for each of W = 1 or "
                         f"2 walls, and positions (B, 2); got {tuple(layouts.shape)} and "
                         f"{tuple(positions.shape)}")
    x, y = positions.unbind(-1)
    outside = ~torch.isfinite(positions).all(-1) | (x < LOW) | (x > HIGH) | (y < LOW) | (y > HIGH)
    bad = outside | in_wall(positions, layouts)
    if bad.any():
        i = int(bad.nonzero()[0])
        raise ValueError(f"position {i} = {positions[i].tolist()} is outside the arena "
                         f"[{LOW}, {HIGH}] or inside the wall")
