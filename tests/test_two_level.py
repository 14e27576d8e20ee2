"""The coarse model, its fit (research.beyond_fits) and the two-level planner of notebook 07
(defined in its cells, run here through research.beyond_fits.NOTEBOOK)."""

from dataclasses import replace
from types import SimpleNamespace

import pytest
import torch
from torch import nn

from ebjepa_tutorial.envs import MAX_STEP, clip_actions
from ebjepa_tutorial.planning import Habits, Noise, PlannerConfig, plan, shift_plan
from research.beyond_fits import (
    NOTEBOOK,
    CoarseConfig,
    CoarseFit,
    fit_coarse_on,
    macro_actions,
    windows,
)

TwoLevel = NOTEBOOK.TwoLevel


class Drift(nn.Module):
    """Latent = position; ``stride`` steps of the rollout move by the summed actions."""

    def __init__(self, stride: int = 1):
        super().__init__()
        self.config, self.stride = SimpleNamespace(action_dim=2), stride
        self.unused = nn.Parameter(torch.zeros(()))

    def rollout(self, z0, actions):
        return z0[:, None] + actions.cumsum(dim=1)


LOW = PlannerConfig(horizon=8, samples=64, elites=8, iterations=4, execute=4,
                    habits=Habits(warm_iterations=2, stop_px=0))
HIGH = PlannerConfig(horizon=8, samples=64, elites=8, iterations=4, execute=1,
                     noise=Noise(std=6.0, period=2, bound=4 * MAX_STEP),
                     habits=Habits(warm_iterations=2, stop_px=0))


def test_macro_actions_sum_each_stride():
    actions = torch.arange(12.0).view(1, 6, 2)
    assert macro_actions(actions, 3).tolist() == [[[6.0, 9.0], [24.0, 27.0]]]
    assert macro_actions(actions, 4).shape == (1, 1, 2)  # the last 2 steps make no macro


def test_windows_start_every_few_steps_and_keep_their_length():
    x = torch.arange(10.0).view(1, 10, 1) + torch.tensor([0.0, 100.0]).view(2, 1, 1)
    cut = windows(x, 4, 3)  # (2 sequences x 3 windows, 4, 1): starts 0, 3 and 6
    assert cut[..., 0].tolist() == [[0, 1, 2, 3], [3, 4, 5, 6], [6, 7, 8, 9],
                                    [100, 101, 102, 103], [103, 104, 105, 106],
                                    [106, 107, 108, 109]]
    with pytest.raises(ValueError, match="no window of 11"):
        windows(x, 11, 1)


def test_two_levels_reach_a_far_goal_under_a_known_linear_model():
    """Start at the origin, goal 30 px away: beyond the low level's 8 steps x 1.8 px."""
    two = TwoLevel(Drift(stride=4), HIGH, lookahead=2)
    z, goal = torch.zeros(1, 2), torch.tensor([[30.0, -12.0]])
    generators = [torch.Generator().manual_seed(0)]
    low_mean, high_mean = torch.zeros(1, 8, 2), torch.zeros(1, 8, 2)
    for _ in range(12):
        subgoal, high_mean = two.subgoals(z, goal, HIGH, generators, high_mean)
        assert (subgoal - z).norm() <= 2 * 4 * MAX_STEP + 1e-4  # two coarse steps at most
        low_mean = plan(Drift(), z, subgoal, LOW, generators, low_mean).mean
        z = z + clip_actions(low_mean[:, :4]).sum(dim=1)  # the world: free motion
        low_mean, high_mean = shift_plan(low_mean, 4), shift_plan(high_mean, 1)
    assert (z - goal).norm() < 3.0, z


def test_the_final_approach_aims_at_the_goal_once_the_coarse_plan_reaches_it():
    """Under Drift (latent = position) a plan that comes within ``reach`` of the goal by its
    second coarse step makes the goal the subgoal; one that does not keeps its latent."""
    z, g = torch.zeros(2, 2), torch.tensor([[3.0, 0.0], [30.0, 0.0]])
    generators = [torch.Generator().manual_seed(s) for s in range(2)]
    two = TwoLevel(Drift(stride=4), HIGH, lookahead=2, reach_px=4.5, reach=3.5)
    subgoal, plan_ = two.subgoals(z, g, HIGH, generators, torch.zeros(2, 8, 2))
    ahead = plan_[0, :2].cumsum(dim=0)  # the two imagined latents of the near episode
    assert (ahead - g[0]).norm(dim=-1).min() < 3.5 and torch.equal(subgoal[0], g[0])
    assert torch.allclose(subgoal[1], plan_[1, :2].sum(dim=0))  # Drift: the summed macros
    assert (subgoal[1] - g[1]).norm() > 10


def test_a_final_approach_must_be_calibrated_first():
    two = TwoLevel(Drift(stride=4), HIGH, lookahead=2, reach_px=4.5)
    with pytest.raises(ValueError, match="calibrate"):
        two.subgoals(torch.zeros(1, 2), torch.ones(1, 2), HIGH,
                     [torch.Generator().manual_seed(0)], torch.zeros(1, 8, 2))
    assert TwoLevel(Drift(4), HIGH).calibrate(None).reach is None  # no final approach: as is
    calibrated = replace(two, reach=2.0)
    assert calibrated.calibrate(None) is calibrated  # once


def test_a_coarse_model_learns_a_linear_world_from_trajectories():
    g = torch.Generator().manual_seed(0)
    actions = torch.randn(300, 16, 2, generator=g)
    # latent = position / 10, so a coarse step adds its macro-action / 10
    latents = torch.cat([torch.zeros(300, 1, 2), actions.cumsum(dim=1)], dim=1) / 10
    coarse, history = fit_coarse_on(latents, actions, CoarseConfig(steps=300, batch_size=64,
                                                                   hidden=32))
    assert history["loss"][-1] < 0.1 * history["loss"][0]
    with torch.no_grad():
        step = coarse.predict(torch.zeros(1, 2), torch.tensor([[4.0, -2.0]]))
    assert torch.allclose(step, torch.tensor([[0.4, -0.2]]), atol=0.1)


def test_settings_a_coarse_fit_cannot_use_are_refused():
    with pytest.raises(ValueError, match="stride"):
        CoarseConfig(stride=0)
    with pytest.raises(ValueError, match="episodes"):
        CoarseFit(CoarseConfig(), LOW, HIGH, lookahead=2, reach_px=4.5, episodes=0)


def test_a_coarse_rollout_chains_its_steps():
    torch.manual_seed(0)
    coarse = NOTEBOOK.CoarseModel(2, stride=4, hidden=8)
    torch.nn.init.normal_(coarse.out.weight)  # a step that moves (an untrained one stands still)
    z0, macro = torch.randn(3, 2), torch.randn(3, 3, 2)
    with torch.no_grad():
        chained = coarse.predict(coarse.predict(coarse.predict(z0, macro[:, 0]), macro[:, 1]),
                                 macro[:, 2])
        assert torch.allclose(coarse.rollout(z0, macro)[:, 2], chained)


def test_the_high_level_re_plans_from_its_last_plan_one_coarse_step_on():
    from dataclasses import dataclass

    seen = []  # (warm start, iterations, the plan made) per call of subgoals

    @dataclass(frozen=True)
    class Recording(TwoLevel):
        def subgoals(self, z0, z_goal, config, generators, mean):
            out = super().subgoals(z0, z_goal, config, generators, mean)
            seen.append((mean.clone(), config.iterations, out[1].clone()))
            return out

    aim = Recording(Drift(stride=4), HIGH, lookahead=2).aim(
        [torch.Generator().manual_seed(s) for s in range(2)])
    z, goal = torch.zeros(2, 2), torch.tensor([[30.0, -12.0], [5.0, 5.0]])
    first = aim(z, goal, torch.tensor([True, True]))
    second = aim(z, goal, torch.tensor([True, False]))  # episode 1 has arrived
    assert torch.equal(seen[1][0], shift_plan(seen[0][2], 1)[:1])  # only the moving row re-plans
    assert [s[1] for s in seen] == [HIGH.iterations, HIGH.warm().iterations]
    assert torch.equal(second[1], goal[1])  # an arrived episode aims at the goal itself
    # the subgoal: where the first `lookahead` macro-actions lead under the coarse model
    assert torch.allclose(first[0], seen[0][2][0, :2].sum(0))
