"""The planner and its diagnostics in Three Rooms (layouts (B, 4)), next to Two Rooms (B, 2)."""

import torch
from test_planning import SMALL_PLANNER, LinearLatentModel

from ebjepa_tutorial import planning
from ebjepa_tutorial.envs import (
    Trajectories,
    generate_trajectories,
    render,
    room_of,
    transition,
)
from ebjepa_tutorial.envs.episodes import EPISODE_STEPS, THREE_ROOMS_EPISODE_STEPS
from ebjepa_tutorial.envs.two_rooms import DOT_STD, in_wall
from ebjepa_tutorial.evaluation.position import middle_wall_test, wall_test_by_door_distance
from ebjepa_tutorial.planning import PlannerConfig

LAYOUT = torch.tensor([[20, 15, 44, 50]])  # doors at rows 11..19 and 46..54
TINY = PlannerConfig(horizon=8, samples=8, elites=2, iterations=1, execute=4)


# -- episodes ------------------------------------------------------------------------------
def test_three_room_episodes_run_their_step_budget_and_never_enter_a_wall():
    result = planning.run_episodes(LinearLatentModel(), range(2), SMALL_PLANNER,
                                   world="true_xy", walls=2)
    episodes, steps = result.episodes, THREE_ROOMS_EPISODE_STEPS
    assert episodes.layouts.shape == (2, 4) and result.paths.shape == (2, steps + 1, 2)
    assert room_of(episodes.starts, episodes.layouts).tolist() == [2, 2]  # seeds 0 and 1
    assert room_of(episodes.goals, episodes.layouts).tolist() == [0, 0]
    per_step = episodes.layouts.repeat_interleave(steps + 1, dim=0)
    assert not in_wall(result.paths.flatten(0, 1), per_step).any()
    # true motion and the Euclidean energy get through both doors on these two seeds
    assert result.success.all()
    assert (room_of(result.paths, episodes.layouts) == 1).any(dim=1).all()


def test_the_step_budget_follows_the_walls_and_steps_still_overrides_it():
    model = LinearLatentModel()
    two = planning.run_episodes(model, [3], TINY, world="true_xy")
    assert two.paths.shape[1] == EPISODE_STEPS + 1
    assert torch.equal(two.paths, planning.run_episodes(model, [3], TINY, EPISODE_STEPS,
                                                        world="true_xy").paths)
    short = planning.run_episodes(model, [3], TINY, 12, world="true_xy", walls=2)
    assert short.paths.shape == (1, 13, 2) and short.episodes.layouts.shape == (1, 4)


def test_episode_generators_and_the_arrival_distance_use_the_walls(monkeypatch):
    episodes, _ = planning.episode_generators([5, 6], walls=2)
    rooms = room_of(torch.stack([episodes.starts, episodes.goals], 1), episodes.layouts)
    assert episodes.layouts.shape == (2, 4) and (rooms.sort(1).values == torch.tensor([0, 2])).all()
    model = LinearLatentModel()  # its latent is the dot's centre: the free move is the median
    assert abs(planning.arrival_distance(model, 2.0, walls=2) - 2.0) < 1e-3
    calls = []

    def recording(model, px, **kwargs):
        calls.append(kwargs)
        return 2.0

    monkeypatch.setattr(planning, "arrival_distance", recording)
    planning.run_episodes(model, [5], TINY, 4, world="learned", walls=2)
    assert calls == [{"walls": 2}]  # a Three Rooms model is calibrated on Three Rooms frames


# -- true dynamics and energy maps ----------------------------------------------------------
def test_true_dynamics_moves_each_row_in_its_own_three_room_layout():
    layouts = torch.tensor([[20, 50, 44, 15], [20, 15, 44, 50]])  # the doors swapped
    imagine = planning.TrueDynamics(layouts)  # model=None: the energy is in pixels
    episode = torch.tensor([0.0, 0, 0, 1, 1, 1])[:, None]  # rows 0-2: episode 0, 3-5: 1
    start = torch.cat([episode, torch.tensor([[17.0, 15.0]]).repeat(6, 1)], dim=1)
    actions = torch.tensor([1.5, 0.0]).repeat(6, 24, 1)  # walk right for 24 steps (36 px)
    path = imagine.rollout(start, actions)[..., 1:]  # (6, 24, 2) positions
    expected, per_row = [start[:, 1:]], layouts.repeat_interleave(3, dim=0)
    for k in range(24):
        expected.append(transition(expected[-1], actions[:, k], per_row))
    assert torch.equal(path, torch.stack(expected[1:], dim=1))
    assert path[:3, -1, 0].max() < 18.5  # episode 0: stopped by the first wall
    assert 40.5 < path[3:, -1, 0].min() < 42.5  # episode 1: through door 0, stopped by wall 1


def test_true_dynamics_tables_encode_the_three_room_frames():
    model = LinearLatentModel()
    imagine = planning.TrueDynamics(LAYOUT, model)
    on_grid = torch.tensor([[33.5, 25.5]])  # LOW = 1.5, spacing 1
    state = torch.cat([torch.zeros(1, 1), on_grid], dim=1)  # episode 0
    assert torch.equal(imagine.embed(state), model.encode(render(on_grid, LAYOUT)))


def test_energy_map_of_three_rooms_marks_both_walls_and_opens_both_doors():
    goal = torch.tensor([55.0, 30.0])
    coords, energy = planning.energy_map(LinearLatentModel(), LAYOUT[0], goal, spacing=1.0)
    _, grid = planning.dot_grid(1.0)
    blocked = in_wall(grid, LAYOUT.expand(len(grid), -1)).view(len(coords), len(coords))
    assert torch.equal(energy.isnan(), blocked)

    def at(x, y):  # energy at the grid point (x, y); coords start at 1.5
        return energy[int(y - 1.5), int(x - 1.5)]

    assert at(20.5, 40.5).isnan() and at(44.5, 20.5).isnan()  # each wall, beside its door
    assert not at(20.5, 15.5).isnan() and not at(44.5, 50.5).isnan()  # each doorway
    assert abs(at(55.5, 30.5) - 0.5**0.5) < 1e-3  # the latent is the dot: energy = distance


# -- the wall test ------------------------------------------------------------------------
def read_layouts(frames: torch.Tensor) -> torch.Tensor:
    """The walls read off the wall channel: frames (B, 2, 65, 65) -> layouts (B, 2W) long."""
    walls = frames[:, 1, 1:-1, 1:-1] > 0.5  # inside the border, (B, 63, 63)
    columns = walls.any(dim=1)  # (B, 63): each wall fills 3 neighbouring columns
    centre = columns[:, 1:-1] & columns[:, :-2] & columns[:, 2:]
    b, c = centre.nonzero().unbind(1)  # wall by wall, left to right
    door = ~walls[b, :, c + 1]  # (n, 63): the open rows of the centre column
    door_y = (door * torch.arange(1.0, 64.0)).sum(1) / door.sum(1)
    return torch.stack([c + 2, door_y.round().long()], dim=1).view(len(frames), -1)


def read_dot(frames: torch.Tensor) -> torch.Tensor:
    """The dot's centre, exact for a Gaussian: frames (B, 2, 65, 65) -> (B, 2) px.

    Beside the peak pixel j, log g(j+1) - log g(j) = (2 (x - j) - 1) / (2 std^2).
    """
    dot, rows = frames[:, 0].double(), torch.arange(len(frames))
    peak = dot.flatten(1).argmax(1)
    i, j = peak // 65, peak % 65
    x = j + 0.5 + DOT_STD**2 * (dot[rows, i, j + 1].log() - dot[rows, i, j].log())
    y = i + 0.5 + DOT_STD**2 * (dot[rows, i + 1, j].log() - dot[rows, i, j].log())
    # to 0.001 px: a dot resting on a wall's face must not be read a hair inside it
    return (torch.stack([x, y], 1) * 1000).round().float() / 1000


class WallsReader(torch.nn.Module):
    """A stand-in world model whose latent is the state, (x, y, wall_x_0, door_y_0, ...).

    Its predictor moves the dot by the true rule of motion in every room, except
    within ``reach`` px (along the wall) of the door of the wall nearest in x,
    where it moves the dot by the action alone, as if there were no walls.
    """

    def __init__(self, reach: float = 0.0):
        super().__init__()
        self.reach = reach
        self.unused = torch.nn.Parameter(torch.zeros(()))  # for the device lookup

    def encode(self, frames):
        return torch.cat([read_dot(frames), read_layouts(frames).float()], dim=1)

    def predict(self, z, actions):
        xy, walls = z[:, :2], z[:, 2:].view(len(z), -1, 2)
        nearest = (walls[..., 0] - xy[:, None, 0]).abs().argmin(1)
        door_y = walls[torch.arange(len(z)), nearest, 1]
        blind = ((xy[:, 1] - door_y).abs() < self.reach)[:, None]
        moved = torch.where(blind, xy + actions, transition(xy, actions, z[:, 2:].long()))
        return torch.cat([moved, z[:, 2:]], dim=1)


def test_the_wall_reader_reads_three_room_frames_exactly():
    positions = torch.tensor([[17.5, 20.0], [41.5, 45.0], [1.5, 62.5]])
    layouts = torch.tensor([[20, 15, 44, 50], [25, 54, 39, 10], [14, 10, 50, 54]])
    latents = WallsReader().encode(render(positions, layouts))
    assert torch.equal(latents, torch.cat([positions, layouts.float()], dim=1))


def test_wall_steps_of_three_rooms_are_binned_by_the_door_of_the_wall_that_stopped_them():
    # Three steps right into a wall (two) or left into the second wall; the doors are 35
    # rows apart, so the first door's distance would put the last two in other bins.
    starts = torch.tensor([[17.0, 20.0], [41.0, 45.0], [47.0, 30.0]])
    actions = torch.tensor([[1.8, 0.0], [1.8, 0.0], [-1.8, 0.0]])
    layouts = LAYOUT.expand(3, -1)
    ends = transition(starts, actions, layouts)
    assert ends[:, 0].tolist() == [17.5, 41.5, 46.5]  # each stopped at a wall's face
    trajectories = Trajectories(torch.stack([starts, ends], 1), actions[:, None], layouts,
                                torch.zeros(3, dtype=torch.bool))
    edges = (0, 8, 16, 24, 65)  # |y - door_y| of its own wall: 5, 5, 20
    bins = wall_test_by_door_distance(WallsReader(reach=8), trajectories, edges)
    assert [b["n"] for b in bins] == [2, 0, 1, 0]  # by the first door it would be 1, 1, 0, 1
    assert [b["stopped"] for b in bins][::2] == [0.0, 1.0]  # blind within 8 px of its door


def test_the_wall_test_on_three_room_trajectories():
    trajectories = generate_trajectories(300, seed=3, wall_fraction=0.3, walls=2)
    walled = middle_wall_test(WallsReader(), trajectories)
    blind = middle_wall_test(WallsReader(reach=65), trajectories)
    assert walled["n_stopped"] >= 100 and (walled["stopped"], walled["moved"]) == (1.0, 1.0)
    assert (blind["stopped"], blind["moved"]) == (0.0, 1.0)
    edges = (0, 8, 12, 16, 65)
    bins = wall_test_by_door_distance(WallsReader(reach=12), trajectories, edges)
    assert sum(b["n"] for b in bins) == walled["n_stopped"] and all(b["n"] >= 10 for b in bins)
    assert [b["stopped"] for b in bins] == [0.0, 0.0, 1.0, 1.0]


def test_an_energy_map_can_show_another_distance_such_as_a_cost_head():
    goal, model = torch.tensor([55.0, 30.0]), LinearLatentModel()
    _, straight = planning.energy_map(model, LAYOUT[0], goal, spacing=4.0)
    _, manhattan = planning.energy_map(model, LAYOUT[0], goal, spacing=4.0,
                                       distance=lambda z, g: (z - g).abs().sum(dim=-1))
    free = straight.isfinite()
    assert torch.equal(manhattan.isfinite(), free)
    # the latent is the dot, so |dx| + |dy| lies between ||d|| and sqrt(2) ||d||
    assert (manhattan[free] >= straight[free] - 1e-4).all()
    assert (manhattan[free] <= 2**0.5 * straight[free] + 1e-4).all()
    assert (manhattan[free] > straight[free] + 1).any()
