"""The learned cost-to-go of notebook 07: its loss, its targets, its fit and its use in planning."""

import math
from dataclasses import replace
from types import SimpleNamespace

import pytest
import torch
from torch import nn

from ebjepa_tutorial.losses.cost import imagination_gap, spread_loss, step_violation
from ebjepa_tutorial.models.cost import COST_SCALE, CostToGo, WithLearnedCost
from ebjepa_tutorial.planning import PlannerConfig, planning_cost
from ebjepa_tutorial.training.cost import (
    CAP,
    TOLERANCE,
    CostConfig,
    CostData,
    Multiplier,
    cost_objective,
    fit_cost_to_go,
    sample_batch,
)


def test_spread_loss_by_hand():
    distance = torch.tensor([0.0, 1.0, 30.0])
    expected = (math.log(1 + math.e) + math.log(2) + math.log(1 + math.exp(-29))) / 3
    assert spread_loss(distance, 1.0) == pytest.approx(expected)
    distance.requires_grad_(True)
    spread_loss(distance, 1.0).backward()  # pushing apart lowers it; far pairs hardly move
    assert (distance.grad < 0).all() and distance.grad[2] > -1e-12


def test_step_violation_by_hand():
    # three steps; the second is stretched 2 units beyond its action, the others are within
    assert step_violation(torch.tensor([1.0, 3.0, 2.0]), torch.tensor([2.0, 1.0, 2.0])) == \
        pytest.approx(4 / 3)
    with pytest.raises(ValueError, match="same shape"):
        step_violation(torch.ones(3), torch.ones(2))


def test_imagination_gap_by_hand():
    imagined, true = torch.tensor([[3.0, 4.0], [1.0, 1.0]]), torch.tensor([[0.0, 0.0], [1.0, 1.0]])
    assert imagination_gap(imagined, true) == pytest.approx((25 + 0) / 2)


class Ruler(CostToGo):
    """A hand-set head on latents that are positions / COST_SCALE: the straight distance in px."""

    def __init__(self, latent_dim=1):
        super().__init__(latent_dim)
        self.embed = nn.Identity()


def test_the_objective_on_a_hand_made_trajectory():
    # a dot walks 0 -> 2 -> 3 -> 6 px on a line; its actions asked for 2, 2 and 2 px, so the
    # last step (3 px) is 1 px longer than its action, the second 1 px shorter
    x = torch.tensor([0.0, 2.0, 3.0, 6.0])[:, None] / COST_SCALE
    z, z_next, length = x[:-1], x[1:], torch.full((3,), 2.0)
    other = x.flip(0)[:3]  # pairs (0, 6), (2, 3), (3, 2) px
    config = CostConfig(consistency=0.0)
    head, multiplier = Ruler(), Multiplier()
    loss, terms = cost_objective(head, multiplier, (z, z_next, length, other, z, z), config)
    violation = (1 / COST_SCALE) ** 2 / 3  # only the last step: 1 px over, in head units
    assert terms["violation_px"] == pytest.approx(COST_SCALE * violation ** 0.5)
    spread = sum(math.log(1 + math.exp((CAP - d) / 10)) for d in (6.0, 1.0, 1.0)) / 3
    # lambda * violation - lambda * (violation - eps) leaves lambda * eps; lambda = 100 log 2
    eps = (TOLERANCE / COST_SCALE) ** 2
    assert loss.item() == pytest.approx(spread + 100 * math.log(2) * eps)
    loss.backward()  # violation (1/300) above eps (1/10,000): the multiplier must rise
    assert multiplier.raw.grad < 0
    # within tolerance (every step <= its action): the multiplier falls
    multiplier.raw.grad = None
    cost_objective(head, multiplier, (z, z_next, torch.full((3,), 3.0), other, z, z),
                   config)[0].backward()
    assert multiplier.raw.grad > 0


def test_the_objective_reads_imagined_latents_through_the_embedding():
    head, x = Ruler(2), torch.zeros(4, 2)
    imagined = torch.tensor([[0.3, 0.4]]).expand(4, 2)  # 0.5 from the true latents, each
    batch = (x, x, torch.ones(4), x + 1, imagined, x)
    without = cost_objective(head, Multiplier(), batch, CostConfig(consistency=0.0))[0]
    with_gap = cost_objective(head, Multiplier(), batch, CostConfig(consistency=10.0))[0]
    assert (with_gap - without).item() == pytest.approx(10 * 0.25)


def test_a_batch_pairs_frames_of_one_layout_and_imagined_latents_with_their_frames():
    n, frames, k = 6, 9, 4  # latent = (trajectory, frame); imagined from frames 0 and 4
    latents = torch.stack(torch.meshgrid(torch.arange(n), torch.arange(frames), indexing="ij"),
                          dim=-1).float()
    imagined = torch.stack([latents[:, p * k + 1: p * k + k + 1] for p in range(2)], dim=1)
    data = CostData(latents, torch.full((n, frames - 1), 2.0), imagined + 0.5, group=3)
    z, z_next, length, other, imag, true = sample_batch(data, 500, torch.Generator().manual_seed(0))
    assert (z_next == z + torch.tensor([0.0, 1.0])).all() and (length == 2).all()
    assert (other[:, 0] // 3 == z[:, 0] // 3).all()  # the same group of trajectories
    assert set(other[:, 1].tolist()) == set(range(frames)) and len(set(other[:, 0].tolist())) == n
    assert (imag == true + 0.5).all()  # each imagined latent beside the frame it stands for
    assert (true[:, 0] == z[:, 0]).all() and set(true[:, 1].tolist()) == set(range(1, frames))


@pytest.mark.slow  # 1,000 Adam steps: seconds
def test_on_a_line_the_head_learns_the_distance_not_the_random_walks():
    """Random walks on [0, 20] with steps up to 1.5 px either way: the shortest way is
    |x - g|, while the data's walks take far longer. The largest distance that no step
    exceeds is the former."""
    g = torch.Generator().manual_seed(0)
    n, steps = 400, 16
    moves = (torch.rand(n, steps, generator=g) * 2 - 1) * 1.5
    x = (torch.rand(n, 1, generator=g) * 20 + torch.cat([torch.zeros(n, 1), moves.cumsum(1)],
                                                        1)).clamp(0, 20)
    line = torch.stack([x / 10, torch.zeros_like(x)], dim=-1)  # (N, T+1, 2) latents
    imagined = line[:, 1:].reshape(n, 1, steps, 2)  # a perfect predictor
    data = CostData(line, (x[:, 1:] - x[:, :-1]).abs(), imagined, group=n)  # one world
    config = CostConfig(steps=1000, batch_size=256, hidden=64, dims=4, trajectory_steps=16)
    head, history = fit_cost_to_go(data, config)
    at = torch.tensor([[0.5, 0.0], [1.0, 0.0], [1.5, 0.0]])  # x = 5, 10, 15
    with torch.no_grad():
        near, far = head(at[1], at[0]), head(at[2], at[0])
        here = head(at[1], at[1])
    assert 4 < near < 6.5, near  # 5 px; a random walk needs ~25
    assert 8 < far < 13 and here == 0, (far, here)
    assert history["violation_px"][-1] < 0.3


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


@pytest.mark.parametrize("field, value", [("consistency", -1.0), ("steps", 0), ("dims", 0),
                                          ("trajectory_steps", 40), ("layouts", 3)])
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
    config = CostConfig(n_trajectories=4, trajectory_steps=16, layouts=2, steps=3,
                        batch_size=16, hidden=8, dims=4)
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
    from ebjepa_tutorial.course.presets import preset
    from ebjepa_tutorial.planning import two_level_episodes
    from ebjepa_tutorial.training.cost import cost_head_or_load
    from ebjepa_tutorial.training.hierarchy import coarse_or_load
    from ebjepa_tutorial.training.runs import train_or_load
    from ebjepa_tutorial.training.world import identity
    from research import fit_beyond

    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path))  # the world model trains here too
    fit_beyond.main(["--world", "three_rooms", "--scale", "ci",
                     "--out-dir", str(tmp_path / "checkpoints")])
    cfg, (walls, config, name) = preset("07", "ci"), fit_beyond.world_run("three_rooms", "ci")
    assert walls == 2 and config == cfg.three_rooms
    model, _ = train_or_load(config, name, device="cpu")
    capsys.readouterr()
    cost_head_or_load(model, identity(config), replace(cfg.cost, walls=2),
                      "cost_head_three_rooms_ci")
    coarse_or_load(model, identity(config), cfg.coarse_fit(2), "coarse_three_rooms_ci",
                   two_level_episodes)
    assert capsys.readouterr().out.count("Loaded a trained model") == 2  # nothing refitted
