"""MPPI and CEM: the update against its formula, optima of known costs, goals in known dynamics."""

import ast
import inspect
import itertools
import json
import math
import textwrap
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from torch import nn

from ebjepa_tutorial import planning
from ebjepa_tutorial.course.presets import preset
from ebjepa_tutorial.envs import SUCCESS_RADIUS, clip_actions, render
from ebjepa_tutorial.envs.two_rooms import transition
from ebjepa_tutorial.evaluation.metrics import wilson_interval
from ebjepa_tutorial.planning import Habits, Noise, PlannerConfig
from research.beyond_fits import as_trajectories


class LinearLatentModel(nn.Module):
    """Hand-written dynamics ``z' = z + M a`` in 2-D; ``encode`` reads the dot's centroid."""

    def __init__(self, matrix=((1.0, 0.0), (0.0, 1.0))):
        super().__init__()
        self.config = SimpleNamespace(action_dim=2)
        self.register_buffer("matrix", torch.tensor(matrix))
        self.unused = nn.Parameter(torch.zeros(()))  # so the planner can find a device

    def encode(self, frames):
        dot = frames[:, 0].clamp_min(0)
        ys, xs = torch.meshgrid(torch.arange(65.0), torch.arange(65.0), indexing="ij")
        centroid = [(dot * grid).sum(dim=(1, 2)) for grid in (xs, ys)]
        return torch.stack(centroid, dim=1) / dot.sum(dim=(1, 2))[:, None]

    def rollout(self, z0, actions):
        return z0[:, None] + (actions @ self.matrix.T).cumsum(dim=1)


def generators(n, seed=0):
    return [torch.Generator().manual_seed(seed + i) for i in range(n)]


def test_mppi_weights_match_the_formula():
    costs = torch.tensor([[3.0, 1.0, 2.0, 1.5]])
    tau = 0.7
    expected = torch.exp(-(costs - 1.0) / tau)
    expected = expected / expected.sum()
    assert torch.allclose(planning.mppi_weights(costs, tau), expected)
    huge = costs + 1e6  # the S_min shift keeps exp from underflowing
    assert torch.allclose(planning.mppi_weights(huge, tau), expected)


def test_mppi_update_by_hand():
    # Two plans of one step in 1-D-like actions: elites {cost 0: a=1, cost 1: a=3}, tau=1.
    actions = torch.tensor([[1.0, 3.0, 10.0]]).view(1, 3, 1, 1).expand(1, 3, 1, 2).clone()
    costs = torch.tensor([[0.0, 1.0, 5.0]])
    mean, std = planning.mppi_update(actions, costs, elites=2, temperature=1.0)
    w0, w1 = 1 / (1 + math.exp(-1)), math.exp(-1) / (1 + math.exp(-1))
    expected_mean = w0 * 1 + w1 * 3
    expected_std = math.sqrt(w0 * (1 - expected_mean) ** 2 + w1 * (3 - expected_mean) ** 2)
    assert torch.allclose(mean, torch.full((1, 1, 2), expected_mean))
    assert torch.allclose(std, torch.full((1, 1, 2), expected_std))
    mean, std = planning.cem_update(actions, costs, elites=2)
    assert torch.allclose(mean, torch.full((1, 1, 2), 2.0))
    assert torch.allclose(std, torch.full((1, 1, 2), 1.0))


def test_low_temperature_mppi_picks_the_best_elite():
    actions = torch.randn(2, 8, 3, 2, generator=torch.Generator().manual_seed(0))
    costs = torch.rand(2, 8, generator=torch.Generator().manual_seed(1))
    mean, _ = planning.mppi_update(actions, costs, elites=4, temperature=1e-6)
    best = costs.argmin(dim=1)
    assert torch.allclose(mean, actions[torch.arange(2), best])


class Offset(nn.Module):
    """A "world" whose imagined latent at step k is the action minus ``target[k]``."""

    def __init__(self, target):
        super().__init__()
        self.config, self.target = SimpleNamespace(action_dim=2), target

    def rollout(self, z0, actions):
        return z0[:, None] + actions - self.target


@pytest.mark.parametrize("method", ["mppi", "cem"])
def test_the_iterations_find_the_optimum_of_a_known_energy(method):
    # Cost sum_k ||a_k - target_k|| to the goal 0: the optimum is the target itself.
    target = torch.tensor([[0.7, -0.4], [1.2, 0.3], [-0.5, -1.0]])
    config = PlannerConfig(method=method, horizon=3, samples=300, elites=30, iterations=30,
                           temperature=1.0, execute=1, noise=Noise(std=1.0, period=1, bound=2.0))
    result = planning.plan(Offset(target), torch.zeros(1, 2), torch.zeros(1, 2), config,
                           generators(1))
    assert torch.allclose(result.mean[0], target, atol=0.05)


def first_samples(mean, std, samples, gens, bound=1.8):
    """The plans that one iteration samples around ``mean`` (B, H, A) with spread ``std``."""
    config = PlannerConfig(horizon=mean.shape[1], samples=samples, elites=1, iterations=1,
                           execute=1, noise=Noise(std=std, period=1, bound=bound))
    z = torch.zeros(len(mean), 2)
    return planning.plan(LinearLatentModel(), z, z, config, gens, mean, record=True).history[0][0]


def test_smooth_noise_carries_a_plan_farther_than_white_noise():
    g = torch.Generator().manual_seed(0)
    white, smooth = (planning.smooth_noise(4000, 64, 2, period, g) for period in (1, 8))
    assert white.std().item() == pytest.approx(1.0, abs=0.02)  # same spread per step
    assert smooth.std().item() == pytest.approx(1.0, abs=0.02)
    # summed over 64 steps, white noise wanders sqrt(64) = 8 std; coherent noise much farther
    assert white.sum(dim=1).std().item() == pytest.approx(8.0, rel=0.05)
    assert smooth.sum(dim=1).std().item() > 3 * white.sum(dim=1).std().item()


def test_sampled_plans_are_clipped_and_keep_the_mean():
    mean = torch.full((2, 5, 2), 1.0)
    actions = first_samples(mean, 3.0, 50, generators(2), bound=1.8)
    lengths = actions.norm(dim=-1)  # clipped on the step's length, as the world clips it
    assert lengths.max() <= 1.8 + 1e-5
    assert (lengths > 1.79).float().mean() > 0.5  # std 3 sends most samples to the bound
    assert torch.equal(actions[:, 0], mean)  # (1, 1) is shorter than 1.8: kept as it is


def test_sampling_does_not_depend_on_the_batch():
    mean = torch.zeros(3, 4, 2)
    together = first_samples(mean, 1.0, 10, generators(3))
    alone = first_samples(mean[1:2], 1.0, 10, generators(1, seed=1))
    assert torch.equal(together[1], alone[0])


LINEAR = ((0.0, -1.0), (2.0, 0.0))  # a rotation and a stretch: actions do not map to latents 1:1


@pytest.mark.parametrize("method", ["mppi", "cem"])
def test_replanning_reaches_a_goal_under_linear_latent_dynamics(method):
    model = LinearLatentModel(LINEAR)
    config = PlannerConfig(method=method, horizon=12, samples=200, elites=20, iterations=4,
                           execute=2, noise=Noise(std=1.0))
    z, goal = torch.tensor([[0.0, 0.0], [5.0, -3.0]]), torch.tensor([[12.0, -15.0], [-4.0, 9.0]])
    gens, mean = generators(2), None
    for _ in range(20):
        result = planning.plan(model, z, goal, config, gens, mean)
        z = model.rollout(z, result.mean[:, : config.execute])[:, -1]
        mean = planning.shift_plan(result.mean, config.execute)
    assert (z - goal).norm(dim=1).max() < 1.0  # from 19 and 13 latent units away
    assert result.costs.shape == (2, config.iterations)


@pytest.mark.parametrize("method", ["mppi", "cem"])
def test_last_state_cost_plans_to_end_at_the_goal(method):
    # Only the end of the plan counts: the imagined last state lands on the goal.
    model = LinearLatentModel(LINEAR)
    config = PlannerConfig(method=method, cost="last", horizon=12, iterations=15,
                           noise=Noise(std=1.0))
    z, goal = torch.zeros(2, 2), torch.tensor([[12.0, -15.0], [-4.0, 9.0]])
    result = planning.plan(model, z, goal, config, generators(2))
    assert (model.rollout(z, result.mean)[:, -1] - goal).norm(dim=1).max() < 1.0


def test_costs_fall_over_iterations():
    model = LinearLatentModel()
    config = PlannerConfig(horizon=10, iterations=6, execute=1)
    result = planning.plan(model, torch.zeros(4, 2), torch.full((4, 2), 8.0), config,
                           generators(4), record=True)
    assert (result.costs[:, -1] < result.costs[:, 0]).all()
    assert len(result.history) == 6 and result.history[0][0].shape == (4, 200, 10, 2)
    # each iteration's figure is its cheapest sample (what notebook 06 prints), not a mean
    best = torch.stack([costs.min(dim=1).values for _, costs in result.history], dim=1)
    assert torch.equal(result.costs, best)


def test_a_shifted_plan_drops_what_was_executed_and_pads_with_zeros():
    mean = torch.arange(6.0).view(1, 6, 1)  # (B, H, A): actions 0..5
    assert planning.shift_plan(mean, 2).flatten().tolist() == [2, 3, 4, 5, 0, 0]


def test_the_summary_averages_first_arrival_over_the_episodes_that_arrived():
    episodes, _ = planning.episode_generators([0, 1, 2])
    result = planning.EpisodeResults(
        [0, 1, 2], episodes, torch.zeros(3, 3, 2), torch.zeros(3, 2, 2),
        torch.tensor([True, False, True]), torch.tensor([10, -1, 30]), 3.0, 3.0)
    assert "mean first arrival 20 steps" in result.summary()  # -1: never arrived, left out


class XOnly(LinearLatentModel):
    """The dot's x alone: an energy blind to y."""

    def encode(self, frames):
        return super().encode(frames)[:, :1]


def test_true_motion_plans_with_the_models_energy():
    # world="true" imagines the real motion but scores it with the model's latent distance:
    # an energy that sees only x brings x to the goal and leaves y where it lies
    result = planning.run_episodes(XOnly(), range(2), SMALL_PLANNER, world="true")
    gap = (result.paths[:, -1] - result.episodes.goals).abs()  # (2, 2): |dx|, |dy| at the end
    assert (gap[:, 0] < 2).all() and not result.success.any()


def test_planning_cost_sum_and_last():
    model = LinearLatentModel()
    actions = torch.ones(1, 1, 3, 2)  # imagined latents (1,1), (2,2), (3,3) from the origin
    goal = torch.tensor([[3.0, 3.0]])
    distances = torch.tensor([2.0, 1.0, 0.0]) * math.sqrt(2)
    z0 = torch.zeros(1, 2)
    assert torch.allclose(planning.planning_cost(model, z0, goal, actions, "sum"),
                          distances.sum().view(1, 1))
    assert torch.allclose(planning.planning_cost(model, z0, goal, actions, "last"),
                          torch.zeros(1, 1))


def test_episodes_reproduce_from_their_seed():
    model = LinearLatentModel()
    config = PlannerConfig(horizon=8, samples=32, elites=4, iterations=2, execute=4)
    batch = planning.run_episodes(model, [11, 12, 13], config, steps=16)
    again = planning.run_episodes(model, [11, 12, 13], config, steps=16)
    alone = planning.run_episodes(model, [12], config, steps=16)
    assert torch.equal(batch.paths, again.paths)
    assert torch.allclose(batch.paths[1], alone.paths[0], atol=1e-4)
    assert batch.paths.shape == (3, 17, 2)


def test_success_and_first_arrival_agree_with_the_paths():
    model = LinearLatentModel()  # no walls in its imagination: some episodes get stuck
    config = PlannerConfig(horizon=16, samples=64, elites=8, iterations=3, execute=4)
    result = planning.run_episodes(model, range(8), config, steps=120)
    distance = (result.paths - result.episodes.goals[:, None]).norm(dim=-1)
    assert torch.equal(result.success, distance[:, -1] <= SUCCESS_RADIUS)
    within = distance <= SUCCESS_RADIUS
    expected_first = torch.where(within.any(1), within.float().argmax(1), torch.tensor(-1))
    assert torch.equal(result.first_arrival, expected_first)
    low, high = result.interval()
    assert (low, high) == wilson_interval(int(result.success.sum()), 8)
    assert "episodes" in result.summary()


def test_success_is_where_an_episode_ends_not_whether_it_passed_the_goal():
    def visit_then_leave(model, env, config, generators, steps, arrived=None, aim=None):
        env.positions = env.goals.clone()  # at the goal: the first step records it
        away = torch.where(env.goals[:, 1:] < 32, 1.8, -1.8)  # (B, 1): up or down the room
        env.step(torch.zeros(len(env.goals), 2))
        for _ in range(steps - 1):  # then 1.8 px a step away from it, along its room
            env.step(torch.cat([torch.zeros_like(away), away], dim=1))

    result = planning.run_episodes(LinearLatentModel(), range(4), PlannerConfig(), steps=5,
                                   loop=visit_then_leave)
    assert result.first_arrival.tolist() == [1, 1, 1, 1]  # each was at its goal after step 1
    assert not result.success.any()  # and ended 7.2 px from it


def test_wilson_interval_by_hand():
    low, high = wilson_interval(0, 10)
    assert low == 0 and high == pytest.approx(1.96**2 / (10 + 1.96**2))
    low, high = wilson_interval(50, 100)
    assert (low, high) == pytest.approx((0.4038, 0.5962), abs=1e-4)
    with pytest.raises(ValueError):
        wilson_interval(5, 3)


@pytest.mark.parametrize("kwargs, words", [
    (dict(horizon=0), "horizon"), (dict(samples=0), "samples"), (dict(elites=300), "elites"),
    # one sample is the mean alone: nothing explores, and its noise would be normalised by
    # the spread of a single number (NaN)
    (dict(samples=1, elites=1, horizon=1, execute=1), "samples .*>= 2"),
    (dict(method="adam"), "method"), (dict(execute=100), "execute"),
    (dict(temperature=0.0), "temperature"),
])
def test_bad_planner_configs_name_the_problem(kwargs, words):
    with pytest.raises(ValueError, match=words):
        PlannerConfig(**kwargs)


@pytest.mark.parametrize("kwargs, words", [
    (dict(stop_px=-1.0), "stop_px"), (dict(stop_px=float("nan")), "stop_px"),
    (dict(warm_iterations=-1), "warm_iterations"),
])
def test_bad_habits_name_the_problem(kwargs, words):
    with pytest.raises(ValueError, match=words):
        Habits(**kwargs)


def test_a_goal_image_of_the_wrong_shape_is_named():
    from ebjepa_tutorial.models.world import WORLD_CONFIGS, WorldModel
    model = WorldModel(WORLD_CONFIGS["ci"]).fit_input_stats(render(
        torch.tensor([[10.0, 10.0]]), torch.tensor([[30, 30]])))
    with pytest.raises(ValueError, match="frames must be"):
        model.encode(torch.zeros(1, 3, 65, 65))


def test_batches_run_one_after_the_other_give_the_same_episodes():
    model = LinearLatentModel()
    config = PlannerConfig(horizon=8, samples=32, elites=4, iterations=2, execute=4)
    whole = planning.run_episodes(model, [3, 4, 5], config, steps=8)
    split = planning.run_episodes(model, [3, 4, 5], config, steps=8, batch=2)
    assert split.seeds == [3, 4, 5]
    assert torch.allclose(whole.paths, split.paths, atol=1e-4)
    assert torch.equal(whole.episodes.goals, split.episodes.goals)


def test_the_first_episodes_of_a_batch_are_a_smaller_batch():
    model = LinearLatentModel()
    config = PlannerConfig(horizon=8, samples=32, elites=4, iterations=2, execute=4)
    whole = planning.run_episodes(model, [3, 4, 5], config, steps=8)
    part = whole.first(2)
    assert part.seeds == [3, 4] and torch.equal(part.paths, whole.paths[:2])
    assert part.cpu_seconds == pytest.approx(whole.cpu_seconds * 2 / 3)


@pytest.mark.slow  # a fresh interpreter runs the script
def test_the_benchmark_prints_its_figures(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    from ebjepa_tutorial.models.world import WORLD_CONFIGS, WorldModel
    from ebjepa_tutorial.training.checkpoints import save_checkpoint
    model = WorldModel(WORLD_CONFIGS["ci"]).fit_input_stats(
        render(torch.tensor([[10.0, 10.0], [50.0, 40.0]]), torch.tensor([[30, 30], [30, 30]])))
    path = save_checkpoint(tmp_path / "ci.pt", model=model.state_dict())
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run(
        [sys.executable, "-m", "research.benchmarks.planning", "--checkpoint", str(path),
         "--episodes", "3", "--batch", "2", "--horizon", "4", "--samples", "8", "--elites", "2",
         "--iterations", "1", "--threads", "1"],
        cwd=root, capture_output=True, text=True, check=True).stdout
    assert "samples=8, elites=2, iterations=1" in out.splitlines()[0]  # the flags reach it
    last = dict(item.split("=") for item in out.strip().splitlines()[-1].split())
    assert set(last) == {"success", "ci_low", "ci_high", "s_per_episode"}
    assert 0 <= float(last["ci_low"]) <= float(last["success"]) <= float(last["ci_high"]) <= 1


def test_a_collapsed_spread_is_held_at_the_smallest_spread():
    # One elite: its weighted spread is 0, and a search that stops exploring stays stuck.
    config = PlannerConfig(horizon=6, samples=50, elites=1, iterations=3, noise=Noise(period=1))
    result = planning.plan(LinearLatentModel(), torch.zeros(1, 2), torch.full((1, 2), 5.0),
                           config, generators(1), record=True)
    assert torch.equal(result.std, torch.full((1, 6, 2), planning.MIN_STD))
    spread = result.history[-1][0][0, 1:].std(dim=0)  # the last iteration still samples
    assert (spread > 0).all()


def test_true_dynamics_moves_each_row_in_its_own_episode_layout():
    layouts = torch.tensor([[30, 50], [30, 15]])  # same wall, doors far apart
    imagine = planning.TrueDynamics(layouts)  # model=None: the energy is in pixels
    episode = torch.tensor([0.0, 0, 0, 1, 1, 1])[:, None]  # rows 0-2: episode 0, 3-5: 1
    start = torch.cat([episode, torch.tensor([[27.0, 15.0]]).repeat(6, 1)], dim=1)
    actions = torch.tensor([1.5, 0.0]).repeat(6, 4, 1)  # walk right for 4 steps
    path = imagine.rollout(start, actions)  # (6, 4, 3): [episode, x, y]
    expected, per_row = [start[:, 1:]], layouts.repeat_interleave(3, dim=0)
    for k in range(4):
        expected.append(transition(expected[-1], actions[:, k], per_row))
    assert torch.equal(path[..., 1:], torch.stack(expected[1:], dim=1))
    assert torch.equal(path[..., 0], episode.expand(6, 4))
    assert path[:3, -1, 1].max() < 28 and path[3:, -1, 1].min() > 32  # wall vs door


def test_true_dynamics_looks_up_the_model_encoding_on_the_grid():
    model, layout = LinearLatentModel(), torch.tensor([[40, 20]])
    imagine = planning.TrueDynamics(layout, model)
    on_grid = torch.tensor([[10.5, 33.5]])  # LOW = 1.5, spacing 1
    state = torch.tensor([[0.0, 10.6, 33.4]])  # episode 0, nearest grid point on_grid
    assert torch.equal(imagine.embed(state), model.encode(render(on_grid, layout)))
    goal = torch.tensor([[0.0, 20.5, 33.5]])
    assert imagine.distance(state, goal).item() == pytest.approx(10.0, abs=1e-3)


SMALL_PLANNER = PlannerConfig(samples=32, elites=6, iterations=2, execute=8)


@pytest.mark.parametrize("config", [
    SMALL_PLANNER, pytest.param(PlannerConfig(), marks=pytest.mark.slow, id="course-planner")])
def test_with_true_motion_and_the_euclidean_energy_the_planner_crosses_the_door(config):
    result = planning.run_episodes(LinearLatentModel(), range(2), config, world="true_xy")
    assert result.success.all()  # each start and goal lie in opposite rooms
    with pytest.raises(ValueError, match="world must be one of"):
        planning.run_episodes(LinearLatentModel(), [0], config, world="perfect")
    with pytest.raises(ValueError, match="at least one seed.*got 0 seeds"):  # not range()'s
        planning.run_episodes(LinearLatentModel(), [], config)
    with pytest.raises(ValueError, match="steps None or an int >= 1.*steps=0"):  # not stack's
        planning.run_episodes(LinearLatentModel(), [0], config, steps=0)
    with pytest.raises(ValueError, match="batch None or an int >= 1.*batch=0"):  # not all
        planning.run_episodes(LinearLatentModel(), [0], config, batch=0)
    with pytest.raises(TypeError, match=r"one episode each \(e.g. range\(5, 5 \+ 10\)\)"):
        planning.run_episodes(LinearLatentModel(), 5, config)


def test_energy_by_distance_of_a_position_latent_is_the_ring_distance():
    episodes, _ = planning.episode_generators([3, 4])
    edges = (0, 10, 20, 40)
    profile = planning.energy_by_distance(LinearLatentModel(), episodes, edges, spacing=1.0)
    assert profile.shape == (3,)
    # the latent is the dot's centroid, so the energy is the distance itself: each ring's
    # mean lies inside the ring (the centroid is biased by < 0.5 px near the border)
    for mean, low, high in zip(profile, edges[:-1], edges[1:]):
        assert low - 0.5 < mean < high + 0.5
    assert profile.diff().gt(0).all()


def test_success_bars_show_rates_intervals_and_the_reference_on_its_bar():
    import matplotlib

    matplotlib.use("agg")
    from ebjepa_tutorial import viz

    rows = {"full loss": (0.8, 0.65, 0.9), "without x": (0.1, 0.03, 0.25)}
    ax = viz.plot_success_rates(rows, reference={"without x": 0.46, "not drawn": 0.5})
    assert [bar.get_height() for bar in ax.patches] == pytest.approx([0.8, 0.1])
    ticks = ax.collections[-1].get_segments()  # the reference, drawn last
    assert len(ticks) == 1
    (x0, y0), (x1, y1) = ticks[0]
    assert (y0, y1) == (0.46, 0.46) and x0 < 1 < x1  # across the second bar only
    whiskers = ax.containers[0].lines[2][0].get_segments()
    ends = [end for seg in whiskers for end in (seg[0][1], seg[1][1])]
    assert ends == pytest.approx([0.65, 0.9, 0.03, 0.25])
    matplotlib.pyplot.close(ax.figure)


def test_the_wall_test_by_door_distance_draws_each_series_side_by_side():
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("agg")
    from ebjepa_tutorial import viz

    bins = [{"lo": 0, "hi": 8, "n": 5, "stopped": 0.5}, {"lo": 8, "hi": 65, "n": 9, "stopped": 1.0}]
    other = [{**b, "stopped": b["stopped"] / 2} for b in bins]
    ax = viz.plot_stopped_by_door_distance({"a": bins, "b": other})
    assert [bar.get_height() for bar in ax.patches] == pytest.approx([0.5, 1.0, 0.25, 0.5])
    centres = [bar.get_x() + bar.get_width() / 2 for bar in ax.patches]
    assert centres == pytest.approx([-0.2, 0.8, 0.2, 1.2])  # each pair centred on its tick
    assert [t.get_text() for t in ax.get_xticklabels()] == ["0-8 px\n(5 steps)",
                                                           "8-65 px\n(9 steps)"]
    matplotlib.pyplot.close(ax.figure)


def test_plot_energy_shapes_draws_each_profile_over_its_ring_middles_scaled_to_1():
    import matplotlib

    matplotlib.use("agg")
    from ebjepa_tutorial import viz

    ax = viz.plot_energy_shapes({"a": torch.tensor([1.0, 2.0, 4.0]),
                                 "b": torch.tensor([3.0, 3.0, 6.0])}, (0, 2, 6, 10))
    (xa, ya), (xb, yb) = (line.get_data() for line in ax.lines)
    assert list(xa) == list(xb) == [1.0, 4.0, 8.0]
    assert list(ya) == pytest.approx([0.25, 0.5, 1.0])
    assert list(yb) == pytest.approx([0.5, 0.5, 1.0])
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["a", "b"]
    matplotlib.pyplot.close(ax.figure)


def test_two_rooms_pictures_colour_the_floor_the_walls_and_the_dot():
    """An observation (dot, walls) as a picture: white floor, grey (0.35, 0.4, 0.5) walls, a
    red (0.85, 0.1, 0.1) dot, and a dot pixel at half intensity half way from floor to red."""
    import matplotlib

    matplotlib.use("agg")
    from ebjepa_tutorial import viz

    obs = torch.zeros(2, 3, 3)
    obs[1, 0, 0] = 1.0  # a wall pixel
    obs[0, 1, 1], obs[0, 2, 2] = 1.0, 0.5  # the dot's centre, and its flank
    rgb = viz.two_rooms_rgb(obs)
    assert rgb.shape == (3, 3, 3)
    assert rgb[0, 1].tolist() == pytest.approx([1.0, 1.0, 1.0])
    assert rgb[0, 0].tolist() == pytest.approx([0.35, 0.4, 0.5])
    assert rgb[1, 1].tolist() == pytest.approx([0.85, 0.1, 0.1])
    assert rgb[2, 2].tolist() == pytest.approx([0.925, 0.55, 0.55])


def test_episode_pictures_show_every_wall_the_goal_the_start_and_the_trail_so_far():
    """``draw_two_rooms`` draws both walls of a Three Rooms layout with row 0 at the top (as
    an observation is shown), the success circle and the star on the goal, the black dot on
    the start; a frame of ``animate_episodes`` draws the trail up to its step, and the
    frames, ``every`` steps apart, end on the last position."""
    import matplotlib

    matplotlib.use("agg")
    from ebjepa_tutorial import viz
    from ebjepa_tutorial.envs import Episodes

    layouts = torch.tensor([[30, 30, 30, 30], [20, 15, 44, 50]])
    starts, goals = torch.tensor([[5.0, 5.0], [5.0, 60.0]]), torch.tensor([[9.0, 9.0], [60.0, 5.0]])
    paths = torch.arange(20.0).view(2, 5, 2)  # two episodes of 4 steps
    results = SimpleNamespace(episodes=Episodes(layouts, starts, goals), paths=paths)
    animation = viz.animate_episodes(results, [1], every=2, titles=["second"])
    assert list(animation.new_frame_seq()) == [0, 2, 4]
    animation._init_draw()  # its first frame, as a notebook's first draw would (else it warns)
    trail, dot = animation._func(2)  # FuncAnimation's drawing function, at step 2
    assert trail.get_xydata().tolist() == paths[1, :3].tolist()
    assert dot.get_xydata().tolist() == paths[1, 2:3].tolist()
    ax = trail.axes
    picture = ax.images[0].get_array()
    for column in (20, 44):  # both walls, grey; the floor between them white
        assert picture[30, column].tolist() == pytest.approx([0.35, 0.4, 0.5])
    assert picture[30, 32].tolist() == pytest.approx([1.0, 1.0, 1.0])
    assert ax.yaxis_inverted()
    (circle,) = ax.patches
    assert circle.center == (60.0, 5.0) and circle.radius == SUCCESS_RADIUS
    assert [marks.get_offsets().tolist() for marks in ax.collections] == [[[60.0, 5.0]],
                                                                          [[5.0, 60.0]]]
    matplotlib.pyplot.close(ax.figure)


def test_energy_maps_show_each_energy_at_its_point_with_the_anchor_on_top():
    """``energy[i, j]``, the energy at ``(x, y) = (coords[j], coords[i])``, is drawn in the
    cell centred on that point (rows upwards; up to half a step either side, the edges
    included), and the anchor's star at ``(anchor[0], anchor[1])``."""
    import matplotlib

    matplotlib.use("agg")
    from ebjepa_tutorial import viz

    coords = torch.linspace(-2.0, 2.0, 5)
    energy = 10 * torch.arange(5.0)[:, None] + torch.arange(5.0)  # 10 i + j
    ax = viz.plot_energy_map(coords, energy, (1.0, -2.0), torch.tensor([[0.5, 1.5]]))
    image = ax.images[0]
    for i, j in itertools.product(range(5), repeat=2):
        for dx, dy in itertools.product((-0.45, 0.45), repeat=2):
            x, y = coords[j].item() + dx, coords[i].item() + dy
            xs, ys = ax.transData.transform((x, y))
            assert image.get_cursor_data(SimpleNamespace(x=xs, y=ys)) == 10 * i + j, (x, y)
    points, anchor = ax.collections
    assert points.get_offsets().tolist() == [[0.5, 1.5]]
    assert anchor.get_offsets().tolist() == [[1.0, -2.0]]
    matplotlib.pyplot.close(ax.figure)


def test_spectra_are_drawn_from_rank_1_with_zeros_kept_on_the_log_scale():
    """Eigenvalues in the order given, largest first, at ranks 1 .. D; a zero eigenvalue is
    drawn at 1e-8 (a log scale has no 0), one labelled line per run."""
    import matplotlib

    matplotlib.use("agg")
    from ebjepa_tutorial import viz

    ax = viz.plot_spectrum({"run": torch.tensor([4.0, 1.0, 0.0])})
    ((ranks, values),) = (line.get_data() for line in ax.get_lines())
    assert list(ranks) == [1, 2, 3] and list(values) == pytest.approx([4.0, 1.0, 1e-8])
    assert ax.get_yscale() == "log"
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["run"]
    matplotlib.pyplot.close(ax.figure)


def test_embeddings_are_drawn_on_their_first_two_principal_components():
    """Points spread 3 along one direction and 1 along another, turned in 3-D and moved off
    the origin: the scatter shows those two spreads, in that order (each up to its sign)."""
    import matplotlib

    matplotlib.use("agg")
    from ebjepa_tutorial import viz

    a, b = torch.tensor([3.0, -3.0, 0.0, 0.0]), torch.tensor([0.0, 0.0, 1.0, -1.0])
    turn = torch.linalg.qr(torch.randn(3, 3, generator=torch.Generator().manual_seed(0)))[0]
    z = torch.stack([a, b, torch.zeros(4)], 1) @ turn.T + torch.tensor([5.0, -3.0, 2.0])
    ax = viz.plot_embedding(z, torch.arange(4))
    xy = torch.as_tensor(ax.collections[0].get_offsets().data)
    assert torch.allclose(xy.abs().float(), torch.stack([a, b], 1).abs(), atol=1e-4)
    matplotlib.pyplot.close(ax.figure)


@pytest.mark.slow  # three panels: about 0.1 s
def test_characteristic_function_panels_show_the_modulus_and_the_epps_pulley_integrand():
    """For 8 samples all at x = 1, phi_N(t) = exp(i t): Re is cos t, |phi_N| is 1; the third
    panel's curve integrates over [-3, 3] to the Epps-Pulley statistic in its legend, and the
    histogram is a density (area 1)."""
    import matplotlib

    matplotlib.use("agg")
    from ebjepa_tutorial import viz
    from ebjepa_tutorial.losses.sigreg import epps_pulley

    x = torch.ones(8)
    axes = viz.plot_characteristic_functions({"ones": x})
    _, real, modulus = axes[1].get_lines()
    t = torch.as_tensor(real.get_xdata())
    assert torch.allclose(torch.as_tensor(real.get_ydata()), t.cos(), atol=1e-5)
    assert torch.allclose(torch.as_tensor(modulus.get_ydata()), torch.ones_like(t), atol=1e-5)
    (gap,) = axes[2].get_lines()
    area = torch.trapezoid(torch.as_tensor(gap.get_ydata()), torch.as_tensor(gap.get_xdata()))
    assert area.item() == pytest.approx(epps_pulley(x).item(), rel=1e-3)
    assert sum(bar.get_height() * bar.get_width() for bar in axes[0].patches) == pytest.approx(1)
    matplotlib.pyplot.close(axes[0].figure)


def test_episodes_keep_the_actions_that_replay_their_paths():
    """What the agent asked, moved by the world's transition, is the path it took, walls
    included (the linear model plans straight through them): offline data, as
    ``generate_trajectories`` stores a random walk."""
    config = planning.PlannerConfig(horizon=8, samples=32, elites=4, iterations=2, execute=4)
    played = as_trajectories(planning.run_episodes(LinearLatentModel(), [10, 11], config,
                                                   steps=40, walls=2))
    assert played.actions.shape == (2, 40, 2) and played.positions.shape == (2, 41, 2)
    for t in range(40):
        moved = transition(played.positions[:, t], played.actions[:, t], played.layouts)
        assert torch.equal(moved, played.positions[:, t + 1])
    asked = clip_actions(played.actions).norm(dim=-1)
    assert (played.positions.diff(dim=1).norm(dim=-1) < asked - 0.5).any()  # a wall stopped it


def test_a_summary_with_no_arrival_says_so_instead_of_nan():
    episodes, _ = planning.episode_generators([0, 1])
    result = planning.EpisodeResults([0, 1], episodes, torch.zeros(2, 3, 2), torch.zeros(2, 2, 2),
                                     torch.zeros(2, dtype=torch.bool), torch.tensor([-1, -1]),
                                     cpu_seconds=1.0, wall_seconds=1.0)
    assert "no episode reached the goal" in result.summary() and "nan" not in result.summary()


# -- on the model's device ------------------------------------------------------------------
class MetaModel(nn.Module):
    """A model on another device, "meta" (shapes without numbers: there is no GPU here), that
    refuses inputs from anywhere else. Latents are ``(B, 3)``; a rollout stays on meta, while
    ``encode`` answers zeros on the CPU, as a copy back from a GPU would (a meta tensor holds
    nothing to copy)."""

    def __init__(self):
        super().__init__()
        self.config = SimpleNamespace(action_dim=2)
        self.unused = nn.Parameter(torch.zeros((), device="meta"))

    def encode(self, frames):
        assert frames.is_meta, f"frames on {frames.device}, the model is on meta"
        return torch.zeros(len(frames), 3)

    def rollout(self, z0, actions):
        assert z0.is_meta and actions.is_meta, f"{z0.device} and {actions.device}, not meta"
        return z0.new_zeros(len(z0), actions.shape[1], 3)


def test_plans_and_energy_maps_are_computed_on_the_models_device():
    model, z = MetaModel(), torch.zeros(2, 3, device="meta")
    config = PlannerConfig(horizon=6, samples=8, elites=2, iterations=2, execute=2)
    result = planning.plan(model, z, z, config, generators(2))
    assert {t.device.type for t in (result.mean, result.std, result.costs)} == {"meta"}
    episodes, _ = planning.episode_generators([0])
    _, energy = planning.energy_map(model, episodes.layouts[0], episodes.goals[0], spacing=8.0)
    assert energy.device.type == "cpu" and (energy[energy.isfinite()] == 0).all()
    rings = planning.energy_by_distance(model, episodes, spacing=8.0)
    assert rings.device.type == "cpu"


def test_the_arrival_distance_of_a_position_latent_is_the_distance_moved():
    model = LinearLatentModel()  # its latent is the dot's centre in px
    for px in (0.5, 2.0, 3.0):  # walls shorten a few moves; the median is the free move
        assert planning.arrival_distance(model, px) == pytest.approx(px, abs=1e-3)


def test_an_arrived_agent_stands_still_and_plans_no_more(monkeypatch):
    planned = []

    def counting_plan(imagine, z0, *args, **kwargs):
        planned.append(len(z0))
        return planning_plan(imagine, z0, *args, **kwargs)

    planning_plan = planning.plan
    monkeypatch.setattr(planning, "plan", counting_plan)
    model, seeds = LinearLatentModel(), range(6)
    config = PlannerConfig(horizon=16, samples=64, elites=8, iterations=3, execute=4,
                           habits=Habits(stop_px=2.0))
    result = planning.run_episodes(model, seeds, config, steps=120, world="learned")
    arrived = planning.arrival_distance(model, 2.0)
    at_replans = result.paths[:, ::config.execute][:, :-1]  # (B, re-plans, 2)
    layouts = result.episodes.layouts
    here = torch.stack([model.encode(render(p, layouts)) for p in at_replans.unbind(1)], 1)
    goal = model.encode(result.episodes.goal_images())
    stands = (here - goal[:, None]).norm(dim=-1) < arrived  # (B, re-plans)
    assert stands.any(), "no episode arrived: the test shows nothing"
    moves = (result.paths[:, 1:] - result.paths[:, :-1]).norm(dim=-1).view(len(seeds), -1, 4)
    assert (moves[stands] == 0).all()  # the four steps after each arrived re-plan
    assert sum(planned) == (~stands).sum()  # only the episodes under way were planned
    assert result.success[stands.any(1)].all()  # 2 px from the goal is inside the 4.5 px radius
    xy = planning.run_episodes(model, seeds, config, steps=120, world="true_xy")
    last = (xy.paths[:, -1] - xy.episodes.goals).norm(dim=-1)  # arrived: stood about 2 px away
    arrived_xy = xy.first_arrival >= 0
    assert arrived_xy.any() and (last[arrived_xy] < 3.0).all()  # 2 px on a 1-px grid


def test_warm_replans_refine_the_plan_warm_iterations_times(monkeypatch):
    iterations = []

    def recording_plan(imagine, z0, z_goal, config, *args, **kwargs):
        iterations.append(config.iterations)
        return planning_plan(imagine, z0, z_goal, config, *args, **kwargs)

    planning_plan = planning.plan
    monkeypatch.setattr(planning, "plan", recording_plan)
    config = PlannerConfig(horizon=8, samples=16, elites=4, iterations=5,
                           habits=Habits(warm_iterations=2))
    planning.run_episodes(LinearLatentModel(), [3, 4], config, steps=12)
    assert iterations == [5, 2, 2]  # the cold first plan, then one per re-plan
    iterations.clear()
    planning.run_episodes(LinearLatentModel(), [3, 4], replace(config, habits=Habits(0)),
                          steps=12)
    assert iterations == [5, 5, 5]
    iterations.clear()
    planning.run_episodes(LinearLatentModel(), [3, 4], replace(config, habits=Habits(9)),
                          steps=12)
    assert iterations == [5, 5, 5]  # never more than J


# -- one source of truth: notebook 06 shows the package's iteration and loop, and runs its copy
NOTEBOOK_06 = Path(__file__).resolve().parents[1] / "notebooks" / "06_planning.ipynb"


def notebook_cell(name: str) -> str:
    """The source of notebook 06's cell (tagged package-source) that defines ``name``."""
    cells = json.loads(NOTEBOOK_06.read_text())["cells"]
    found = [cell for cell in cells if "package-source" in cell["metadata"].get("tags", [])
             and f"def {name}(" in "".join(cell["source"])]
    assert len(found) == 1, f"notebook 06 has {len(found)} package-source cells defining {name}"
    return "".join(found[0]["source"])


def normalised(source: str) -> list[str]:
    """The lines of a function's source with trailing spaces and blank lines dropped."""
    return [line.rstrip() for line in textwrap.dedent(source).splitlines() if line.strip()]


@pytest.mark.parametrize("function", [planning.mppi_iteration, planning.mpc_loop])
def test_notebook_06_shows_the_package_copy_of_the_iteration_and_the_loop(function):
    source = notebook_cell(function.__name__)
    tree = ast.parse(source)
    [definition] = [node for node in tree.body if isinstance(node, ast.FunctionDef)]
    shown = "\n".join(source.splitlines()[definition.lineno - 1:])  # to the cell's end
    assert normalised(shown) == normalised(inspect.getsource(function)), (
        f"notebook 06's {function.__name__} differs from planning.{function.__name__}: "
        "edit both, or copy the package's into the notebook")


def notebook_functions(edit=lambda name, source: source) -> dict:
    """Run notebook 06's iteration and loop cells (after ``edit``), as the notebook does."""
    namespace = {"torch": torch, "mppi_update": planning.mppi_update}
    for name in ("mppi_iteration", "mpc_loop"):
        exec(edit(name, notebook_cell(name)), namespace)  # noqa: S102 - the notebook's own code
    return namespace


def ci_episodes(loop):
    config = preset("06", "ci").planner
    return planning.run_episodes(LinearLatentModel(), range(3), config, steps=24, loop=loop)


def test_the_notebooks_loop_plays_the_packages_episodes_and_an_edit_changes_them():
    package = ci_episodes(planning.mpc_loop)
    assert torch.equal(ci_episodes(notebook_functions()["mpc_loop"]).paths, package.paths)

    def every_two_steps(name, source):  # re-plan after 2 actions instead of m = 4
        return source.replace("config.execute", "2") if name == "mpc_loop" else source

    def equal_weights(name, source):  # the update line of the iteration: CEM's instead
        old = "mean, std = mppi_update(actions, costs, config.elites, config.temperature)"
        if name != "mppi_iteration":
            return source
        assert old in source
        return source.replace(old, "mean, std = cem_update(actions, costs, config.elites)")

    for edit in (every_two_steps, equal_weights):
        edited = ci_episodes(notebook_functions(edit)["mpc_loop"])
        assert not torch.equal(edited.paths, package.paths), edit.__name__
