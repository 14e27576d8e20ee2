"""Offline Two Rooms trajectories from the paper's data policy, generated in batches.

The policy is a persistent random walk: the heading turns each step by a von
Mises increment (concentration ``kappa`` = 5, so consecutive headings agree
with mean cosine I1(5)/I0(5) = 0.893), and the step length is a normal (mean 1,
std 0.4) truncated to [0.2, 1.8]. The action is the intended displacement
``length * (cos heading, sin heading)``; the dot moves by
:func:`~ebjepa_tutorial.envs.two_rooms.transition`, the same function the
evaluation environment uses, so a wall may stop part of the move.

Starts. A fraction ``door_fraction`` (35%) of trajectories is built to go
through the door: the dot starts on a random side, 0.5 to 4 px in front of
the wall's face (where the slab its centre may not enter begins), within 2 px
of the door's centre row, with its first heading aimed at the door's centre.
With kappa 5, most of these cross at least once and end in the other room
(the rest drift into the door's side or turn back). The other trajectories
start uniformly on the free floor with a uniform heading and rarely change
rooms, so the data holds crossings without being made of them (notebook 04
counts them). Each trajectory gets a fresh layout.

Rooms in a row (``walls=2``, Three Rooms): the same policy and starts, a door
or wall start picking one of the walls at random per trajectory. With
``walls=1`` no such pick is drawn, so Two Rooms data stay bit for bit as they were.

Trajectories are stored compactly (positions, actions, layouts); render the
frames on demand, in batches, with :meth:`Trajectories.frames`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ..utils import as_generator
from .two_rooms import (
    DOT_MARGIN,
    HIGH,
    LOW,
    WALL_WIDTH,
    check_layouts,
    random_layouts,
    render,
    room_of,
    sample_positions,
    transition,
    wall_count,
    walls_of,
)

STEP_STD, STEP_RANGE = 0.4, (0.2, 1.8)  # the step length's normal: std and truncation, px


def sample_von_mises(kappa: float, shape, generator: torch.Generator) -> torch.Tensor:
    """Angles from a von Mises with mean 0 and concentration ``kappa`` > 0: float32 ``shape``.

    Best and Fisher's (1979) rejection sampler, vectorised: draw candidates in
    bulk, keep the accepted ones, repeat until enough (about 1.1 rounds at
    kappa 5). Deterministic given the generator.
    """
    if kappa <= 0:
        raise ValueError(f"kappa must be positive, got {kappa}")
    n = math.prod(shape)
    tau = 1 + math.sqrt(1 + 4 * kappa**2)
    rho = (tau - math.sqrt(2 * tau)) / (2 * kappa)
    r = (1 + rho**2) / (2 * rho)
    out, filled = torch.empty(n), 0
    while filled < n:
        m = int(1.2 * (n - filled)) + 16
        u1, u2, u3 = torch.rand(3, m, generator=generator, dtype=torch.float64)
        z = torch.cos(math.pi * u1)
        f = (1 + r * z) / (r + z)
        c = kappa * (r - f)
        accept = (c * (2 - c) > u2) | (torch.log(c / u2) + 1 - c >= 0)
        theta = torch.sign(u3 - 0.5) * torch.acos(f.clamp(-1, 1))
        theta = theta[accept][: n - filled]
        out[filled : filled + len(theta)] = theta.float()
        filled += len(theta)
    return out.view(*shape)


def sample_truncated_normal(mean, std, low, high, shape, generator) -> torch.Tensor:
    """Normal(mean, std) restricted to [low, high], by inverse CDF: float32 ``shape``."""
    normal = torch.distributions.Normal(torch.tensor(0.0, dtype=torch.float64), 1.0)
    a = normal.cdf(torch.tensor((low - mean) / std))
    b = normal.cdf(torch.tensor((high - mean) / std))
    u = a + (b - a) * torch.rand(shape, generator=generator, dtype=torch.float64)
    return (mean + std * torch.special.ndtri(u)).clamp(low, high).float()


def in_front_of_the_wall(wall_x: torch.Tensor, generator: torch.Generator):
    """Columns 0.5 to 4 px in front of the middle wall's face, on a random side.

    wall_x (B,) float -> x (B,), side (B,): -1 left of the wall, +1 right.
    """
    n = len(wall_x)
    side = torch.randint(0, 2, (n,), generator=generator).float() * 2 - 1
    gap = 0.5 + 3.5 * torch.rand(n, generator=generator)  # px from the wall's face
    return wall_x + side * (WALL_WIDTH / 2 + DOT_MARGIN + gap), side


def one_wall_each(layouts: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """One wall per row, uniform over its W walls: layouts (B, 2W) -> (B, 2) (wall_x, door_y).

    With one wall, the layouts themselves and nothing drawn, so that Two Rooms
    data keep their random stream.
    """
    walls = wall_count(layouts)
    if walls == 1:
        return layouts
    pick = torch.randint(0, walls, (len(layouts),), generator=generator)
    rows = torch.arange(len(layouts))
    return walls_of(layouts)[rows, pick]


def door_starts(layouts: torch.Tensor, generator: torch.Generator):
    """Starts in front of a door (one of the walls' at random), aimed at it.

    layouts (B, 2W) -> positions (B, 2), headings (B,) in radians.
    """
    n = len(layouts)
    wall_x, door_y = one_wall_each(layouts, generator).float().unbind(-1)
    x, _ = in_front_of_the_wall(wall_x, generator)
    y = door_y + 4 * torch.rand(n, generator=generator) - 2
    heading = torch.atan2(door_y - y, wall_x - x)
    return torch.stack([x, y], dim=-1), heading


def wall_starts(layouts: torch.Tensor, generator: torch.Generator):
    """Starts in front of a wall (one at random), away from its door, heading into it.

    layouts (B, 2W) -> positions (B, 2), headings (B,) in radians. The dot starts
    0.5 to 4 px from the wall's face on a random side, on a row at least 6 px
    from the door's edge, and heads at the wall within 60 degrees of straight on,
    so most of these trajectories are stopped by the wall in their first steps.
    """
    n = len(layouts)
    wall_x, door_y = one_wall_each(layouts, generator).float().unbind(-1)
    x, side = in_front_of_the_wall(wall_x, generator)
    # rows beyond the door's edge (door_y +- 4.5) by 6 px, up to the arena's edge
    above, below = (door_y - 10.5 - LOW).clamp_min(0), (HIGH - door_y - 10.5).clamp_min(0)
    u = torch.rand(n, generator=generator) * (above + below)
    y = torch.where(u < above, LOW + u, door_y + 10.5 + (u - above))
    straight_on = torch.where(side > 0, math.pi, 0.0)  # from the right room, head left
    heading = straight_on + (torch.rand(n, generator=generator) * 2 - 1) * math.pi / 3
    return torch.stack([x, y], dim=-1), heading


@dataclass
class Trajectories:
    """N trajectories of T+1 frames.

    positions (N, T+1, 2) float32, actions (N, T, 2) float32 (action t moves
    frame t to frame t+1), layouts (N, 2W) long (W walls), door (N,) bool: built
    to go through a door.
    """

    positions: torch.Tensor
    actions: torch.Tensor
    layouts: torch.Tensor
    door: torch.Tensor

    def __len__(self) -> int:
        return len(self.positions)

    def frames(self, index=slice(None), out: torch.Tensor | None = None) -> torch.Tensor:
        """Render the selected trajectories: (n, T+1, 2, 65, 65) float32 in [0, 1].

        ``out``: an optional buffer of that shape to reuse from batch to batch.
        """
        return render(self.positions[index], self.layouts[index], out=out)

    def changes_room(self) -> torch.Tensor:
        """Whether the last frame is in another room than the first: (N,) bool."""
        rooms = room_of(self.positions[:, [0, -1]], self.layouts)
        return rooms[:, 0] != rooms[:, 1]

    def __getitem__(self, index) -> Trajectories:
        return Trajectories(
            self.positions[index], self.actions[index], self.layouts[index], self.door[index]
        )


def generate_trajectories(
    n: int,
    steps: int = 16,
    seed=0,
    door_fraction: float = 0.35,
    wall_fraction: float = 0.0,
    kappa: float = 5.0,
    step_mean: float = 1.0,
    walls: int = 1,
    layouts: torch.Tensor | None = None,
) -> Trajectories:
    """``n`` random-walk trajectories of ``steps`` actions (``steps + 1`` frames).

    ``seed``: an int or a torch.Generator. Exactly ``round(door_fraction * n)``
    trajectories start at the door (chosen at random), and ``round(wall_fraction * n)``
    of the others in front of the middle wall, heading into it (:func:`wall_starts`).
    ``walls``: 1 for Two Rooms, 2 for Three Rooms (a door or wall start then
    faces one of the two walls, picked at random per trajectory). ``layouts``: one
    layout per trajectory ``(n, 2W)`` instead of fresh random ones (then ``walls`` is theirs).
    The draws come in a fixed order (layouts, starts, turns, step lengths): the
    shipped models were trained on these exact trajectories.
    """
    if not isinstance(n, int) or n < 1 or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"n and steps must be positive ints, got n={n!r}, steps={steps!r}")
    if not (0 <= door_fraction and 0 <= wall_fraction and door_fraction + wall_fraction <= 1):
        raise ValueError("door_fraction and wall_fraction must be >= 0 with a sum <= 1, got "
                         f"{door_fraction} and {wall_fraction}")
    generator = as_generator(seed)
    if layouts is None:
        layouts = random_layouts(n, generator, walls)
    elif layouts.shape[0] != n:
        raise ValueError(f"layouts must hold one layout per trajectory, ({n}, 2W); got "
                         f"{tuple(layouts.shape)}")
    else:
        check_layouts(layouts)
    start, heading, door = random_starts(layouts, door_fraction, wall_fraction, generator)
    actions = random_walk(heading, steps, kappa, step_mean, generator)
    return Trajectories(roll_out(start, actions, layouts), actions, layouts, door)


def random_starts(layouts: torch.Tensor, door_fraction: float, wall_fraction: float,
                  generator: torch.Generator):
    """Start positions (n, 2), first headings (n,) and which start at a door (n,) bool.

    Uniform on the floor with a uniform heading, except ``round(door_fraction * n)``
    door starts (:func:`door_starts`) and ``round(wall_fraction * n)`` of the others
    wall starts (:func:`wall_starts`).
    """
    n = len(layouts)
    door = torch.zeros(n, dtype=torch.bool)
    door[torch.randperm(n, generator=generator)[: round(door_fraction * n)]] = True
    start = sample_positions(layouts, generator)
    heading = 2 * math.pi * torch.rand(n, generator=generator)
    door_start, door_heading = door_starts(layouts, generator)
    start = torch.where(door[:, None], door_start, start)
    heading = torch.where(door, door_heading, heading)
    if wall_fraction:  # drawn last, so that without it the data is unchanged
        others = (~door).nonzero().squeeze(1)
        wall = others[torch.randperm(len(others), generator=generator)[: round(wall_fraction * n)]]
        start[wall], heading[wall] = wall_starts(layouts[wall], generator)
    return start, heading, door


def random_walk(heading: torch.Tensor, steps: int, kappa: float, step_mean: float,
                generator: torch.Generator) -> torch.Tensor:
    """The policy's actions (n, steps, 2) from first headings (n,): each heading turns
    by a von Mises(0, ``kappa``) increment, each step length is a truncated normal."""
    n = len(heading)
    turns = sample_von_mises(kappa, (n, steps - 1), generator)
    headings = heading[:, None] + torch.cat([torch.zeros(n, 1), turns.cumsum(dim=1)], dim=1)
    lengths = sample_truncated_normal(step_mean, STEP_STD, *STEP_RANGE, (n, steps), generator)
    return lengths[..., None] * torch.stack([headings.cos(), headings.sin()], dim=-1)


def roll_out(start: torch.Tensor, actions: torch.Tensor, layouts: torch.Tensor) -> torch.Tensor:
    """Positions (n, T+1, 2) from ``start`` (n, 2) under ``actions`` (n, T, 2), by
    :func:`transition`, the one rule of motion the environment uses too."""
    positions = torch.empty(len(start), actions.shape[1] + 1, 2)
    positions[:, 0] = start
    for t in range(actions.shape[1]):
        positions[:, t + 1] = transition(positions[:, t], actions[:, t], layouts)
    return positions
