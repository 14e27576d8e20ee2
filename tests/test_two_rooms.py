"""Two Rooms: geometry, the transition rule, the data policy, evaluation episodes."""

import math

import pytest
import torch

from ebjepa_tutorial.course.exercises import ExerciseError, check_wall_collision
from ebjepa_tutorial.envs import (
    Episodes,
    TwoRoomsEnv,
    clip_actions,
    generate_trajectories,
    make_episodes,
    random_layouts,
    render,
    room_of,
    sample_positions,
    transition,
)
from ebjepa_tutorial.envs.trajectories import sample_truncated_normal, sample_von_mises
from ebjepa_tutorial.envs.two_rooms import (
    HIGH,
    LOW,
    check_world,
    in_wall,
    shortest_path_length,
    wall_bounds,
    wall_collision,
    wall_images,
)

# ----------------------------------------------------------------- geometry


def test_wall_pixels_by_hand():
    walls = wall_images(torch.tensor([[20, 10], [44, 54]]))
    assert walls.shape == (2, 65, 65)
    for image, wall_x, door_y in ((walls[0], 20, 10), (walls[1], 44, 54)):
        assert image[0].all() and image[64].all() and image[:, 0].all() and image[:, 64].all()
        inner = image[1:64, 1:64]  # without the border
        assert inner.sum(0).nonzero().flatten().tolist() == [wall_x - 2, wall_x - 1, wall_x]
        column = image[1:64, wall_x]
        assert column.sum() == 63 - 9  # 9 px door
        assert (image[door_y - 4 : door_y + 5, wall_x - 1 : wall_x + 2] == 0).all()
        assert image[door_y - 5, wall_x] == 1 and image[door_y + 5, wall_x] == 1


def test_layouts_cover_their_ranges():
    layouts = random_layouts(5000, torch.Generator().manual_seed(0))
    assert layouts[:, 0].min() == 20 and layouts[:, 0].max() == 44
    assert layouts[:, 1].min() == 10 and layouts[:, 1].max() == 54


def test_render_shapes_and_values():
    layouts = torch.tensor([[30, 30], [40, 20]])
    assert render(torch.tensor([[10.0, 10.0], [50.0, 50.0]]), layouts).shape == (2, 2, 65, 65)
    frames = render(torch.full((2, 5, 2), 12.0), layouts)
    assert frames.shape == (2, 5, 2, 65, 65) and frames.dtype == torch.float32
    assert 0 <= frames.min() and frames.max() <= 1
    assert frames[0, 0, 0, 12, 12] == 1.0  # peak 1 at an integer centre
    assert torch.equal(frames[1, 3, 1], wall_images(layouts)[1])
    buffer = torch.full((2, 5, 2, 65, 65), 7.0)
    assert render(torch.full((2, 5, 2), 12.0), layouts, out=buffer) is buffer
    assert torch.equal(buffer, frames)


def test_dot_matches_formula_and_has_std_1_3():
    pos = torch.tensor([[20.3, 41.7]])
    dot = render(pos, torch.tensor([[44, 30]]))[0, 0].double()
    rows, cols = torch.meshgrid(*[torch.arange(65.0, dtype=torch.float64)] * 2, indexing="ij")
    formula = torch.exp(-((cols - 20.3) ** 2 + (rows - 41.7) ** 2) / (2 * 1.3**2))
    assert torch.allclose(dot, formula, atol=1e-6)
    mass = dot.sum()
    mx, my = (dot * cols).sum() / mass, (dot * rows).sum() / mass
    assert abs(mx - 20.3) < 1e-3 and abs(my - 41.7) < 1e-3
    var_x = (dot * (cols - mx) ** 2).sum() / mass
    var_y = (dot * (rows - my) ** 2).sum() / mass
    assert abs(var_x.sqrt() - 1.3) < 2e-3 and abs(var_y.sqrt() - 1.3) < 2e-3


# ----------------------------------------------------------------- collisions


def test_collision_cases_by_hand():
    layouts = torch.tensor([[30, 40]] * 5)  # slab 27.5 < x < 32.5, doorway 36.5 <= y <= 43.5
    pos = torch.tensor([[27.0, 40.0], [27.0, 30.0], [2.0, 2.0], [30.0, 43.0], [10.0, 10.0]])
    moves = torch.tensor([[1.0, 0.0], [1.0, 0.5], [-5.0, 1.0], [0.5, 1.0], [1.0, -1.0]])
    expected = torch.tensor(
        [[28.0, 40.0], [27.5, 30.5], [1.5, 3.0], [30.5, 43.5], [11.0, 9.0]]
    )  # through the door; face stop, y slides; border; door's side; free
    assert torch.equal(wall_collision(pos, moves, layouts), expected)


def _crossing_problems(p0, p1, layouts, slid_ok=False, tol=1e-4):
    """Invariant violations of one step from p0 to p1 (all (B, 2)).

    A side change must cross x = wall_x within the doorway. A huge move can
    enter the doorway, hit the door's side and slide along it out of the slab:
    then the straight line p0 -> p1 is not the path, so ``slid_ok`` accepts a
    crossing that ends exactly on the doorway's edge.
    """
    x_lo, x_hi, y_lo, y_hi = wall_bounds(layouts)
    wall_x = layouts[:, 0].float()
    outside = ((p1 < LOW) | (p1 > HIGH)).any(-1)
    x, y = p1.unbind(-1)
    in_wall = (x > x_lo) & (x < x_hi) & ((y < y_lo) | (y > y_hi))
    crossed = (p0[:, 0] < wall_x) != (p1[:, 0] < wall_x)
    dx = p1[:, 0] - p0[:, 0]
    t = (wall_x - p0[:, 0]) / torch.where(dx == 0, torch.ones_like(dx), dx)
    y_cross = p0[:, 1] + t * (p1[:, 1] - p0[:, 1])
    through_wall = crossed & ((y_cross < y_lo - tol) | (y_cross > y_hi + tol))
    if slid_ok:
        through_wall &= (y != y_lo) & (y != y_hi)
    return outside.sum().item(), in_wall.sum().item(), through_wall.sum().item(), crossed.sum()


@pytest.mark.parametrize("clipped", [True, False])
def test_fuzzed_walks_never_leave_the_arena_or_pass_through_the_wall(clipped):
    g = torch.Generator().manual_seed(1 if clipped else 2)
    n, steps = 2000, 60
    layouts = random_layouts(n, g)
    pos = sample_positions(layouts, g)
    crossings = 0
    for _ in range(steps):
        moves = 2 * torch.randn(n, 2, generator=g)
        huge = torch.rand(n, generator=g) < 0.1
        moves[huge] *= 100
        new = transition(pos, moves, layouts) if clipped else wall_collision(pos, moves, layouts)
        limit = clip_actions(moves) if clipped else moves
        assert ((new - pos).abs() <= limit.abs() + 1e-5).all()  # a move never gets longer
        outside, in_wall, through_wall, crossed = _crossing_problems(pos, new, layouts, not clipped)
        assert (outside, in_wall, through_wall) == (0, 0, 0)
        crossings += crossed
        pos = new
    assert crossings > 50  # the door is really used


def test_moves_that_touch_no_wall_are_unchanged():
    g = torch.Generator().manual_seed(3)
    layouts = random_layouts(4000, g)
    pos = sample_positions(layouts, g)
    moves = 1.8 * torch.randn(4000, 2, generator=g)
    target = pos + moves
    x_lo, x_hi, _, _ = wall_bounds(layouts)
    left = (pos[:, 0] <= x_lo) & (target[:, 0] <= x_lo)
    right = (pos[:, 0] >= x_hi) & (target[:, 0] >= x_hi)
    inside = ((target >= LOW) & (target <= HIGH)).all(-1)
    free = (left | right) & inside
    assert free.sum() > 3000
    new = wall_collision(pos, moves, layouts)
    assert torch.equal(new[free], target[free])


def test_clip_actions_keeps_direction_and_caps_norm():
    actions = torch.tensor([[3.0, 4.0], [0.3, -0.4], [0.0, 0.0]])
    clipped = clip_actions(actions)
    assert torch.allclose(clipped[0], torch.tensor([1.08, 1.44]))
    assert torch.equal(clipped[1:], actions[1:])


def test_checker_accepts_reference_and_explains_mistakes(capsys):
    def mine(positions, moves, layouts):  # a learner's copy of the rule (the reference
        return wall_collision(positions, moves, layouts)  # itself is handed back unchecked)

    assert check_wall_collision(mine) is mine
    assert "Correct" in capsys.readouterr().out

    def no_inner_wall(pos, moves, layouts):
        return (pos + moves).clamp(LOW, HIGH)

    with pytest.raises(ExerciseError, match="left the dot centre inside the wall"):
        check_wall_collision(no_inner_wall)

    def skips_long_moves(pos, moves, layouts):
        long = moves.norm(dim=-1, keepdim=True) > 20
        reference = wall_collision(pos, moves, layouts)
        return torch.where(long, no_inner_wall(pos, moves, layouts), reference)

    with pytest.raises(ExerciseError, match=r"pass through the wall at y=[\d.]+ where the door"):
        check_wall_collision(skips_long_moves)

    def door_always_shut(pos, moves, layouts):
        x_lo, x_hi, _, _ = wall_bounds(layouts)
        new = (pos + moves).clamp(LOW, HIGH)
        x = torch.where(pos[:, 0] <= x_lo, new[:, 0].clamp(max=x_lo), new[:, 0].clamp(min=x_hi))
        return torch.stack([x, new[:, 1]], -1)

    with pytest.raises(ExerciseError, match="stopped the dot at the wall, but the door is open"):
        check_wall_collision(door_always_shut)

    def stops_at_contact(pos, moves, layouts):  # no sliding: y stops where the path hits x_lo/x_hi
        new = wall_collision(pos, moves, layouts)
        target = (pos + moves).clamp(LOW, HIGH)
        at_face = new[:, 0] != target[:, 0]
        t = (new[:, 0] - pos[:, 0]) / torch.where(at_face, target[:, 0] - pos[:, 0], 1.0)
        y = torch.where(at_face, pos[:, 1] + t * (target[:, 1] - pos[:, 1]), new[:, 1])
        return torch.stack([new[:, 0], y], -1)

    with pytest.raises(ExerciseError, match="reference gives .* where its path meets the wall"):
        check_wall_collision(stops_at_contact)

    def todo(pos, moves, layouts):
        raise NotImplementedError

    assert check_wall_collision(todo) is wall_collision  # the notebook runs on with the course's
    assert "not implemented yet" in capsys.readouterr().out


# ----------------------------------------------------------------- bad input


def test_bad_inputs_give_clear_errors():
    env = TwoRoomsEnv()

    def reset(layouts, start=(10.0, 10.0)):
        start = torch.tensor([start])
        return env.reset(episodes=Episodes(torch.tensor(layouts), start, start))

    reset([[30, 30]])
    with pytest.raises(ValueError, match=r"shape \(1, 2\)"):
        env.step(torch.zeros(1, 3))
    with pytest.raises(ValueError, match="NaN"):
        env.step(torch.tensor([[float("nan"), 0.0]]))
    with pytest.raises(ValueError, match="inside the wall"):
        reset([[30, 30]], start=(30.0, 10.0))
    for seed in ("3", 1.5, True, None):
        with pytest.raises(TypeError, match="seed must be an int"):
            make_episodes(4, seed=seed)
        with pytest.raises(TypeError, match="seed must be an int"):
            generate_trajectories(4, seed=seed)


# ----------------------------------------------------------------- data policy


def test_von_mises_sampler_statistics():
    g = torch.Generator().manual_seed(0)
    for kappa in (5.0, 0.5):
        theta = sample_von_mises(kappa, (200_000,), g).double()
        k = torch.tensor(kappa, dtype=torch.float64)
        i0, i1 = torch.special.i0(k), torch.special.i1(k)
        i2 = i0 - 2 / k * i1
        assert abs(theta.cos().mean() - i1 / i0) < 0.005
        assert abs(theta.sin().mean()) < 0.005
        assert abs((2 * theta).cos().mean() - i2 / i0) < 0.006
        # Kolmogorov-Smirnov distance to the CDF integrated from the density
        grid = torch.linspace(-math.pi, math.pi, 20_001, dtype=torch.float64)
        density = torch.distributions.VonMises(0.0, k).log_prob(grid).exp()
        cdf = torch.cumulative_trapezoid(density, grid)
        cdf = torch.cat([torch.zeros(1, dtype=torch.float64), cdf / cdf[-1]])
        empirical = torch.searchsorted(theta.sort().values, grid) / len(theta)
        assert (empirical - cdf).abs().max() < 0.006


def test_truncated_normal_statistics():
    x = sample_truncated_normal(1.0, 0.4, 0.2, 1.8, (200_000,), torch.Generator().manual_seed(0))
    assert x.min() >= 0.2 and x.max() <= 1.8
    # truncated at +-2 std: mean 1, std 0.4 * sqrt(1 - 4 phi(2) / (Phi(2) - Phi(-2)))
    phi2 = math.exp(-2) / math.sqrt(2 * math.pi)
    std = 0.4 * math.sqrt(1 - 4 * phi2 / math.erf(2 / math.sqrt(2)))
    assert abs(x.mean() - 1.0) < 0.003 and abs(x.std() - std) < 0.003


@pytest.fixture(scope="module")
def data():
    return generate_trajectories(20_000, seed=0)


def test_trajectory_shapes_and_policy_statistics(data):
    assert data.positions.shape == (20_000, 17, 2) and data.actions.shape == (20_000, 16, 2)
    assert data.layouts.shape == (20_000, 2) and data.door.sum() == 7000
    lengths = data.actions.norm(dim=-1)
    assert lengths.min() >= 0.2 - 1e-5 and lengths.max() <= 1.8 + 1e-5
    assert abs(lengths.mean() - 1.0) < 0.005
    headings = torch.atan2(data.actions[..., 1], data.actions[..., 0])
    turns = (headings[:, 1:] - headings[:, :-1]).double()
    assert abs(turns.cos().mean() - 0.8934) < 0.003
    assert abs(turns.sin().mean()) < 0.003


def test_door_trajectories_change_rooms(data):
    changes = data.changes_room()
    assert changes[data.door].float().mean() > 0.6
    assert changes[~data.door].float().mean() < 0.03
    assert 0.2 < changes.float().mean() < 0.3


def test_data_replays_through_the_environment_step(data):
    few = data[:500]
    env = TwoRoomsEnv()
    env.reset(episodes=Episodes(few.layouts, few.positions[:, 0], few.positions[:, -1]))
    for t in range(16):
        env.step(few.actions[:, t])
        assert torch.equal(env.positions, few.positions[:, t + 1])  # one transition function
    frames = few.frames(slice(0, 3))
    assert frames.shape == (3, 17, 2, 65, 65)


def test_same_seed_same_data():
    a, b = generate_trajectories(64, seed=7), generate_trajectories(64, seed=7)
    c = generate_trajectories(64, seed=torch.Generator().manual_seed(7))
    for field in ("positions", "actions", "layouts", "door"):
        assert torch.equal(getattr(a, field), getattr(b, field))
        assert torch.equal(getattr(a, field), getattr(c, field))
    assert not torch.equal(a.positions, generate_trajectories(64, seed=8).positions)


def test_a_selection_of_trajectories_keeps_each_ones_door_flag():
    """Indexing picks the same trajectories from every field: the door starts taken out are
    all door starts (a field left unindexed would mix them with the others)."""
    data = generate_trajectories(8, steps=3, seed=0, door_fraction=0.5)
    doors, others = data[data.door], data[~data.door]
    assert len(doors) == len(others) == 4 and doors.door.all() and not others.door.any()
    picked = data[[5, 0, 3]]
    for field in ("positions", "actions", "layouts", "door"):
        assert torch.equal(getattr(picked, field), getattr(data, field)[[5, 0, 3]])


@pytest.mark.parametrize("kwargs", [{"door_fraction": -0.2}, {"wall_fraction": -0.2},
                                    {"kappa": 0.0}])
def test_negative_shares_and_a_flat_turn_distribution_are_refused(kwargs):
    """A negative share would mark all but a few trajectories as door starts (a slice
    ``[:-k]``), and kappa 0 has no von Mises sampler: both refused by name."""
    with pytest.raises(ValueError, match="door_fraction and wall_fraction must be >= 0"):
        generate_trajectories(10, **kwargs)


def test_wall_starts_face_the_wall_away_from_the_door_and_leave_other_data_alone():
    base = generate_trajectories(2000, seed=3)
    more = generate_trajectories(2000, seed=3, wall_fraction=0.25)
    assert torch.equal(base.door, more.door) and torch.equal(base.layouts, more.layouts)
    moved = (base.positions[:, 0] != more.positions[:, 0]).any(-1)
    assert moved.sum() == 500 and not (moved & more.door).any()
    start, layouts = more.positions[moved, 0], more.layouts[moved].float()
    check_world(more.layouts[moved], start)
    gap = (start[:, 0] - layouts[:, 0]).abs() - 2.5  # from the face of the slab
    assert gap.min() >= 0.5 - 1e-4 and gap.max() <= 4 + 1e-4
    assert (start[:, 1] - layouts[:, 1]).abs().min() >= 10.5 - 1e-4  # 6 px beyond the door
    towards = (layouts[:, 0] - start[:, 0]).sign() * more.actions[moved, 0, 0]
    assert (towards > 0).all()  # the first step heads at the wall

    def stopped_by_the_middle_wall(d):  # the share of steps whose x the middle wall cut short
        cut = ((d.positions[:, 1:, 0] - d.positions[:, :-1, 0])
               - clip_actions(d.actions)[..., 0]).abs() > 0.05
        at_wall = (d.positions[:, 1:, 0] - d.layouts[:, :1]).abs() < 3
        return (cut & at_wall).float().mean()

    assert stopped_by_the_middle_wall(more) > 3 * stopped_by_the_middle_wall(base)
    with pytest.raises(ValueError, match="sum <= 1"):
        generate_trajectories(10, wall_fraction=0.7)


# ----------------------------------------------------------------- episodes


def test_episodes_start_and_goal_in_opposite_rooms():
    episodes = make_episodes(1000, seed=3)
    check_world(episodes.layouts, episodes.starts)
    check_world(episodes.layouts, episodes.goals)
    start_rooms = room_of(episodes.starts, episodes.layouts)
    assert (start_rooms != room_of(episodes.goals, episodes.layouts)).all()
    assert 0.4 < start_rooms.float().mean() < 0.6
    again = make_episodes(1000, seed=3)
    assert torch.equal(episodes.goals, again.goals) and torch.equal(episodes.starts, again.starts)
    assert not torch.equal(make_episodes(1000, seed=4).starts, episodes.starts)


def test_episodes_slice_and_concatenate_back():
    """Slices of episodes keep each task's layout, start and goal together, and ``concat``
    puts the pieces back in order: what the planner's batched runs rely on."""
    episodes = make_episodes(6, seed=2)
    parts = [episodes[:2], episodes[2:5], episodes[5:]]
    assert [len(part) for part in parts] == [2, 3, 1]
    assert torch.equal(parts[1].goals, episodes.goals[2:5])
    again = Episodes.concat(parts)
    for field in ("layouts", "starts", "goals"):
        assert torch.equal(getattr(again, field), getattr(episodes, field))


def test_the_goal_image_is_the_view_of_the_dot_standing_on_the_goal():
    """The planner compares observations with the goal image: with the dot exactly on its
    goal (not a rounded one) the two must be the same picture."""
    env = TwoRoomsEnv()
    env.reset(n=4, seed=2)
    assert not torch.equal(env.observe(), env.goal_images())
    env.positions = env.goals.clone()
    assert torch.equal(env.observe(), env.goal_images())


def test_the_environment_reports_the_room_the_dot_is_in():
    """``rooms()`` follows the dot, not its goal: 0 left of the wall at x = 30, 1 right."""
    env = TwoRoomsEnv()
    env.reset(episodes=Episodes(torch.tensor([[30, 30]] * 2),
                                torch.tensor([[10.0, 10.0], [50.0, 50.0]]),
                                torch.tensor([[50.0, 50.0], [10.0, 10.0]])))
    assert env.rooms().tolist() == [0, 1]
    env.positions = env.goals.clone()
    assert env.rooms().tolist() == [1, 0]


def test_environment_steps_and_scores():
    env = TwoRoomsEnv()
    obs = env.reset(n=8, seed=0)
    assert obs.shape == (8, 2, 65, 65) and env.goal_images().shape == (8, 2, 65, 65)
    goal_dot = env.goal_images()[:, 0].flatten(1).argmax(1)
    goal_px = env.goals.round().long()
    assert torch.equal(goal_dot, goal_px[:, 1] * 65 + goal_px[:, 0])
    start = env.positions.clone()
    action = torch.tensor([[0.6, 0.8]] * 8)
    env.step(action)
    assert env.steps_taken == 1
    assert torch.allclose(env.positions, transition(start, action, env.layouts))
    assert not env.success().any()  # goals are in the other room, far away
    env.positions = env.goals.clone()
    assert env.success().all() and torch.equal(env.distance_to_goal(), torch.zeros(8))
    # the paper's 4.5 px, edge included: 3-4-5 away fails, 4.5 straight up succeeds
    offsets = [[3.0, 4.0], [0.0, 4.5], [0.0, 4.6]] + [[0.0, 0.0]] * 5
    env.positions = env.goals + torch.tensor(offsets)
    assert env.distance_to_goal()[:3].tolist() == pytest.approx([5.0, 4.5, 4.6])
    assert env.success()[:3].tolist() == [False, True, False]
    # the record a planner's results are read from: every position, start first, and every
    # action as asked, a copy the caller may reuse
    assert len(env.path) == 2 and torch.equal(env.path[0], start)
    assert torch.equal(env.path[1], transition(start, action, env.layouts))
    asked = action.clone()
    action += 1.0  # the caller's tensor changes after the step
    assert len(env.actions) == 1 and torch.equal(env.actions[0], asked)
    for wrong in (torch.zeros(4, 2), torch.zeros(0, 2)):  # an empty batch too: a clear error
        with pytest.raises(ValueError, match=r"shape \(8, 2\)"):
            env.step(wrong)
    with pytest.raises(RuntimeError, match="reset"):
        TwoRoomsEnv().observe()


# ----------------------------------------------------------------- pinned numbers


def test_two_rooms_draws_are_pinned():
    """Numbers computed by the Two Rooms code before it learned W walls (commit fe26d95).

    Rooms in a row share this code; Two Rooms' data, episodes and layouts must not
    move by a single draw. Starts, layouts and episodes use only the generator and
    + - * /, so they are pinned exactly; the walk's end also runs through cos, sin
    and the inverse normal CDF, whose last bit may differ between CPUs, so it is
    pinned to 1e-4 px (a changed draw moves it by pixels).
    """
    data = generate_trajectories(6, seed=0, wall_fraction=0.25)
    assert data.layouts.tolist() == [[39, 17], [34, 38], [28, 47], [30, 28], [33, 36], [24, 21]]
    assert data.door.tolist() == [True, False, False, False, False, True]
    starts = torch.tensor([
        [42.85280227661133, 18.17264175415039], [10.51764965057373, 27.083908081054688],
        [31.537099838256836, 30.549461364746094], [44.67007827758789, 59.61702346801758],
        [29.154022216796875, 50.543209075927734], [18.145858764648438, 21.793764114379883]])
    assert torch.equal(data.positions[:, 0], starts)
    ends = torch.tensor([
        [29.856271743774414, 20.346826553344727], [22.2994327545166, 33.158103942871094],
        [31.39856719970703, 45.271331787109375], [56.326934814453125, 62.5],
        [28.75626564025879, 43.88933563232422], [31.277339935302734, 22.447824478149414]])
    torch.testing.assert_close(data.positions[:, -1], ends, rtol=0, atol=1e-4)

    episodes = make_episodes(4, seed=1)
    assert episodes.layouts.tolist() == [[40, 53], [34, 38], [44, 21], [38, 51]]
    assert torch.equal(episodes.starts, torch.tensor([
        [56.15228271484375, 36.42079162597656], [10.654484748840332, 31.878158569335938],
        [20.041824340820312, 58.662086486816406], [50.50969696044922, 41.49129867553711]]))
    assert torch.equal(episodes.goals, torch.tensor([
        [12.796688079833984, 22.226320266723633], [41.648502349853516, 33.46038818359375],
        [53.15907287597656, 50.1818962097168], [11.167207717895508, 48.5778694152832]]))
    assert torch.equal(TwoRoomsEnv().reset(n=4, seed=1), render(episodes.starts, episodes.layouts))

    g = torch.Generator().manual_seed(5)
    layouts = random_layouts(4, g)
    assert layouts.tolist() == [[31, 36], [34, 35], [37, 47], [30, 48]]
    assert torch.equal(sample_positions(layouts, g), torch.tensor([
        [3.3628196716308594, 5.917143821716309], [62.174346923828125, 41.71967697143555],
        [40.459999084472656, 45.115352630615234], [38.115989685058594, 36.83898162841797]]))
    assert torch.equal(sample_positions(layouts, g, torch.tensor([0, 1, 1, 0])), torch.tensor([
        [27.985027313232422, 42.355655670166016], [53.40412521362305, 17.449859619140625],
        [40.80257797241211, 3.983628273010254], [25.42290496826172, 49.387184143066406]]))


def test_shortest_path_lengths_by_hand():
    one = torch.tensor([[32, 20]])  # wall faces at x = 29.5 and 34.5, doorway rows 16.5-23.5
    pairs = {((10, 10), (20, 30)): 500 ** 0.5,  # one room: straight
             ((10, 20), (50, 20)): 40.0,  # straight through the doorway, either way
             ((50, 20), (10, 20)): 40.0,
             # round the wall: to the doorway's lower corner, across, on to the goal
             ((10, 50), (50, 50)): math.hypot(19.5, 26.5) + 5 + math.hypot(15.5, 26.5),
             # from the near face and to the far one (where a collision leaves the dot): still
             # round the wall, not through it
             ((29.5, 50), (50, 50)): 26.5 + 5 + math.hypot(15.5, 26.5),
             ((10, 50), (34.5, 50)): math.hypot(19.5, 26.5) + 5 + 26.5}
    for (start, goal), length in pairs.items():
        found = shortest_path_length(torch.tensor([start], dtype=torch.float32),
                                     torch.tensor([goal], dtype=torch.float32), one)
        assert found.item() == pytest.approx(length, abs=1e-3), (start, goal)
    three = torch.tensor([[20, 10, 45, 54]])  # doorways at rows 6.5-13.5 and 50.5-57.5
    corners = torch.tensor([[5.0, 30.0], [17.5, 13.5], [22.5, 13.5], [42.5, 50.5],
                            [47.5, 50.5], [60.0, 30.0]])
    found = shortest_path_length(corners[:1], corners[-1:], three)
    assert found.item() == pytest.approx((corners[1:] - corners[:-1]).norm(dim=1).sum().item())


def test_a_shortest_path_is_never_shorter_than_the_straight_line():
    generator = torch.Generator().manual_seed(3)
    for walls in (1, 2):
        layouts = random_layouts(500, generator, walls)
        starts, goals = sample_positions(layouts, generator), sample_positions(layouts, generator)
        length = shortest_path_length(starts, goals, layouts)
        straight = (starts - goals).norm(dim=1)
        assert (length >= straight - 1e-4).all()
        same = room_of(starts, layouts) == room_of(goals, layouts)
        assert torch.allclose(length[same], straight[same], atol=1e-4)


def test_trajectories_can_share_given_layouts():
    layouts = random_layouts(2, torch.Generator().manual_seed(0)).repeat_interleave(3, dim=0)
    data = generate_trajectories(6, seed=1, layouts=layouts)
    assert torch.equal(data.layouts, layouts)
    assert not in_wall(data.positions.flatten(0, 1),
                       layouts.repeat_interleave(17, dim=0)).any()
    assert torch.equal(data.frames(4), data.frames(slice(4, 5)))  # one trajectory: (1, T + 1, ...)
    with pytest.raises(ValueError, match="one layout per trajectory, n = 5; got 6"):
        generate_trajectories(5, seed=1, layouts=layouts)


def test_the_environment_asks_for_reset_before_anything_else():
    env = TwoRoomsEnv()
    for use in (env.observe, lambda: env.step(torch.zeros(1, 2)), env.goal_images,
                env.distance_to_goal, env.success, env.rooms):
        with pytest.raises(RuntimeError, match=r"call env.reset\(n, seed\) before"):
            use()


def test_actions_that_carry_a_gradient_move_the_dot_and_leave_the_world_without_one():
    """A plan found by gradient descent is a leaf that requires grad: the world takes its
    values (it is not differentiable) and keeps stepping."""
    env, plain = TwoRoomsEnv(), TwoRoomsEnv()
    env.reset(2, seed=0)
    plain.reset(2, seed=0)
    plan = torch.full((2, 3, 2), 0.5, requires_grad=True)
    for t in range(3):
        env.step(plan[:, t])
        plain.step(plan[:, t].detach())
    assert torch.equal(env.positions, plain.positions) and not env.positions.requires_grad
    assert env.steps_taken == 3 and not any(a.requires_grad for a in env.actions)


@pytest.mark.parametrize("start", [(10.0, 64.0), (10.0, 0.5), (64.0, 10.0), (0.5, 10.0),
                                   (float("nan"), 10.0)])
def test_a_start_outside_the_arena_is_refused(start):
    layouts, positions = torch.tensor([[30, 30]]), torch.tensor([start])
    with pytest.raises(ValueError, match="outside the arena"):
        check_world(layouts, positions)
    check_world(layouts, torch.tensor([[LOW, HIGH]]))  # the arena's own corner is allowed
