"""Three Rooms: two walls in a row, run by the same transition code as Two Rooms."""

from dataclasses import replace

import pytest
import torch

from ebjepa_tutorial.course.presets import preset
from ebjepa_tutorial.envs import (
    MAX_STEP,
    SUCCESS_RADIUS,
    TwoRoomsEnv,
    clip_actions,
    generate_trajectories,
    make_episodes,
    random_layouts,
    render,
    room_of,
    sample_positions,
    step_budget,
    transition,
)
from ebjepa_tutorial.envs.episodes import THREE_ROOMS_EPISODE_STEPS
from ebjepa_tutorial.envs.two_rooms import (
    HIGH,
    LOW,
    WALL_X_RANGES,
    check_world,
    in_wall,
    room_floors,
    wall_bounds,
    wall_collision,
    wall_images,
)
from ebjepa_tutorial.training import world

LAYOUT = torch.tensor([[20, 15, 44, 50]])  # doors at rows 11..19 and 46..54


def good_path(starts, goals, layouts):
    """Waypoints (B, 2W+2, 2): the start, each door's two mouths in travel order, the goal.

    A mouth is where the doorway meets a room, (wall_x -+ 2.5, door_y); every leg
    stays in one room or runs along a doorway's centre row, so no wall stops it.
    """
    x_lo, x_hi = (torch.stack([wall_bounds(layouts[:, 2 * k:2 * k + 2])[i] for k in (0, 1)], 1)
                  for i in (0, 1))
    door_y = layouts[:, 1::2].float()
    right = (goals[:, 0] > starts[:, 0])[:, None]  # else the walls come right to left
    enter = torch.where(right, x_lo, x_hi.flip(1))
    leave = torch.where(right, x_hi, x_lo.flip(1))
    rows = torch.where(right, door_y, door_y.flip(1))
    mouths = torch.stack([torch.stack([enter, rows], -1), torch.stack([leave, rows], -1)], 2)
    return torch.cat([starts[:, None], mouths.flatten(1, 2), goals[:, None]], 1)


def walk(positions, waypoints, layouts, steps):
    """Step toward each waypoint in turn with :func:`transition`, ``steps`` times.

    Returns the path (B, steps+1, 2) and the first step within SUCCESS_RADIUS of
    the last waypoint (B,), ``steps + 1`` where never.
    """
    rows, leg = torch.arange(len(positions)), torch.zeros(len(positions), dtype=torch.long)
    path = [positions]
    for _ in range(steps):
        positions = transition(positions, waypoints[rows, leg] - positions, layouts)
        reached = (positions - waypoints[rows, leg]).norm(dim=-1) < 1e-3
        leg = (leg + reached.long()).clamp(max=waypoints.shape[1] - 1)
        path.append(positions)
    path = torch.stack(path, 1)
    near = (path - waypoints[:, -1:]).norm(dim=-1) <= SUCCESS_RADIUS
    arrival = torch.where(near.any(1), near.float().argmax(1), steps + 1)
    return path, arrival


# ----------------------------------------------------------------- geometry


def test_layouts_ranges_and_room_widths():
    layouts = random_layouts(5000, torch.Generator().manual_seed(0), walls=2)
    assert layouts.shape == (5000, 4) and layouts.dtype == torch.long
    check_world(layouts, sample_positions(layouts, torch.Generator()))
    for column, (lo, hi) in enumerate([(14, 25), (10, 54), (39, 50), (10, 54)]):
        assert layouts[:, column].min() == lo and layouts[:, column].max() == hi
    assert not torch.equal(layouts[:, 1], layouts[:, 3])  # doors drawn independently
    _, width = room_floors(layouts)
    assert width[:, 1].min() == 9 and width[:, [0, 2]].min() == 10  # floors of dot centres


def test_walls_and_doors_are_drawn():
    walls = wall_images(LAYOUT)[0]
    inner = walls[1:64, 1:64]
    assert inner.sum(0).nonzero().flatten().tolist() == [18, 19, 20, 42, 43, 44]  # columns-1
    assert (walls[:, 20] == 0).nonzero().flatten().tolist() == list(range(11, 20))
    assert (walls[:, 44] == 0).nonzero().flatten().tolist() == list(range(46, 55))
    both = torch.maximum(wall_images(LAYOUT[:, :2]), wall_images(LAYOUT[:, 2:]))
    assert torch.equal(wall_images(LAYOUT), both)  # the walls ORed
    frames = render(torch.tensor([[[10.0, 10.0], [30.0, 30.0]]]), LAYOUT)
    assert frames.shape == (1, 2, 2, 65, 65) and torch.equal(frames[0, 1, 1], walls)


def test_room_of_counts_the_walls_to_the_left():
    x = torch.tensor([5.0, 19.9, 20.5, 30.0, 44.0, 44.1, 60.0])
    positions = torch.stack([x, torch.full_like(x, 15.0)], -1)
    layouts = LAYOUT.expand(len(x), 4)
    assert room_of(positions, layouts).tolist() == [0, 0, 1, 1, 1, 2, 2]
    assert room_of(positions.view(1, 7, 2), LAYOUT).tolist() == [[0, 0, 1, 1, 1, 2, 2]]


def test_sample_positions_in_each_room():
    g = torch.Generator().manual_seed(1)
    layouts = random_layouts(3000, g, walls=2)
    rooms = torch.randint(0, 3, (3000,), generator=g)
    positions = sample_positions(layouts, g, rooms)
    check_world(layouts, positions)
    assert torch.equal(room_of(positions, layouts), rooms)
    anywhere = sample_positions(layouts, g)
    check_world(layouts, anywhere)
    share = torch.bincount(room_of(anywhere, layouts), minlength=3) / 3000
    _, width = room_floors(layouts)
    assert (share - width.sum(0) / width.sum()).abs().max() < 0.03  # uniform by area


# ----------------------------------------------------------------- collisions


def test_random_walks_keep_every_invariant():
    g = torch.Generator().manual_seed(2)
    n = 2000
    layouts = random_layouts(n, g, walls=2)
    positions = sample_positions(layouts, g)
    crossed = torch.zeros(2, dtype=torch.long)
    for _ in range(60):
        actions = 2 * torch.randn(n, 2, generator=g)
        actions[torch.rand(n, generator=g) < 0.1] *= 100
        new = transition(positions, actions, layouts)
        assert not in_wall(new, layouts).any()
        assert ((new >= LOW) & (new <= HIGH)).all()
        assert (new - positions).norm(dim=-1).max() <= MAX_STEP + 1e-5
        for k in range(2):  # a side change of a wall happens in its doorway
            x_lo, x_hi, y_lo, y_hi = wall_bounds(layouts[:, 2 * k:2 * k + 2])
            wall_x = layouts[:, 2 * k].float()
            side = (positions[:, 0] < wall_x) != (new[:, 0] < wall_x)
            dx = new[:, 0] - positions[:, 0]
            t = (wall_x - positions[:, 0]) / torch.where(dx == 0, torch.ones_like(dx), dx)
            y = positions[:, 1] + t * (new[:, 1] - positions[:, 1])
            assert not (side & ((y < y_lo - 1e-4) | (y > y_hi + 1e-4))).any()
            crossed[k] += side.sum()
        positions = new
    assert (crossed > 50).all()  # both doors are used


def test_huge_moves_never_end_in_a_wall():
    """Moves past both walls are approximated, but the walls are met in the move's order."""
    g = torch.Generator().manual_seed(6)
    layouts = random_layouts(4000, g, walls=2)
    positions = sample_positions(layouts, g)
    for _ in range(30):
        moves = 40 * torch.randn(4000, 2, generator=g)
        new = wall_collision(positions, moves, layouts)
        assert not in_wall(new, layouts).any()
        assert ((new >= LOW) & (new <= HIGH)).all()
        assert ((new - positions).abs() <= moves.abs() + 1e-5).all()  # never longer
        positions = new


def test_moves_that_touch_no_wall_are_unchanged():
    g = torch.Generator().manual_seed(3)
    layouts = random_layouts(4000, g, walls=2)
    positions = sample_positions(layouts, g)
    moves = 1.8 * torch.randn(4000, 2, generator=g)
    target = positions + moves
    left, width = room_floors(layouts)
    room = room_of(positions, layouts)[:, None]
    lo, hi = left.gather(1, room)[:, 0], (left + width).gather(1, room)[:, 0]
    in_room = (target[:, 0] >= lo) & (target[:, 0] <= hi)  # never reaches a slab
    free = ((target >= LOW) & (target <= HIGH)).all(-1) & in_room
    assert free.sum() > 3000
    new = wall_collision(positions, moves, layouts)
    assert torch.equal(new[free], target[free])


def test_moves_up_to_the_floor_between_walls_meet_one_wall_exactly():
    """For |dx| <= 9 px (the narrowest middle floor) two walls give the one-wall rule."""
    g = torch.Generator().manual_seed(4)
    layouts = random_layouts(20_000, g, walls=2)
    positions = sample_positions(layouts, g)
    moves = 5 * torch.randn(20_000, 2, generator=g)
    moves[:, 0] = moves[:, 0].clamp(-9, 9)
    target = (positions + moves).clamp(LOW, HIGH)
    first = wall_collision(positions, moves, layouts[:, :2])
    second = wall_collision(positions, moves, layouts[:, 2:])
    by_first = (first != target).any(-1, keepdim=True)
    assert by_first.sum() > 500 and (second != target).any(-1).sum() > 500
    assert torch.equal(wall_collision(positions, moves, layouts),
                       torch.where(by_first, first, second))


def test_the_dot_crosses_each_door_and_not_the_walls():
    layouts = LAYOUT.expand(2, 4)
    starts = torch.tensor([[5.0, 60.0], [60.0, 5.0]])
    goals = starts.flip(0)
    path, arrival = walk(starts, good_path(starts, goals, layouts), layouts, 120)
    assert (arrival <= 120).all()
    rooms = room_of(path, layouts)
    assert rooms[0].unique_consecutive().tolist() == [0, 1, 2]
    assert rooms[1].unique_consecutive().tolist() == [2, 1, 0]
    # straight at a wall away from its door: x stops at the face, y slides on
    blocked = wall_collision(torch.tensor([[16.0, 40.0], [48.0, 20.0]]),
                             torch.tensor([[3.0, 1.0], [-3.0, -1.0]]), layouts)
    assert torch.equal(blocked, torch.tensor([[17.5, 41.0], [46.5, 19.0]]))


# ----------------------------------------------------------------- bad input


def test_good_layouts_and_other_errors():
    check_world(torch.tensor([[14, 10, 28, 54], [25, 54, 50, 10]]),
                torch.tensor([[5.0, 5.0], [60.0, 60.0]]))
    with pytest.raises(ValueError, match=r"shape \(B, 2W\)"):
        check_world(torch.tensor([[20, 30, 40]]), torch.tensor([[5.0, 5.0]]))
    with pytest.raises(ValueError, match="walls must be 1"):
        random_layouts(3, torch.Generator(), walls=3)
    with pytest.raises(ValueError, match="inside the wall"):
        check_world(LAYOUT, torch.tensor([[44.0, 30.0]]))


# ----------------------------------------------------------------- data and episodes


def test_trajectories_cross_both_walls():
    data = generate_trajectories(1000, seed=0, walls=2, wall_fraction=0.25)
    assert data.layouts.shape == (1000, 4) and data.door.sum() == 350
    rooms = room_of(data.positions, data.layouts)
    pairs = rooms[:, 1:] + rooms[:, :-1]  # 1: a step across wall 0, 3: across wall 1
    changes = rooms[:, 1:] != rooms[:, :-1]
    assert (changes & (pairs == 1)).any(1).sum() > 100  # trajectories through door 0
    assert (changes & (pairs == 3)).any(1).sum() > 100  # through door 1
    assert data.changes_room()[data.door].float().mean() > 0.5
    positions = data.positions[:200, 0]
    for t in range(16):  # one transition function
        positions = transition(positions, data.actions[:200, t], data.layouts[:200])
        assert torch.equal(positions, data.positions[:200, t + 1])


def test_door_and_wall_starts_face_one_wall_each():
    base = generate_trajectories(1000, seed=1, walls=2)
    data = generate_trajectories(1000, seed=1, walls=2, wall_fraction=0.25)
    wall = (base.positions[:, 0] != data.positions[:, 0]).any(-1)  # drawn last: the rest agree
    assert wall.sum() == 250 and not (wall & data.door).any()
    starts, layouts = data.positions[:, 0], data.layouts.float()
    gaps = (starts[:, :1] - layouts[:, 0::2]).abs() - 2.5  # from each wall's face
    nearest = gaps.argmin(1)
    for built in (data.door, wall):
        assert gaps[built].min(1).values.min() >= 0.5 - 1e-4
        assert gaps[built].min(1).values.max() <= 4 + 1e-4
        assert 0.35 < nearest[built].float().mean() < 0.65  # both walls picked
    rows = torch.arange(1000)
    wall_x, door_y = layouts[rows, 2 * nearest], layouts[rows, 2 * nearest + 1]
    assert ((starts[:, 1] - door_y).abs()[data.door] <= 2 + 1e-4).all()  # aimed at that door
    assert ((starts[:, 1] - door_y).abs()[wall] >= 10.5 - 1e-4).all()  # away from it
    towards = (wall_x - starts[:, 0]).sign() * data.actions[:, 0, 0]
    assert (towards[wall | data.door] > 0).all()  # the first step heads at that wall


def test_three_room_episodes_go_between_the_outer_rooms_within_budget():
    episodes = make_episodes(400, seed=5, walls=2)
    assert episodes.layouts.shape == (400, 4)
    check_world(episodes.layouts, episodes.starts)
    check_world(episodes.layouts, episodes.goals)
    start_rooms = room_of(episodes.starts, episodes.layouts)
    assert set(start_rooms.tolist()) == {0, 2} and 0.4 < (start_rooms == 0).float().mean() < 0.6
    assert torch.equal(room_of(episodes.goals, episodes.layouts), 2 - start_rooms)
    assert torch.equal(make_episodes(400, seed=5, walls=2).goals, episodes.goals)
    path, arrival = walk(episodes.starts, good_path(episodes.starts, episodes.goals,
                                                    episodes.layouts), episodes.layouts, 110)
    assert arrival.max() <= 110 < THREE_ROOMS_EPISODE_STEPS  # a good path fits the budget
    # the worst good path of any layout (module docstring): 170.7 px, about 95 steps
    layouts = torch.tensor([[14, 54, 50, 10]])
    starts, goals = torch.tensor([[LOW, LOW]]), torch.tensor([[HIGH, HIGH]])
    waypoints = good_path(starts, goals, layouts)
    length = (waypoints[:, 1:] - waypoints[:, :-1]).norm(dim=-1).sum()
    assert abs(length - 170.71) < 0.01 and length / MAX_STEP + 25 < THREE_ROOMS_EPISODE_STEPS
    assert walk(starts, waypoints, layouts, 110)[1] <= 100


def test_environment_runs_three_rooms():
    env = TwoRoomsEnv()
    assert env.reset(n=4, seed=0).shape == (4, 2, 65, 65) and env.step_budget == 200
    obs = env.reset(episodes=make_episodes(4, 0, walls=2))
    assert obs.shape == (4, 2, 65, 65) and env.layouts.shape == (4, 4)
    assert env.step_budget == THREE_ROOMS_EPISODE_STEPS
    assert set(env.rooms().tolist()) <= {0, 2}
    waypoints, leg = good_path(env.positions, env.goals, env.layouts), torch.zeros(4, dtype=int)
    for _ in range(env.step_budget):
        if env.success().all():
            break
        env.step(clip_actions(waypoints[torch.arange(4), leg] - env.positions))
        reached = (env.positions - waypoints[torch.arange(4), leg]).norm(dim=-1) < 1e-3
        leg = (leg + reached.long()).clamp(max=5)
    assert env.success().all() and env.steps_taken < 110


def test_step_budgets_are_200_steps_in_two_rooms_and_120_in_three():
    """The budgets of the module docstring, which every recorded success rate was run
    with: a longer Three Rooms budget would let sliding along the walls find the doors."""
    assert step_budget(random_layouts(3, torch.Generator(), walls=1)) == 200
    assert step_budget(LAYOUT) == 120
    env = TwoRoomsEnv()
    env.reset(episodes=make_episodes(2, seed=0, walls=2))
    assert env.step_budget == 120


def test_a_three_rooms_run_records_the_ranges_of_its_walls(monkeypatch):
    config = preset("07", "class").three_rooms
    current = world.identity(config)
    assert current["wall_x_ranges"] == [[14, 25], [39, 50]]
    assert "wall_x_ranges" not in world.identity(replace(config, walls=1))
    # a learner who narrows the walls must not load the model of the old geometry
    monkeypatch.setitem(WALL_X_RANGES, 2, ((23, 25), (39, 41)))
    assert world.identity(config) != current
