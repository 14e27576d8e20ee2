"""Offline Two Rooms trajectories from the paper's data policy, generated in batches: a random
walk whose heading turns by von Mises(0, ``kappa``) steps and whose step lengths are truncated
normals, moved by :func:`~ebjepa_tutorial.envs.two_rooms.transition`."""

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
    random_layouts,
    render,
    room_of,
    sample_positions,
    transition,
    walls_of,
)


def sample_von_mises(kappa: float, shape, generator: torch.Generator) -> torch.Tensor:
    """Angles from a von Mises with mean 0 and concentration ``kappa`` > 0: float32 ``shape``.
    Best and Fisher's (1979) rejection sampler, in bulk until enough are accepted."""
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


def in_front_of_a_wall(layouts: torch.Tensor, generator: torch.Generator):
    """A column 0.5 to 4 px in front of one wall (of the W, at random), on a random side:
    layouts (B, 2W) -> wall_x, door_y, x, side (-1 left of the wall, +1 right), each (B,)."""
    n, walls = len(layouts), walls_of(layouts)
    if walls.shape[1] > 1:  # with one wall nothing is drawn: Two Rooms data keep their draws
        pick = torch.randint(0, walls.shape[1], (n,), generator=generator)
        layouts = walls[torch.arange(n), pick]
    wall_x, door_y = layouts.float().unbind(-1)
    side = torch.randint(0, 2, (n,), generator=generator).float() * 2 - 1
    gap = 0.5 + 3.5 * torch.rand(n, generator=generator)  # px from the wall's face
    return wall_x, door_y, wall_x + side * (WALL_WIDTH / 2 + DOT_MARGIN + gap), side


def door_starts(layouts: torch.Tensor, generator: torch.Generator):
    """Starts in front of a door, within 2 px of its centre row, aimed at it: layouts (B, 2W)
    -> positions (B, 2), headings (B,)."""
    wall_x, door_y, x, _ = in_front_of_a_wall(layouts, generator)
    y = door_y + 4 * torch.rand(len(layouts), generator=generator) - 2
    heading = torch.atan2(door_y - y, wall_x - x)
    return torch.stack([x, y], dim=-1), heading


def wall_starts(layouts: torch.Tensor, generator: torch.Generator):
    """Starts in front of a wall, on a row at least 6 px from its door, heading at it within 60
    degrees of straight on: layouts (B, 2W) -> positions (B, 2), headings (B,)."""
    n = len(layouts)
    wall_x, door_y, x, side = in_front_of_a_wall(layouts, generator)
    # rows beyond the door's edge (door_y +- 4.5) by 6 px, up to the arena's edge
    above, below = (door_y - 10.5 - LOW).clamp_min(0), (HIGH - door_y - 10.5).clamp_min(0)
    u = torch.rand(n, generator=generator) * (above + below)
    y = torch.where(u < above, LOW + u, door_y + 10.5 + (u - above))
    straight_on = torch.where(side > 0, math.pi, 0.0)  # from the right room, head left
    heading = straight_on + (torch.rand(n, generator=generator) * 2 - 1) * math.pi / 3
    return torch.stack([x, y], dim=-1), heading


@dataclass
class Trajectories:
    """N trajectories of T+1 frames: positions (N, T+1, 2) float32, actions (N, T, 2) float32
    (action t moves frame t to t+1), layouts (N, 2W) long, door (N,) bool (a door start)."""

    positions: torch.Tensor
    actions: torch.Tensor
    layouts: torch.Tensor
    door: torch.Tensor

    def __len__(self) -> int:
        return len(self.positions)

    def frames(self, index=slice(None), out: torch.Tensor | None = None) -> torch.Tensor:
        """Render the selected trajectories: (n, T+1, 2, 65, 65) float32; ``out``: a buffer."""
        index = [index] if isinstance(index, int) else index  # one trajectory: n = 1
        return render(self.positions[index], self.layouts[index], out=out)

    def changes_room(self) -> torch.Tensor:
        """Whether the last frame is in another room than the first: (N,) bool."""
        rooms = room_of(self.positions[:, [0, -1]], self.layouts)
        return rooms[:, 0] != rooms[:, 1]

    def __getitem__(self, index) -> Trajectories:
        return Trajectories(self.positions[index], self.actions[index], self.layouts[index],
                            self.door[index])


def generate_trajectories(n: int, steps: int = 16, seed=0, door_fraction: float = 0.35,
                          wall_fraction: float = 0.0, kappa: float = 5.0, step_mean: float = 1.0,
                          walls: int = 1, layouts: torch.Tensor | None = None) -> Trajectories:
    """``n`` random walks of ``steps`` actions (``steps + 1`` frames), in fresh layouts of
    ``walls`` walls or in ``layouts`` (n, 2W); ``seed``: an int or a torch.Generator. Of them,
    ``round(door_fraction * n)`` start at a door, up to ``round(wall_fraction * n)`` at a wall."""
    if not (0 <= door_fraction and 0 <= wall_fraction and door_fraction + wall_fraction <= 1
            and kappa > 0):
        raise ValueError("door_fraction and wall_fraction must be >= 0 with a sum <= 1, and kappa "
                         f"> 0; got {door_fraction}, {wall_fraction} and {kappa}")
    if layouts is not None and len(layouts) != n:
        raise ValueError(f"layouts must hold one layout per trajectory, n = {n}; "
                         f"got {len(layouts)}")
    generator = as_generator(seed)  # the draws' order made the shipped models' data: keep it
    layouts = random_layouts(n, generator, walls) if layouts is None else layouts
    start, heading, door = random_starts(layouts, door_fraction, wall_fraction, generator)
    actions = random_walk(heading, steps, kappa, step_mean, generator)
    return Trajectories(roll_out(start, actions, layouts), actions, layouts, door)


def random_starts(layouts: torch.Tensor, door_fraction: float, wall_fraction: float,
                  generator: torch.Generator):
    """Start positions (n, 2), first headings (n,) and which start at a door (n,) bool."""
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
    """The policy's actions (n, steps, 2) from first headings (n,): each heading turns by a von
    Mises(0, ``kappa``) increment; step lengths are normal(step_mean, 0.4) cut to 0.2..1.8 px."""
    n = len(heading)
    turns = sample_von_mises(kappa, (n, steps - 1), generator)
    headings = heading[:, None] + torch.cat([torch.zeros(n, 1), turns.cumsum(dim=1)], dim=1)
    lengths = sample_truncated_normal(step_mean, 0.4, 0.2, 1.8, (n, steps), generator)
    return lengths[..., None] * torch.stack([headings.cos(), headings.sin()], dim=-1)


def roll_out(start: torch.Tensor, actions: torch.Tensor, layouts: torch.Tensor) -> torch.Tensor:
    """Positions (n, T+1, 2) from ``start`` (n, 2) under ``actions`` (n, T, 2)."""
    positions = [start]
    for action in actions.unbind(1):
        positions.append(transition(positions[-1], action, layouts))
    return torch.stack(positions, dim=1)
