"""The learned cost-to-go of notebook 07: its loss, its targets, its fit and its use in planning."""

from dataclasses import replace
from types import SimpleNamespace

import pytest
import torch
from torch import nn

from ebjepa_tutorial.losses.cost import cost_to_go_targets, expectile_loss
from ebjepa_tutorial.models.cost import CostToGo, WithLearnedCost
from ebjepa_tutorial.planning import PlannerConfig, planning_cost
from ebjepa_tutorial.training.cost import CostConfig, fit_cost_to_go, sample_goals


def test_expectile_loss_by_hand():
    estimate, target = torch.tensor([1.0, 2.0]), torch.tensor([2.0, 1.0])
    # errors +1 (target above: weight tau) and -1 (below: weight 1 - tau)
    assert expectile_loss(estimate, target, 0.1) == pytest.approx((0.1 + 0.9) / 2)
    assert expectile_loss(estimate, target + 1, 0.1) == pytest.approx((0.1 * 4 + 0.0) / 2)
    assert expectile_loss(estimate, target, 0.5) == pytest.approx(0.5 * 1.0)
    with pytest.raises(ValueError, match="tau must be in"):
        expectile_loss(estimate, target, 1.0)
    with pytest.raises(ValueError, match="same shape"):
        expectile_loss(estimate, target[:1], 0.1)


def test_targets_on_a_hand_made_trajectory():
    # steps of 1, 2 and 3 px along a line; the target head believes 10 px remain from s'
    step_cost, next_to_go = torch.tensor([1.0, 1.0, 1.0, 2.0]), torch.full((4,), 10.0)
    offset = torch.tensor([0, 1, 3, -1])  # s is the goal; s' is; 3 frames on; elsewhere
    spent = torch.tensor([0.0, 1.0, 6.0, 99.0])  # 1 + 2 + 3 px to the frame 3 on
    y = cost_to_go_targets(step_cost, next_to_go, offset, spent)
    assert y.tolist() == [0.0, 1.0, 6.0, 12.0]  # 0; min(11, 1); min(11, 6); 2 + 10
    tight = cost_to_go_targets(step_cost, torch.full((4,), 2.0), offset, spent)
    assert tight.tolist() == [0.0, 1.0, 3.0, 4.0]  # the bootstrap undercuts the data's path


def test_goals_come_from_the_same_trajectory_later_or_from_anywhere():
    n, frames = 6, 5  # latent = (trajectory, frame); every step 2 px long
    latents = torch.stack(torch.meshgrid(torch.arange(n), torch.arange(frames), indexing="ij"),
                          dim=-1).float()
    actions = torch.tensor([2.0, 0.0]).expand(n, frames - 1, 2)
    z, z_next, goal, step_cost, offset, spent = sample_goals(
        latents, actions, 500, 0.5, torch.Generator().manual_seed(0), group=3)
    assert (z_next == z + torch.tensor([0.0, 1.0])).all()  # the next frame
    assert (step_cost == 2).all()
    own = offset >= 0
    assert 0.3 < own.float().mean() < 0.7
    assert (goal[own, 0] == z[own, 0]).all() and (goal[own, 1] == z[own, 1] + offset[own]).all()
    assert (spent[own] == 2 * offset[own]).all()
    assert set(offset[own].tolist()) == set(range(frames))  # the goal itself up to the last frame
    # the others: any frame of a trajectory in the same group of 3 (which share a layout)
    assert (goal[~own, 0] // 3 == z[~own, 0] // 3).all()
    assert len(set(goal[~own, 0].tolist())) == n and set(goal[~own, 1].tolist()) == set(range(5))


@pytest.mark.slow  # 1,000 Adam steps: seconds
def test_on_a_line_the_head_learns_the_distance_not_the_random_walks():
    """Random walks on [0, 20] with steps up to 1.5 px either way: the shortest way is
    |x - g|, while the data's walks take far longer. The low expectile finds the former."""
    g = torch.Generator().manual_seed(0)
    n, steps = 400, 16
    moves = (torch.rand(n, steps, generator=g) * 2 - 1) * 1.5
    x = (torch.rand(n, 1, generator=g) * 20 + torch.cat([torch.zeros(n, 1), moves.cumsum(1)],
                                                        1)).clamp(0, 20)
    line = torch.stack([x / 10, torch.zeros_like(x)], dim=-1)  # (N, T+1, 2) latents
    actions = torch.stack([moves, torch.zeros_like(moves)], dim=-1)
    config = CostConfig(steps=1000, batch_size=256, hidden=64, lr=3e-3, target_momentum=0.95)
    head, history = fit_cost_to_go(line, actions, config, progress=False, group=n)  # one world
    at = torch.tensor([[0.5, 0.0], [1.0, 0.0], [1.5, 0.0]])  # x = 5, 10, 15
    with torch.no_grad():
        near, far = head(at[1], at[0]), head(at[2], at[0])
        back, here = head(at[0], at[1]), head(at[1], at[1])
    assert 4 < near < 6 and 4 < back < 6, (near, back)  # 5 px; a random walk needs ~25
    assert 8 < far < 12 and here < 1


class Drift(nn.Module):
    """Latent = position; the rollout adds the actions (a known linear model)."""

    def __init__(self):
        super().__init__()
        self.config = SimpleNamespace(action_dim=2)
        self.latent_dim = 2
        self.unused = nn.Parameter(torch.zeros(()))

    def encode(self, frames):
        return frames

    def rollout(self, z0, actions):
        return z0[:, None] + actions.cumsum(dim=1)


class Euclid(CostToGo):
    """A hand-set head: the straight distance, exactly."""

    def forward(self, z, goal):
        return (z - goal).norm(dim=-1)


def test_the_learned_cost_is_the_cost_to_go_from_the_last_imagined_step():
    model = WithLearnedCost(Drift(), Euclid(2))
    z0, goal = torch.zeros(1, 2), torch.tensor([[10.0, 0.0]])
    plans = torch.tensor([[[[1.0, 0.0]] * 3,  # 3 px towards the goal: 7 left
                           [[0.0, 1.0]] * 3,  # 3 px sideways: sqrt(100 + 9) left
                           [[0.0, 0.0]] * 3]])  # standing still: 10 left
    cost = planning_cost(model, z0, goal, plans, "learned")
    assert cost[0].tolist() == pytest.approx([7.0, 109 ** 0.5, 10.0])
    with pytest.raises(ValueError, match="WithLearnedCost"):
        planning_cost(Drift(), z0, goal, plans, "learned")
    assert PlannerConfig(cost="learned").cost == "learned"


def test_a_head_for_other_latents_is_refused():
    with pytest.raises(ValueError, match="latents of size 3"):
        WithLearnedCost(Drift(), CostToGo(3))


@pytest.mark.parametrize("field, value", [("tau", 0.0), ("target_momentum", 1.0),
                                          ("hindsight", 1.5), ("steps", 0),
                                          ("layouts", 30_000), ("layouts", 3)])
def test_cost_config_refuses_settings_that_cannot_fit(field, value):
    with pytest.raises(ValueError, match=field):
        CostConfig(**{field: value})


def test_a_fitted_head_is_saved_once_and_loaded_after(tmp_path, monkeypatch):
    from ebjepa_tutorial.training import cost, loop
    from ebjepa_tutorial.training.world import WorldTrainConfig, identity, make_data, new_model

    monkeypatch.setattr(loop, "checkpoint_paths",
                        lambda name: (tmp_path / f"{name}.pt", tmp_path / "none.pt"))
    world = WorldTrainConfig(n_trajectories=8, steps=1)
    model = new_model(world, make_data(world)).eval()
    config = CostConfig(n_trajectories=4, layouts=2, steps=3, batch_size=16, hidden=8)
    first = cost.cost_head_or_load(model, identity(world), config, "head")
    assert (tmp_path / "head.pt").exists()
    again = cost.cost_head_or_load(model, identity(world), config, "head")
    for a, b in zip(first.parameters(), again.parameters()):
        assert torch.equal(a, b)


def test_calibration_sets_the_straight_distance_against_the_way_round_the_walls():
    from test_planning import LinearLatentModel

    from ebjepa_tutorial.evaluation.cost import correlation, cost_calibration

    # the latent is the dot's centre and the head the straight distance: both read the
    # straight line, which the shortest way equals within a room and exceeds across walls
    anywhere = cost_calibration(LinearLatentModel(), Euclid(2), n=64, walls=2, seed=3)
    across = cost_calibration(LinearLatentModel(), Euclid(2), n=64, walls=2, seed=3,
                              rooms=(0, 2))
    assert torch.allclose(anywhere["head"], anywhere["latent"])
    for pairs in (anywhere, across):
        assert (pairs["shortest"] >= pairs["latent"] - 0.1).all()  # never under the line
    assert (across["shortest"] > across["latent"] + 0.5).float().mean() > 0.5  # detours
    assert correlation(anywhere["shortest"], anywhere["latent"]) > 0.8
    assert correlation(torch.arange(5.0), -torch.arange(5.0)) == pytest.approx(-1.0)


@pytest.mark.slow  # trains a ci world model, then fits both
def test_the_fit_command_writes_files_that_the_notebook_then_loads(tmp_path, monkeypatch, capsys):
    from ebjepa_tutorial.commands import fit_beyond
    from ebjepa_tutorial.course.presets import preset
    from ebjepa_tutorial.training.cost import cost_head_or_load
    from ebjepa_tutorial.training.hierarchy import coarse_or_load
    from ebjepa_tutorial.training.runs import train_or_load
    from ebjepa_tutorial.training.world import identity

    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path))  # the world model trains here too
    fit_beyond.main(["--world", "three_rooms", "--scale", "ci",
                     "--out-dir", str(tmp_path / "checkpoints")])
    cfg, (walls, config, name) = preset("07", "ci"), fit_beyond.world_run("three_rooms", "ci")
    assert walls == 2 and config == cfg.three_rooms
    model, _ = train_or_load(config, name, device="cpu")
    capsys.readouterr()
    cost_head_or_load(model, identity(config), replace(cfg.cost, walls=2),
                      "cost_head_three_rooms_ci")
    coarse_or_load(model, identity(config), replace(cfg.coarse, walls=2), "coarse_three_rooms_ci")
    assert capsys.readouterr().out.count("Loaded a trained model") == 2  # nothing refitted
