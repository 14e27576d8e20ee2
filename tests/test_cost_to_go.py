"""The learned cost-to-go of notebook 07 (defined in its cells, run here through
research.beyond_fits.NOTEBOOK): its loss, its targets, its fit (research.beyond_fits), its use
in planning, and the loading of the shipped fits."""

import math
from types import SimpleNamespace

import pytest
import torch
from torch import nn

from ebjepa_tutorial.planning import planning_cost
from ebjepa_tutorial.training.checkpoints import (
    CheckpointError,
    UnsafeCheckpointError,
    save_checkpoint,
)
from ebjepa_tutorial.training.world import identity
from research.beyond_fits import (
    CAP,
    NOTEBOOK,
    TOLERANCE,
    CostConfig,
    CostData,
    Multiplier,
    cost_data,
    cost_objective,
    fit_cost_to_go,
    imagination_gap,
    sample_batch,
)

COST_SCALE, CostToGo, WithLearnedCost = (NOTEBOOK.COST_SCALE, NOTEBOOK.CostToGo,
                                         NOTEBOOK.WithLearnedCost)
CoarseModel, load_fit = NOTEBOOK.CoarseModel, NOTEBOOK.load_fit
spread_loss, step_violation = NOTEBOOK.spread_loss, NOTEBOOK.step_violation


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


def test_a_head_for_other_latents_is_refused():
    with pytest.raises(ValueError, match="latents of size 3"):
        WithLearnedCost(Drift(), CostToGo(3))


@pytest.mark.parametrize("field, value", [("consistency", -1.0), ("steps", 0), ("dims", 0),
                                          ("trajectory_steps", 40), ("layouts", 3)])
def test_cost_config_refuses_settings_that_cannot_fit(field, value):
    with pytest.raises(ValueError, match=field):
        CostConfig(**{field: value})


def test_the_shipped_fits_load_for_their_world_models():
    from research import fit_beyond
    from research.beyond_fits import CoarseConfig

    for world in fit_beyond.WORLDS:
        _, config, _ = fit_beyond.world_run(world)
        base, latent = identity(config), config.model.latent_dim
        head = load_fit("cost_head", world, CostToGo(latent), base)
        coarse = load_fit("coarse", world, CoarseModel(latent), base)
        assert not head.training and not coarse.training
        assert coarse.stride == CoarseConfig().stride  # the fit's stride is the model's default
        assert [m.out_features for m in head.embed if isinstance(m, nn.Linear)] == [
            CostConfig().hidden, CostConfig().hidden, CostConfig().dims]
        with pytest.raises(CheckpointError, match="not fitted on the world model loaded here"):
            load_fit("cost_head", world, CostToGo(latent), {**base, "seed": 1})


def test_a_missing_damaged_or_foreign_fit_is_refused_naming_the_file_and_command(tmp_path):
    command = "python -m research.fit_beyond --world two_rooms --fits cost_head"
    path = tmp_path / "cost_head_two_rooms_class.pt"
    with pytest.raises(FileNotFoundError, match=f"(?s){path.name}.*made by: {command}"):
        load_fit("cost_head", "two_rooms", CostToGo(2), {}, folder=tmp_path)
    path.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match=f"(?s){path.name} is damaged.*{command}"):
        load_fit("cost_head", "two_rooms", CostToGo(2), {}, folder=tmp_path)
    torch.save({"config": {"base": {}}, "model": nn.Linear(2, 2)}, path)  # a pickled module
    with pytest.raises(UnsafeCheckpointError, match=f"(?s){path.name}.*{command}"):
        load_fit("cost_head", "two_rooms", CostToGo(2), {}, folder=tmp_path)
    save_checkpoint(path, model=CostToGo(3).state_dict(), config={"base": {"seed": 0}})
    with pytest.raises(CheckpointError, match="not fitted on the world model"):
        load_fit("cost_head", "two_rooms", CostToGo(3), {"seed": 1}, folder=tmp_path)
    with pytest.raises(CheckpointError, match=f"holds no CostToGo of this shape.*{command}"):
        load_fit("cost_head", "two_rooms", CostToGo(2), {"seed": 0}, folder=tmp_path)
    loaded = load_fit("cost_head", "two_rooms", CostToGo(3), {"seed": 0}, folder=tmp_path)
    assert torch.equal(loaded.embed[0].weight, torch.load(path)["model"]["embed.0.weight"])


def test_calibration_sets_the_straight_distance_against_the_way_round_the_walls():
    from test_planning import LinearLatentModel

    cost_calibration, correlation = NOTEBOOK.cost_calibration, NOTEBOOK.correlation

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


@pytest.mark.slow  # tiny fits on the shipped Three Rooms world model: seconds
def test_the_fit_command_writes_files_that_the_notebook_then_loads(tmp_path, capsys):
    from ebjepa_tutorial.training.world import load_run
    from research import fit_beyond

    out = tmp_path / "fits"
    fit_beyond.main(["--world", "three_rooms", "--tiny", "--out-dir", str(out),
                     "--set", "consistency=0", "seed=3"])
    walls, config, name = fit_beyond.world_run("three_rooms")
    assert walls == 2 and name == "world_model_three_rooms_class"
    model = load_run(config, name, device="cpu")
    assert "Loaded a trained model" in capsys.readouterr().out  # the shipped world model
    head = load_fit("cost_head", "three_rooms", CostToGo(model.latent_dim, 32, 8),
                    identity(config), folder=out)
    load_fit("coarse", "three_rooms", CoarseModel(model.latent_dim, 4, 32), identity(config),
             folder=out)
    stored = torch.load(out / "cost_head_three_rooms_class.pt")["config"]
    assert stored["consistency"] == 0.0 and stored["seed"] == 3 and stored["walls"] == 2
    assert torch.load(out / "coarse_three_rooms_class.pt")["config"]["coarse"]["seed"] == 3
    assert head(torch.zeros(1, model.latent_dim), torch.zeros(1, model.latent_dim)) == 0


class _ExactModel(nn.Module):
    """Latent = (x, y, wall_x, door_y) read off a frame; rollout = the world's own transition."""

    def __init__(self):
        from test_three_rooms_planning import WallsReader

        super().__init__()
        self.reader, self.unused = WallsReader(), nn.Parameter(torch.zeros(()))

    def encode(self, frames):
        return self.reader.encode(frames.flatten(0, -4)).view(*frames.shape[:-3], -1)

    def rollout(self, z0, actions):
        z, out = z0, []
        for action in actions.unbind(1):
            z = self.reader.predict(z, action)
            out.append(z)
        return torch.stack(out, 1)


def test_cost_data_imagines_each_piece_from_its_own_first_frame():
    # with a model that imagines exactly, imagined step j of piece p is the latent of frame
    # p k + j + 1: a rollout started a frame late or early is off by a whole step
    data = cost_data(_ExactModel(), CostConfig(n_trajectories=8, trajectory_steps=32, layouts=2,
                                               seed=0))
    pieces, k = data.imagined.shape[1:3]
    true = torch.stack([data.latents[:, p * k + 1:p * k + k + 1] for p in range(pieces)], 1)
    assert pieces == 2 and (data.imagined - true).abs().max() < 2e-3
