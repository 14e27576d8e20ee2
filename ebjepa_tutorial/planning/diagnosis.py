"""Is it the predictor or the energy that fails? The energy's pictures (:func:`energy_map`,
:func:`energy_by_distance`) and :class:`TrueDynamics`, a perfect predictor for
``run_episodes(..., world="true")`` (the learned energy) or ``"true_xy"`` (pixels)."""

from __future__ import annotations

import math
from types import SimpleNamespace

import torch

from ..envs import Episodes, TwoRoomsEnv
from ..envs.two_rooms import HIGH, LOW, in_wall, render, transition


def dot_grid(spacing: float = 1.0, device=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Dot positions every ``spacing`` px over the arena: ``coords (G,)``, ``xy (G*G, 2)``;
    row ``i * G + j`` of ``xy`` is ``(x=coords[j], y=coords[i])``: image order."""
    coords = torch.arange(LOW, HIGH + 1e-6, spacing, device=device)
    ys, xs = torch.meshgrid(coords, coords, indexing="ij")
    return coords, torch.stack([xs.flatten(), ys.flatten()], dim=1)


def _states(positions: torch.Tensor) -> torch.Tensor:
    """``(B, 2)`` positions -> ``(B, 3)`` states ``[episode, x, y]``, episode b in row b."""
    rows = torch.arange(len(positions), device=positions.device, dtype=positions.dtype)
    return torch.cat([rows[:, None], positions], dim=1)


class StateEnv(TwoRoomsEnv):
    """The world as :class:`TrueDynamics` sees it: states ``[episode, x, y]`` (B, 3) where
    the agent sees images, for the observation and the goal alike."""

    def observe(self) -> torch.Tensor:
        return _states(self.positions)

    def goal_images(self) -> torch.Tensor:
        return _states(self.goals)


class TrueDynamics:
    """A stand-in world model that imagines with the TRUE motion of its world (a diagnosis).

    Its state is ``[episode, x, y]``; ``rollout`` moves the dot by ``transition`` in its
    episode's layout (``layouts (B, 2W)``), and ``distance`` is the latent distance between
    ``model``'s encodings of the nearest points of a 1-px grid (``model=None``: pixels).
    """

    def __init__(self, layouts: torch.Tensor, model=None):
        self.config = SimpleNamespace(action_dim=2)
        self.layouts = layouts
        coords, grid = dot_grid(1.0, layouts.device)
        self.side = len(coords)
        if model is None:
            self.tables = grid.expand(len(layouts), -1, -1)
        else:
            self.tables = torch.stack([
                torch.cat([model.encode(render(chunk, layout.expand(len(chunk), -1)))
                           for chunk in grid.split(1024)])
                for layout in layouts[:, None]])  # (B, G*G, D)

    def encode(self, states: torch.Tensor) -> torch.Tensor:
        return states

    def embed(self, states: torch.Tensor) -> torch.Tensor:
        """The table's latents at states ``(..., 3)`` -> ``(..., D)``."""
        ij = (states[..., 1:] - LOW).round().long().clamp(0, self.side - 1)  # the 1-px grid
        return self.tables[states[..., 0].long(), ij[..., 1] * self.side + ij[..., 0]]

    def distance(self, z: torch.Tensor, z_goal: torch.Tensor) -> torch.Tensor:
        return (self.embed(z) - self.embed(z_goal)).norm(dim=-1)

    def rollout(self, states: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """States ``(R, 3)``, actions ``(R, H, 2)`` -> the states visited ``(R, H, 3)``."""
        episode, positions = states[:, :1], states[:, 1:]
        layouts, out = self.layouts[episode[:, 0].long()], []
        for action in actions.unbind(1):
            positions = transition(positions, action, layouts)
            out.append(torch.cat([episode, positions], dim=1))
        return torch.stack(out, dim=1)


@torch.no_grad()
def energy_map(model, layout: torch.Tensor, goal: torch.Tensor, spacing: float = 1.0,
               distance=None):
    """The planner's view of one layout, ``layout (2W,)``, goal ``(2,)`` px: the latent
    distance ``||Enc(o_x) - Enc(o_goal)||`` (or ``distance(z, z_goal)``, such as a cost-to-go
    head) for every dot position x. Returns ``(coords (G,), energy (G, G))`` on the CPU,
    ``energy[i, j]`` at ``(x=coords[j], y=coords[i])``, NaN inside the walls."""
    device = next(model.parameters()).device
    layout, goal = layout.cpu(), goal.cpu()
    coords, positions = dot_grid(spacing)
    layouts = layout.view(1, -1).expand(len(positions), -1)
    free = ~in_wall(positions, layouts)
    z_goal = model.encode(render(goal.view(1, 2), layout.view(1, -1)).to(device))
    energy = torch.full((len(positions),), math.nan)
    for chunk in free.nonzero().squeeze(1).split(1024):
        z = model.encode(render(positions[chunk], layouts[chunk]).to(device))
        energy[chunk] = ((z - z_goal).norm(dim=-1) if distance is None
                         else distance(z, z_goal)).cpu()
    return coords, energy.view(len(coords), len(coords))


@torch.no_grad()
def energy_by_distance(model, episodes: Episodes, edges=(0, 5, 10, 15, 20, 30, 40, 60, 90),
                       spacing: float = 2.0) -> torch.Tensor:
    """The energy's mean in rings ``edges[i] <= distance < edges[i + 1]`` px from the goal,
    over the free dot positions of each episode's :func:`energy_map`: ``(len(edges) - 1,)``
    (NaN if empty). A useful energy keeps rising with distance."""
    edges = torch.as_tensor(edges, dtype=torch.float32)
    rings = len(edges) - 1
    sums, counts = torch.zeros(rings), torch.zeros(rings)
    positions = dot_grid(spacing)[1]  # the rows of every energy_map, flattened
    for layout, goal in zip(episodes.layouts.cpu(), episodes.goals.cpu()):
        energy = energy_map(model, layout, goal, spacing)[1].flatten()
        free = energy.isfinite()
        distance = (positions - goal).norm(dim=-1)
        ring = torch.bucketize(distance[free], edges, right=True) - 1
        keep = (ring >= 0) & (ring < rings)
        sums += torch.bincount(ring[keep], energy[free][keep], minlength=rings).float()
        counts += torch.bincount(ring[keep], minlength=rings).float()
    return sums / counts
