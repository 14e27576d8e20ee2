"""Planning and Two Rooms on inputs that used to fail quietly (issue 26, items 6, 7, 10, 12).

Goals of the wrong shape, planner settings that cannot work, what the batch of
episodes may and may not change, and actions too long for their dtype.
"""

import dataclasses
import math
from types import SimpleNamespace

import pytest
import torch
from torch import nn

from ebjepa_tutorial import planning
from ebjepa_tutorial.envs import Episodes, TwoRoomsEnv, clip_actions, render, transition
from ebjepa_tutorial.envs.two_rooms import MAX_STEP, wall_collision
from ebjepa_tutorial.planning import Noise, PlannerConfig

SEEDS = [10600, 10601, 10602]
TINY = PlannerConfig(horizon=8, samples=32, elites=4, iterations=2, execute=4)


class ShiftModel(nn.Module):
    """Latent = position, ``z_k = z0 + 0.8 * (a_1 + ... + a_k)``: only per-row arithmetic.

    No matrix product or convolution, so a row's result cannot depend on how
    many other rows share the batch.
    """

    def __init__(self):
        super().__init__()
        self.config = SimpleNamespace(action_dim=2)
        self.unused = nn.Parameter(torch.zeros(()))  # run_episodes finds the device here

    def rollout(self, z0, actions):
        """``(R, 2), (R, H, 2) -> (R, H, 2)``."""
        return z0[:, None] + (0.8 * actions).cumsum(dim=1)


def generators(seeds):
    return [torch.Generator().manual_seed(s) for s in seeds]


# -- 6: the goal's shape is checked against the start's ------------------------------------
@pytest.mark.parametrize("goal, words", [
    (torch.zeros(1, 2), r"z0 \(3, 2\), z_goal \(1, 2\).*expand\(3, -1\)"),
    (torch.zeros(3), r"z_goal \(3,\).*z_goal\[None\]"),
    (torch.zeros(3, 2, 65, 65), r"z_goal \(3, 2, 65, 65\).*encode them first"),
    (torch.zeros(2, 2), r"one goal per start; got z0 \(3, 2\), z_goal \(2, 2\)"),
])
def test_a_goal_that_is_not_one_latent_per_start_is_refused(goal, words):
    config = dataclasses.replace(TINY, iterations=1)
    with pytest.raises(ValueError, match=words):
        planning.plan(ShiftModel(), torch.zeros(3, 2), goal, config, generators(SEEDS))
    with pytest.raises(ValueError, match=words):
        planning.planning_cost(ShiftModel(), torch.zeros(3, 2), goal, torch.zeros(3, 4, 5, 2))


def test_a_single_start_is_told_to_add_the_batch_axis_to_both():
    with pytest.raises(ValueError, match=r"one start: z0\[None\] and z_goal\[None\]"):
        planning.planning_cost(ShiftModel(), torch.zeros(2), torch.zeros(2),
                               torch.zeros(1, 4, 5, 2))


@pytest.mark.parametrize("given", [generators([0]), generators([0, 1, 2, 3]),
                                   torch.Generator(), [0, 1, 2]])
def test_plan_needs_one_generator_per_start(given):
    """One generator for three starts would give all three the same samples."""
    config = dataclasses.replace(TINY, iterations=1)
    with pytest.raises(ValueError, match=r"one torch.Generator per start, 3 here"):
        planning.plan(ShiftModel(), torch.zeros(3, 2), torch.ones(3, 2), config, given)


def test_a_start_that_is_not_a_batch_of_latents_is_refused():
    with pytest.raises(ValueError, match=r"must be latents \(B, D\).*got z0 \(2,\)"):
        planning.plan(ShiftModel(), torch.zeros(2), torch.zeros(2, 2), TINY, generators([1, 2]))


# -- 7: planner settings that cannot work --------------------------------------------------
@pytest.mark.parametrize("kwargs, words", [
    (dict(temperature=math.nan), "temperature"),
    (dict(samples=True), r"samples \(plans per iteration.*\) must be an int >= 2"),
    (dict(horizon=8.0), "horizon must be an int >= 1"),
    (dict(iterations=0), "iterations"),
    (dict(elites=201), r"elites <= samples.*elites \(Q=201\), samples \(N=200\)"),
    # a dict of Noise's fields would pass here and fail mid-plan with an AttributeError
    (dict(noise={"period": 1}), r"noise must be a planning.Noise\(...\), got \{'period': 1\}"),
    (dict(habits=(0, 0.0)), r"habits must be a planning.Habits\(...\), got \(0, 0.0\)"),
])
def test_planner_settings_that_cannot_work_name_the_field_and_range(kwargs, words):
    with pytest.raises(ValueError, match=words):
        PlannerConfig(**kwargs)


@pytest.mark.parametrize("kwargs, words", [
    (dict(bound=0), r"Noise.bound \(the longest sampled step.*> 0, got 0"),
    (dict(bound=-1.8), "bound"),
    (dict(bound=math.inf), "bound"),
    (dict(std=-0.5), r"Noise.std .* > 0, got -0.5"),
    (dict(std=0.0), "std"),
    (dict(period=0), "period"),
])
def test_sampling_noise_that_cannot_work_names_the_field_and_range(kwargs, words):
    with pytest.raises(ValueError, match=words):
        Noise(**kwargs)


def test_every_shipped_preset_still_builds_its_planner():
    from ebjepa_tutorial.course import presets

    for notebook in presets.PRESETS:
        for size in presets.SCALES:
            chosen = presets.preset(notebook, size)
            planner = getattr(chosen, "planner", None)
            if planner is not None:  # notebook 06 also plans with CEM and the last-step cost
                for change in ({}, {"method": "cem"}, {"cost": "last"}):
                    assert isinstance(dataclasses.replace(planner, **change), PlannerConfig)


# -- 10: what the batch of episodes may change ---------------------------------------------
def test_episodes_do_not_couple_through_their_costs():
    # Episode 2's goal is 10,000 away, so its costs are ~1e5 times the others': any
    # reduction over the batch (a shared minimum, a shared scale) would show.
    z0 = torch.tensor([[0.0, 0.0], [5.0, -3.0], [1.0, 1.0]])
    goal = torch.tensor([[6.0, -4.0], [-2.0, 3.0], [1e4, -1e4]])
    together = planning.plan(ShiftModel(), z0, goal, TINY, generators(SEEDS))
    for i, seed in enumerate(SEEDS):
        alone = planning.plan(ShiftModel(), z0[i:i + 1], goal[i:i + 1], TINY, generators([seed]))
        for name in ("mean", "std", "costs"):
            assert torch.equal(getattr(together, name)[i], getattr(alone, name)[0]), name


def test_with_exact_dynamics_an_episode_is_the_same_alone_and_in_a_batch():
    model = ShiftModel()
    together = planning.run_episodes(model, SEEDS, TINY, steps=24, world="true_xy")
    for i, seed in enumerate(SEEDS):
        alone = planning.run_episodes(model, [seed], TINY, steps=24, world="true_xy")
        assert torch.equal(together.paths[i], alone.paths[0])


def test_with_a_network_an_episode_alone_differs_only_by_rounding():
    # Batched convolutions and matrix products may round differently for another
    # batch size; the first re-plan must still agree to that rounding.
    from ebjepa_tutorial.models.world import WORLD_CONFIGS, WorldModel

    with torch.random.fork_rng():
        torch.manual_seed(0)
        model = WorldModel(WORLD_CONFIGS["ci"]).eval()
        for weight in model.predictor.parameters():  # an untrained predictor imagines no motion
            nn.init.normal_(weight, std=0.2)
    episodes, gens = planning.episode_generators(SEEDS)
    starts = render(episodes.starts, episodes.layouts)
    goals = render(episodes.goals, episodes.layouts)
    model.fit_input_stats(torch.cat([starts, goals]))
    with torch.no_grad():
        z0, z_goal = model.encode(starts), model.encode(goals)
        together = planning.plan(model, z0, z_goal, TINY, gens)
        for i, seed in enumerate(SEEDS):
            z0_i, z_goal_i = model.encode(starts[i:i + 1]), model.encode(goals[i:i + 1])
            assert torch.allclose(z0_i, z0[i:i + 1], atol=1e-4)
            assert torch.allclose(z_goal_i, z_goal[i:i + 1], atol=1e-4)
            alone = planning.plan(model, z0_i, z_goal_i, TINY, planning.episode_generators(
                [seed])[1])
            assert torch.allclose(together.costs[i], alone.costs[0], rtol=1e-4)
            assert torch.allclose(together.mean[i], alone.mean[0], atol=1e-3)


# -- 12: actions too long for their dtype --------------------------------------------------
def one_world(start=(12.0, 30.0)):
    """A world whose dot is far from every wall: layout (40, 30)."""
    env = TwoRoomsEnv()
    env.reset(episodes=Episodes(torch.tensor([[40, 30]]), torch.tensor([start]),
                                torch.tensor([[50.0, 30.0]])))
    return env


@pytest.mark.parametrize("action", [(3e19, 4e19), (2e38, -3e38), (-1e30, 0.0)])
def test_a_huge_finite_action_moves_the_dot_by_the_longest_step(action):
    action = torch.tensor([action])  # float32: its squared length is infinite
    direction = action.double() / action.double().norm()
    expected = torch.tensor([[12.0, 30.0]]) + MAX_STEP * direction.float()
    env = one_world()
    env.step(action)
    assert torch.allclose(env.positions, expected, atol=1e-5)
    assert clip_actions(action).norm().item() == pytest.approx(MAX_STEP, rel=1e-6)


def test_a_float64_action_beyond_float32_is_refused_by_name():
    huge = torch.tensor([[1e39, 0.0]], dtype=torch.float64)  # finite, but inf in float32
    with pytest.raises(ValueError, match=r"finite also in torch.float32 .* 1e\+39"):
        one_world().step(huge)
    env = one_world()
    env.step(torch.tensor([[1e30, 0.0]], dtype=torch.float64))  # fits in float32: moves
    assert torch.allclose(env.positions, torch.tensor([[12.0 + MAX_STEP, 30.0]]))


def test_ordinary_actions_are_clipped_bitwise_as_before():
    g = torch.Generator().manual_seed(0)
    scales = torch.tensor([1e-30, 1e-3, 0.5, 1.0, 1.8, 3.0, 1e3, 1e15])
    actions = torch.randn(8, 500, 2, generator=g) * scales[:, None, None]
    actions[:, 0] = 0  # standing still
    before = actions * (MAX_STEP / actions.norm(dim=-1, keepdim=True).clamp_min(1e-12)).clamp(
        max=1.0)  # the formula clip_actions had
    assert torch.equal(clip_actions(actions), before)
    positions = 5 + 55 * torch.rand(8 * 500, 2, generator=g)
    layouts = torch.tensor([[40, 30]]).expand(8 * 500, 2)
    flat = actions.flatten(0, 1)
    assert torch.equal(transition(positions, flat, layouts),
                       wall_collision(positions, before.flatten(0, 1), layouts))
