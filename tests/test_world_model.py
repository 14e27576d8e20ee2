"""World model (notebooks 04-05): shapes, loss terms by hand, the position probe, bad input."""

import io
import math
from dataclasses import dataclass, replace

import pytest
import torch

from ebjepa_tutorial.envs import generate_trajectories, transition
from ebjepa_tutorial.envs.trajectories import Trajectories
from ebjepa_tutorial.evaluation.position import (
    fit_position_probe,
    mean_baseline_px,
    middle_wall_test,
    probe_error_px,
    wall_test_by_door_distance,
)
from ebjepa_tutorial.losses import world as wl
from ebjepa_tutorial.models.world import WORLD_CONFIGS, WorldConfig, WorldModel, encode_trajectories
from ebjepa_tutorial.training import world
from ebjepa_tutorial.training.checkpoints import CheckpointError
from ebjepa_tutorial.training.loop import History
from research.train_world import notebook, train_world_model

TINY = WorldConfig(widths=(4, 8), blocks=1, input_size=17, latent_dim=8,
                   action_embed_dim=8, idm_hidden=16)


@pytest.fixture(scope="module")
def data():
    trajectories = generate_trajectories(6, steps=4, seed=0)
    return trajectories, trajectories.frames()


def tiny_model(frames=None, seed=0):
    torch.manual_seed(seed)
    model = WorldModel(TINY)
    return model if frames is None else model.fit_input_stats(frames)


# -- the model ---------------------------------------------------------------------------
def test_shapes_of_encode_predict_rollout(data):
    trajectories, frames = data  # frames (6, 5, 2, 65, 65)
    model = tiny_model(frames)
    z = model.encode(frames)
    assert z.shape == (6, 5, 8)
    assert model.encode(frames[:, 0]).shape == (6, 8)
    assert torch.allclose(model.encode(frames[:, 0]), z[:, 0], atol=1e-5)
    assert model.predict(z[:, 0], trajectories.actions[:, 0]).shape == (6, 8)
    assert model.rollout(z[:, 0], trajectories.actions).shape == (6, 4, 8)
    assert model.predict_actions(z[:, :-1], z[:, 1:]).shape == (6, 4, 2)


def test_rollout_is_repeated_predict(data):
    trajectories, frames = data
    model = tiny_model(frames)
    with torch.no_grad():  # make the predictor move: its output layer starts at zero
        model.predictor.out.weight.normal_(0, 0.3, generator=torch.Generator().manual_seed(1))
    z, actions = model.encode(frames[:, 0]), trajectories.actions
    rolled = model.rollout(z, actions)
    for k in range(actions.shape[1]):
        z = model.predict(z, actions[:, k])
        assert torch.allclose(rolled[:, k], z, atol=1e-6)


def test_untrained_predictor_is_the_identity(data):
    trajectories, frames = data
    model = tiny_model(frames)
    z = model.encode(frames[:, 0])
    assert torch.equal(model.predict(z, trajectories.actions[:, 0]), z)


def test_input_stats_standardise_each_channel(data):
    _, frames = data
    model = WorldModel(replace(TINY, input_size=65)).fit_input_stats(frames)
    x = model.normalize(frames.flatten(0, 1))
    assert bool(model.input_stats_fitted)
    assert torch.allclose(x.mean(dim=(0, 2, 3)), torch.zeros(2), atol=1e-4)
    assert torch.allclose(x.std(dim=(0, 2, 3)), torch.ones(2), atol=1e-3)
    # the dot covers far fewer pixels than the walls, so its std is much smaller
    assert model.input_std[0] < model.input_std[1] / 3


def test_checkpoint_carries_config_and_input_stats(data):
    _, frames = data
    model = tiny_model(frames)
    state = model.state_dict()
    loaded = WorldModel.from_state_dict(state)
    assert loaded.config == model.config
    assert torch.equal(loaded.input_std, model.input_std)
    assert torch.equal(loaded.encode(frames), model.encode(frames))
    other = WorldModel(WorldConfig(widths=(4, 8), blocks=1, input_size=17, latent_dim=4,
                                   action_embed_dim=8, idm_hidden=16))
    with pytest.raises(ValueError, match="latent_dim: the checkpoint has 8, this model has 4"):
        other.load_state_dict(state)


def test_presets_build():
    for name, config in WORLD_CONFIGS.items():
        assert WorldModel(config).latent_dim == config.latent_dim, name


# -- the loss terms by hand --------------------------------------------------------------
def test_temporal_similarity_by_hand():
    z = torch.tensor([[[0.0, 0.0], [1.0, 2.0], [1.0, 0.0]]])  # (1, 3, 2)
    # differences (1, 2) and (0, -2): squares 1 + 4 + 0 + 4 = 9 over 4 elements
    assert wl.temporal_similarity_loss(z).item() == pytest.approx(9 / 4)


def test_inverse_dynamics_with_a_hand_set_linear_head():
    z = torch.tensor([[[0.0, 0.0], [1.0, 2.0], [1.0, 0.0]]])
    actions = torch.tensor([[[1.0, 2.0], [0.0, 0.0]]])
    head = lambda z_t, z_next: z_next - z_t  # noqa: E731  exact for the first step
    # predicted (1, 2) and (0, -2): errors 0, 0, 0, -2 -> 4 / 4 elements
    assert wl.inverse_dynamics_loss(head, z, actions).item() == pytest.approx(1.0)


def test_multistep_prediction_with_z_plus_a():
    actions = torch.tensor([[[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]])  # (1, 3, 2)
    exact = torch.cat([torch.zeros(1, 1, 2), actions.cumsum(dim=1)], dim=1)  # (1, 4, 2)
    add = lambda z, a: z + a  # noqa: E731
    assert wl.multistep_prediction_loss(add, exact, actions, steps=3).item() == 0.0
    shifted = exact.clone()
    shifted[:, 2] += torch.tensor([2.0, 0.0])  # target 2 off by (2, 0)
    # k=1: 0; k=2: (4 + 0)/2 = 2; k=3: 0 (the rollout ignores targets) -> mean 2/3
    assert wl.multistep_prediction_loss(add, shifted, actions, steps=3).item() == pytest.approx(
        2 / 3
    )
    # K=1 only looks at the first step
    assert wl.multistep_prediction_loss(add, shifted, actions, steps=1).item() == 0.0


def test_prediction_rolls_out_from_the_first_frame_only():
    # scalar latents along one trajectory, a predictor that adds the action, K = 2
    z = torch.tensor([[[0.0], [1.0], [3.0], [3.0]]])  # (1, 4, 1)
    actions = torch.ones(1, 3, 1)
    add = lambda z, a: z + a  # noqa: E731
    # from frame 0: zhat 1, 2 against 1, 3 -> errors 0, 1 -> mean 1/2
    assert wl.multistep_prediction_loss(add, z, actions, steps=2).item() == pytest.approx(0.5)
    z[0, 3] = 5.0  # frame 3 is K + 1 frames away: never a target
    assert wl.multistep_prediction_loss(add, z, actions, steps=2).item() == pytest.approx(0.5)


def test_still_steps_repeat_the_target_under_a_zero_action():
    z = torch.tensor([[[0.0], [1.0], [3.0]]])  # (1, K + 1 = 3, 1)
    actions = torch.tensor([[[1.0], [2.0]]])  # (1, K = 2, 1)
    sequence, taken = wl.with_still_steps(z, actions, torch.tensor([[True, False]]))
    assert sequence.flatten().tolist() == [0.0, 0.0, 1.0]  # stand still, then the first move
    assert taken.flatten().tolist() == [0.0, 1.0]
    sequence, taken = wl.with_still_steps(z, actions, torch.tensor([[False, True]]))
    assert sequence.flatten().tolist() == [0.0, 1.0, 1.0] and taken.flatten().tolist() == [1, 0]


def test_a_predictor_that_adds_the_action_is_exact_with_still_steps_too():
    actions = torch.randn(5, 8, 2)
    exact = torch.cat([torch.zeros(5, 1, 2), actions.cumsum(dim=1)], dim=1)  # (5, 9, 2)
    add = lambda z, a: z + a  # noqa: E731
    loss = wl.multistep_prediction_loss(add, exact, actions, 4, stay_probability=0.5,
                                        generator=torch.Generator().manual_seed(0))
    assert loss.item() == pytest.approx(0.0, abs=1e-10)
    drift = lambda z, a: z + a + 0.1  # noqa: E731  (moves even under a zero action)
    still = wl.multistep_prediction_loss(drift, exact, actions, 4, stay_probability=0.5,
                                         generator=torch.Generator().manual_seed(0))
    assert still.item() > 0


def test_detached_targets_stop_the_gradient():
    z = torch.zeros(1, 3, 2, requires_grad=True)
    actions = torch.ones(1, 2, 2)
    add = lambda z, a: z + a  # noqa: E731
    wl.multistep_prediction_loss(add, z, actions, steps=2, detach_targets=True).backward()
    # only zhat's path remains: d/dz0 of mean((z0+1)^2)/2 + mean((z0+2)^2)/2 at 0 is (1+2)/2
    assert torch.allclose(z.grad[0, 0], torch.full((2,), 1.5))
    assert torch.equal(z.grad[0, 1:], torch.zeros(2, 2))


def test_variance_covariance_flatten_time():
    z = torch.tensor([[[1.0, 0.0], [-1.0, 0.0]], [[1.0, 0.0], [-1.0, 0.0]]])  # (2, 2, 2)
    var, cov = wl.variance_covariance_loss(z)
    # dim 0: values 1, -1, 1, -1 -> var 4/3, std 1.155 > 1; dim 1: constant -> 1 - 0.01
    assert var.item() == pytest.approx((1 - math.sqrt(1e-4)) / 2, abs=1e-6)
    assert cov.item() == 0.0


def first_step(model, frames, actions, coeffs=None, steps=3, seed=0):
    """The training step's ``(total, terms)`` on these inputs, at a rate of 0: the weights
    stay, and the gradients of the total stay in ``.grad``."""
    config = world.WorldTrainConfig(model=model.config, coeffs=coeffs or wl.WorldLossCoeffs(),
                                    rollout_steps=steps)
    optimizer = torch.optim.SGD(model.parameters(), lr=0.0)
    return world.world_model_step(model, optimizer, frames, actions,
                                  torch.Generator().manual_seed(seed), config, step=0)


def test_the_loss_weights_are_the_papers():
    # alpha, beta, delta, omega of the paper's Eq. 11-12 (SIGReg off): every world run uses them
    weights = wl.WorldLossCoeffs()
    assert (weights.prediction, weights.variance, weights.covariance, weights.temporal,
            weights.inverse_dynamics, weights.sigreg) == (1.0, 16.0, 8.0, 12.0, 1.0, 0.0)


def test_the_training_step_weighs_the_five_terms(data):
    trajectories, frames = data
    model = tiny_model(frames)
    with torch.no_grad():  # make the predictor move: its output layer starts at zero
        model.predictor.out.weight.normal_(0, 0.3, generator=torch.Generator().manual_seed(1))
    coeffs = wl.WorldLossCoeffs()
    total, terms = first_step(model, frames, trajectories.actions, coeffs, steps=3)
    assert set(terms) == {"prediction", "variance", "covariance", "temporal", "inverse_dynamics"}
    # each term is its function's value on the encoded latents (the step changed no weight)
    z, actions = model.encode(frames), trajectories.actions
    variance, covariance = wl.variance_covariance_loss(z)
    alone = {"prediction": wl.multistep_prediction_loss(model.predict, z, actions, 3),
             "variance": variance, "covariance": covariance,
             "temporal": wl.temporal_similarity_loss(z),
             "inverse_dynamics": wl.inverse_dynamics_loss(model.predict_actions, z, actions)}
    for name, value in alone.items():
        assert float(terms[name]) == pytest.approx(value.item(), rel=1e-5), name
    expected = sum(getattr(coeffs, name) * float(value) for name, value in terms.items())
    assert total.item() == pytest.approx(expected, rel=1e-5)
    assert model.encoder.linear.weight.grad.abs().sum() > 0
    assert model.inverse_dynamics[0].weight.grad.abs().sum() > 0
    assert model.predictor.out.weight.grad.abs().sum() > 0


def test_sigreg_joins_the_world_model_loss_when_weighted(data):
    from ebjepa_tutorial.losses.sigreg import random_directions, sigreg

    trajectories, frames = data
    model = tiny_model(frames)
    coeffs = wl.WorldLossCoeffs(variance=0.0, covariance=0.0, sigreg=0.05)
    total, terms = first_step(model, frames, trajectories.actions, coeffs, steps=3, seed=7)
    # the statistic of every frame's latent, with the directions the generator draws (no still
    # steps draw before it: the paper's recipe has none)
    z = model.encode(frames).reshape(-1, model.latent_dim)
    directions = random_directions(model.latent_dim, 256, torch.Generator().manual_seed(7))
    assert float(terms["sigreg"]) == pytest.approx(sigreg(z, directions=directions).item(),
                                                 rel=1e-5)
    expected = sum(getattr(coeffs, name) * float(value) for name, value in terms.items())
    assert total.item() == pytest.approx(expected, rel=1e-5)
    assert model.encoder.linear.weight.grad.abs().sum() > 0
    off = first_step(model, frames, trajectories.actions, wl.WorldLossCoeffs(), 3)[1]
    assert "sigreg" not in off  # off by default: the paper's recipe costs nothing more


def _two_runs(config, **changes):
    """The trained weights and history of ``config`` and of ``config`` with ``changes``."""
    runs = [train_world_model(c, progress=False, device="cpu")
            for c in (config, replace(config, **changes))]
    return [(model.state_dict(), history) for model, history in runs]


def _differ(a: dict, b: dict, prefix: str) -> bool:
    """Whether any weight whose name starts with ``prefix`` differs between the state dicts."""
    return any(not torch.equal(a[k], b[k]) for k in a if k.startswith(prefix))


def test_a_sigreg_coefficient_reaches_the_run_and_changes_what_trains():
    config = world.WorldTrainConfig(model=TINY, n_trajectories=16, batch_size=4, steps=2)
    (plain, plain_history), (with_sigreg, history) = _two_runs(
        config, coeffs=wl.WorldLossCoeffs(sigreg=0.05))
    assert len(history["sigreg"]) == 2 and all(math.isfinite(v) for v in history["sigreg"])
    assert "sigreg" not in plain_history  # off by default: computed only when it weighs
    assert _differ(plain, with_sigreg, "encoder.")


def test_training_windows_are_consecutive_frames_of_one_trajectory_at_any_offset():
    config = world.WorldTrainConfig(model=TINY, n_trajectories=8, batch_size=64, steps=3,
                                    recipe=world.Recipe(window=9))
    data, seen = world.make_data(config), []

    def record(model, optimizer, frames, actions, *rest):  # the batches notebook 05's loop makes
        seen.append((frames.clone(), actions))  # a copy: the loop renders into one buffer
        optimizer.step()  # no gradients: nothing moves
        return torch.zeros(()), {}

    train_world_model(config, progress=False, device="cpu", step=record)
    whole, offsets = data.frames(), set()  # (8, 17, 2, 65, 65)
    for frames, actions in zip(*(torch.cat(parts) for parts in zip(*seen))):  # 192 windows
        assert frames.shape == (9, 2, 65, 65) and actions.shape == (8, 2)
        found = [(i, o) for i in range(8) for o in range(9)
                 if torch.equal(data.actions[i, o:o + 8], actions)]
        assert len(found) == 1  # the actions of one trajectory, consecutive...
        (i, o), = found
        assert torch.equal(whole[i, o:o + 9], frames)  # ...and the frames between them
        offsets.add(o)
    assert offsets == set(range(9))  # every offset, both ends included
    with pytest.raises(ValueError, match="window=18 does not fit trajectories of 17 frames"):
        world.Recipe(window=18)
    # K = 8 needs 9 frames: a shorter window is refused when the run is configured
    with pytest.raises(ValueError, match=r"rollout_steps \(K\) must be 1..7 for windows of 8"):
        world.WorldTrainConfig(recipe=world.Recipe(window=8))
    with pytest.raises(ValueError, match="1..16 for windows of 17 frames"):
        world.WorldTrainConfig(rollout_steps=17)


def test_channels_last_is_a_memory_layout_only_the_run_is_the_same():
    recipe = world.Recipe(window=9, wall_fraction=0.25)
    config = world.WorldTrainConfig(model=TINY, n_trajectories=16, batch_size=4, steps=2,
                                    recipe=recipe)
    (plain, plain_history), (last, history) = _two_runs(
        config, recipe=replace(recipe, channels_last=True))
    assert history["loss"] == pytest.approx(plain_history["loss"], rel=1e-4)
    assert all(torch.allclose(plain[k], last[k], atol=1e-5) for k in plain
               if isinstance(plain[k], torch.Tensor))


def test_a_three_rooms_run_trains_on_three_rooms_data_and_is_another_run():
    from ebjepa_tutorial.envs import room_of
    from ebjepa_tutorial.training.world import WorldTrainConfig, identity, make_data

    config = WorldTrainConfig(model=tiny_model().config, n_trajectories=16, batch_size=4,
                              steps=2, recipe=world.Recipe(window=9, wall_fraction=0.25),
                              walls=2)
    data = make_data(config)
    assert data.layouts.shape == (16, 4)  # two walls: (wall_x, door_y) each
    assert (room_of(data.positions[:, 0], data.layouts) == 1).any()  # some start in the middle
    _, history = train_world_model(config, progress=False, device="cpu")
    assert len(history["loss"]) == 2 and all(math.isfinite(v) for v in history["loss"])
    assert identity(WorldTrainConfig()) != identity(WorldTrainConfig(walls=2))
    assert identity(WorldTrainConfig(walls=2))["wall_x_ranges"]  # the geometry is recorded


@pytest.fixture
def small_replay(monkeypatch):
    """A replay buffer of 8 windows drawing 8 per update (the module's sizes, made small)."""
    monkeypatch.setattr(world, "REPLAY_BATCH", 8)
    monkeypatch.setattr(world, "REPLAY_CAPACITY", 8)


def _replay(replay_steps=3, lr=1e-3, monkeypatch=None, decay_steps=0, **options):
    if monkeypatch is not None:
        monkeypatch.setattr(world, "REPLAY_LR", lr)
    recipe = world.Recipe(replay_steps=replay_steps, decay_steps=decay_steps)
    config = world.WorldTrainConfig(model=TINY, batch_size=4, rollout_steps=2, recipe=recipe,
                                    **options)
    return world.LatentReplay(tiny_model(), config, frames=3, device="cpu")


def test_replay_refuses_a_process_count_that_cannot_share_its_draw(monkeypatch):
    # 1024 windows per update: 3 processes pass the launch check of a batch of 384 (the paper's)
    # but could not split the replay's draw; the run says so before it trains
    monkeypatch.setattr(world.distributed, "world_size", lambda: 3)
    with pytest.raises(ValueError, match="1024 windows per update cannot be shared by 3"):
        _replay()


def test_the_replay_buffer_keeps_the_last_windows(small_replay):
    replay = _replay()
    for value in (1.0, 2.0, 3.0):  # three batches of 4 windows into room for 8
        replay.add(torch.full((4, 3, 8), value), torch.full((4, 2, 2), value))
    assert replay.filled == 8 and replay.head == 4
    assert sorted(replay.latents[:, 0, 0].tolist()) == [2.0] * 4 + [3.0] * 4
    assert torch.equal(replay.latents[:, 0, 0], replay.actions[:, 0, 0])  # stored as pairs


def test_replay_fits_the_predictor_on_stored_latents_and_leaves_the_encoder_alone(
        small_replay, monkeypatch):
    torch.manual_seed(0)
    replay, mixing = _replay(replay_steps=5, lr=1e-2, monkeypatch=monkeypatch), torch.randn(2, 8)
    actions = torch.randn(8, 2, 2)
    z = torch.cat([torch.randn(8, 1, 8), torch.zeros(8, 2, 8)], dim=1)
    for t in range(2):  # a world whose next latent is z + a M, learnable by the predictor
        z[:, t + 1] = z[:, t] + actions[:, t] @ mixing
    replay.add(z, actions)
    encoder = [p.clone() for p in replay.model.encoder.parameters()]

    def error():
        return wl.multistep_prediction_loss(replay.model.predict, z, actions, 2).item()

    before = error()
    for step in range(40):
        replay(step)
    assert error() < before / 4
    assert all(torch.equal(a, b) for a, b in zip(encoder, replay.model.encoder.parameters()))


def test_a_replay_restored_from_its_state_continues_exactly(small_replay):
    first, second = _replay(), _replay()
    first.add(torch.randn(4, 3, 8), torch.randn(4, 2, 2))
    first(0)
    saved = io.BytesIO()  # as a checkpoint file, read back safely (tensors and numbers only)
    torch.save({"model": first.model.state_dict(), "replay": first.state_dict()}, saved)
    state = torch.load(io.BytesIO(saved.getvalue()), weights_only=True)
    second.model.load_state_dict(state["model"])
    second.load_state_dict(state["replay"])
    first(1), second(1)
    assert all(torch.equal(a, b) for a, b in zip(first.model.predictor.parameters(),
                                                  second.model.predictor.parameters()))


def test_a_replay_run_updates_the_predictor_after_each_step(small_replay):
    recipe = world.Recipe(window=9, stay_probability=0.2)
    config = world.WorldTrainConfig(model=replace(TINY, predictor="mlp"), n_trajectories=16,
                                    batch_size=4, steps=1, recipe=recipe)
    (plain, plain_history), (replayed, history) = _two_runs(
        config, recipe=replace(recipe, replay_steps=2))
    assert history["loss"] == plain_history["loss"]  # the replay comes after the step...
    assert _differ(plain, replayed, "predictor.")  # ...and moves the predictor
    assert not _differ(plain, replayed, "encoder.")  # on stored latents: the encoder stays


# -- the probe ---------------------------------------------------------------------------
def test_probe_on_an_invertible_map_of_positions_is_nearly_exact():
    g = torch.Generator().manual_seed(0)
    positions = 1.5 + 61 * torch.rand(600, 2, generator=g)
    mixing = torch.randn(2, 6, generator=g)
    latents = positions @ mixing + 3.0
    probe = fit_position_probe(latents[:400], positions[:400])
    assert probe_error_px(probe, latents[400:], positions[400:]) < 2e-2  # the ridge's shrinkage


def test_probe_on_random_latents_is_no_better_than_the_mean():
    g = torch.Generator().manual_seed(0)
    positions = 1.5 + 61 * torch.rand(1000, 2, generator=g)
    latents = torch.randn(1000, 16, generator=g)
    baseline = mean_baseline_px(positions[:800], positions[800:])
    probe = fit_position_probe(latents[:800], positions[:800])
    error = probe_error_px(probe, latents[800:], positions[800:])
    assert 0.9 * baseline < error < 1.3 * baseline


def test_encode_trajectories_pairs_latents_with_positions(data):
    trajectories, frames = data
    model = tiny_model(frames)
    latents, positions = encode_trajectories(model, trajectories, batch_size=4)
    assert latents.shape == (30, 8) and positions.shape == (30, 2)
    assert torch.allclose(latents[5:10], model.encode(frames[1]), atol=1e-5)
    assert torch.equal(positions[5:10], trajectories.positions[1])


class StateReader(torch.nn.Module):
    """A stand-in world model whose latent is the state read off the frame: (x, y, wall_x, door_y).

    Its predictor moves the dot by the true rule of motion, or, with ``knows_walls=False``,
    by ``speed`` times the action alone, as if there were no walls.
    """

    def __init__(self, knows_walls: bool, speed: float = 1.0):
        super().__init__()
        self.knows_walls, self.speed = knows_walls, speed
        self.unused = torch.nn.Parameter(torch.zeros(()))  # for the device lookup

    def encode(self, frames):
        dot, walls, grid = frames[:, 0], frames[:, 1, 1:-1, 1:-1], torch.arange(65.0)
        # The dot's centroid, to 0.001 px: float error would put a dot resting on the wall's
        # face a hair inside it, where the rule of motion lets it through.
        x = ((dot.sum(1) * grid).sum(1) / dot.sum((1, 2)) * 1000).round() / 1000
        y = ((dot.sum(2) * grid).sum(1) / dot.sum((1, 2)) * 1000).round() / 1000
        per_column = walls.sum(1)  # (B, 63): the middle wall's 3 columns are the fullest
        middle = (per_column == per_column.amax(1, keepdim=True)).float()
        wall_x = 1 + (middle * grid[:63]).sum(1) / middle.sum(1)
        column = walls[torch.arange(len(walls)), :, wall_x.long() - 1]  # (B, 63)
        door_y = 1 + ((1 - column) * grid[:63]).sum(1) / (1 - column).sum(1)
        return torch.stack([x, y, wall_x, door_y], dim=1)

    def predict(self, z, actions):
        xy, layouts = z[:, :2], z[:, 2:].round().long()
        moved = transition(xy, actions, layouts) if self.knows_walls else xy + self.speed * actions
        return torch.cat([moved, z[:, 2:]], dim=1)


def test_middle_wall_test_tells_walled_wall_blind_and_frozen_predictors_apart():
    trajectories = generate_trajectories(80, seed=3)
    walled = middle_wall_test(StateReader(knows_walls=True), trajectories)
    blind = middle_wall_test(StateReader(knows_walls=False), trajectories)
    frozen = middle_wall_test(StateReader(knows_walls=False, speed=0.0), trajectories)
    assert walled["n_stopped"] == blind["n_stopped"] >= 10 and walled["n_moved"] >= 100
    assert (walled["stopped"], walled["moved"]) == (1.0, 1.0)
    assert (blind["stopped"], blind["moved"]) == (0.0, 1.0)
    assert (frozen["stopped"], frozen["moved"]) == (1.0, 0.0)  # why "moved" is there


class BlindNearTheDoor(StateReader):
    """Knows the middle wall, except within ``reach`` px (along it) of the door's centre."""

    def __init__(self, reach: float):
        super().__init__(knows_walls=True)
        self.reach, self.blind = reach, StateReader(knows_walls=False)

    def predict(self, z, actions):
        near = ((z[:, 1] - z[:, 3]).abs() < self.reach)[:, None]  # latent: (x, y, wall_x, door_y)
        return torch.where(near, self.blind.predict(z, actions), super().predict(z, actions))


def test_wall_test_by_door_distance_finds_where_along_the_wall_the_predictor_is_blind():
    trajectories = generate_trajectories(400, seed=3)
    edges = (0, 8, 12, 16, 65)
    bins = wall_test_by_door_distance(BlindNearTheDoor(reach=12), trajectories, edges)
    assert [(b["lo"], b["hi"]) for b in bins] == list(zip(edges[:-1], edges[1:]))
    assert all(b["n"] >= 10 for b in bins)
    assert sum(b["n"] for b in bins) == middle_wall_test(StateReader(True),
                                                         trajectories)["n_stopped"]
    assert [b["stopped"] for b in bins] == [0.0, 0.0, 1.0, 1.0]
    walled = wall_test_by_door_distance(StateReader(True), trajectories, edges)
    assert [b["stopped"] for b in walled] == [1.0] * 4


def test_middle_wall_test_needs_a_stopped_step():
    standing = generate_trajectories(3, steps=2, seed=0)
    still = Trajectories(standing.positions[:, :1].expand(-1, 3, -1).clone(),
                         torch.zeros(3, 2, 2), standing.layouts, standing.door)
    with pytest.raises(ValueError, match="stopped no step"):
        middle_wall_test(StateReader(knows_walls=True), still)


# -- bad input ---------------------------------------------------------------------------
def test_bad_inputs_give_clear_errors(data):
    trajectories, frames = data
    model = tiny_model(frames)
    z = model.encode(frames[:, 0])
    with pytest.raises(ValueError, match=r"actions must have shape \(6, 2\)"):
        model.predict(z, trajectories.actions)
    with pytest.raises(ValueError, match=r"actions must have shape \(6, 'H', 2\)"):
        model.rollout(z, trajectories.actions[:, 0])
    with pytest.raises(ValueError, match=r"\(6, 4, 2\)"):
        model.rollout(z, trajectories.actions[:, :, :1])
    nan_actions = trajectories.actions.clone()
    nan_actions[0, 1, 0] = float("nan")
    with pytest.raises(ValueError, match="got NaN or infinity"):  # not the right shape again
        model.rollout(z, nan_actions)
    with pytest.raises(ValueError, match="NaN"):  # the training step checks its batch
        first_step(model, frames, nan_actions)
    framed = r"frames must be \(B, 2, 65, 65\) or \(B, T, 2, 65, 65\)"
    with pytest.raises(ValueError, match=framed):
        model.encode(frames[:, :, :1])
    with pytest.raises(ValueError, match=framed):
        model.encode(frames[..., :64, :64])
    with pytest.raises(ValueError, match=framed + r".*one frame: frames\[None\]"):
        model.encode(frames[0, 0])
    with pytest.raises(ValueError, match="latents of shape"):
        model.rollout(z[:, :4], trajectories.actions)
    with pytest.raises(ValueError, match=r"time - 1"):
        first_step(model, frames, trajectories.actions[:, :3])
    with pytest.raises(ValueError, match="time > 5"):  # K = 5 > T - 1 = 4
        first_step(model, frames, trajectories.actions, steps=5)
    with pytest.raises(ValueError, match="time > 1"):  # one frame has no change to measure
        wl.temporal_similarity_loss(torch.zeros(2, 1, 4))
    with pytest.raises(ValueError, match="at least two samples"):  # no spread to divide by
        fit_position_probe(torch.zeros(1, 3), torch.zeros(1, 2))
    with pytest.raises(ValueError, match="same N"):
        fit_position_probe(torch.zeros(5, 3), torch.zeros(4, 2))


def test_coeff_flag_sets_loss_weights_and_rejects_typos():
    from ebjepa_tutorial.training.world import WorldTrainConfig, ablation_config
    from research.train_world import with_coeffs

    config = with_coeffs(WorldTrainConfig(), ["covariance=1", "temporal=0.5"])
    assert (config.coeffs.covariance, config.coeffs.temporal) == (1.0, 0.5)
    assert config.coeffs.variance == WorldTrainConfig().coeffs.variance  # the rest untouched
    assert with_coeffs(WorldTrainConfig(), []) == WorldTrainConfig()
    assert ablation_config(config, "covariance").coeffs.covariance == 0.0  # --without wins
    for bad, message in [("covariance", "name=value"), ("covarience=1", "name=value"),
                         ("covariance=lots", "not a number"), ("variance=-1", ">= 0"),
                         ("variance=nan", "finite")]:
        with pytest.raises(ValueError, match=message):
            with_coeffs(WorldTrainConfig(), [bad])


def test_command_line_sets_steps_data_size_and_decay(tmp_path, monkeypatch, capsys):
    from research import train_world

    seen = {}

    def fake_train(config, checkpoint=None, device=None):
        seen["config"], seen["partial"] = config, checkpoint
        return tiny_model(), {"loss": [1.0]}

    monkeypatch.setattr(train_world, "train_world_model", fake_train)
    monkeypatch.setattr(train_world, "probe_report",
                        lambda model, walls=1: {"probe_px": 1.5, "baseline_px": 20.0})
    out = tmp_path / "long.pt"
    out.with_suffix(".partial").write_bytes(b"")  # what a real run leaves until it ends
    train_world.main(["--out", str(out), "--steps", "3000", "--trajectories", "100000",
                      "--decay-steps", "500", "--without", "covariance"])
    config = seen["config"]
    assert (config.steps, config.n_trajectories, config.recipe.decay_steps) == (3000, 100_000,
                                                                                 500)
    assert config.coeffs.covariance == 0
    assert seen["partial"] == out.with_suffix(".partial") and not seen["partial"].exists()
    state = torch.load(out, weights_only=False)
    assert state["config"]["n_trajectories"] == 100_000 and state["probe_px"] == 1.5
    assert "probe error 1.50 px" in capsys.readouterr().out


def test_learning_rate_decays_linearly_over_the_last_steps(monkeypatch):
    from ebjepa_tutorial.training.world import WorldTrainConfig

    config = WorldTrainConfig(model=TINY, n_trajectories=8, batch_size=4, steps=6,
                              recipe=world.Recipe(decay_steps=4), lr=0.5)
    rates = []

    def record(model, optimizer, *args):
        rates.append(optimizer.param_groups[0]["lr"])
        optimizer.step()  # no gradients: nothing moves
        return torch.zeros(()), {}

    train_world_model(config, progress=False, device="cpu", step=record)
    assert rates == pytest.approx([0.5, 0.5, 0.5, 0.375, 0.25, 0.125])  # (6 - s) / 4, capped
    assert world.decay_factor(WorldTrainConfig(), 999) == 1  # the class run: constant


def test_the_replay_follows_the_joint_steps_schedule(small_replay, monkeypatch):
    # a replay at a constant rate kept the predictor's updates at full size through the
    # decay; each step's replayed updates now use that step's share of REPLAY_LR
    replay = _replay(replay_steps=1, lr=0.2, monkeypatch=monkeypatch, steps=6, decay_steps=4)
    config = replay.config
    replay.add(torch.randn(8, 3, 8), torch.randn(8, 2, 2))
    rates = []
    for step in range(config.steps):
        replay(step)
        rates.append(replay.optimizer.param_groups[0]["lr"])
    assert rates == pytest.approx([0.2, 0.2, 0.2, 0.15, 0.1, 0.05])  # 0.2 x (6 - s) / 4, capped


def test_a_decayed_run_trains_and_saves_its_schedule(tmp_path):
    from ebjepa_tutorial.models.world import WORLD_CONFIGS
    from ebjepa_tutorial.training.world import WorldTrainConfig

    config = WorldTrainConfig(model=WORLD_CONFIGS["ci"], n_trajectories=32, batch_size=4,
                              steps=3, recipe=world.Recipe(decay_steps=2), rollout_steps=2)
    partial = tmp_path / "run.partial"
    model, history = train_world_model(config, checkpoint=partial, progress=False,
                                       device="cpu")
    assert history["step"] == [0, 2] and all(map(math.isfinite, history["loss"]))  # every 10th
    state = torch.load(partial, weights_only=False)
    assert state["step"] == 3 and state["scheduler"]["last_epoch"] == 3


# -- the MLP predictor and its refit on frozen latents -------------------------------------
def test_mlp_predictor_starts_as_the_identity_and_travels_in_checkpoints(data):
    trajectories, frames = data
    torch.manual_seed(0)
    model = WorldModel(replace(TINY, predictor="mlp", predictor_hidden=12)).fit_input_stats(frames)
    z = model.encode(frames[:, 0])
    assert torch.equal(model.predict(z, trajectories.actions[:, 0]), z)
    loaded = WorldModel.from_state_dict(model.state_dict())
    assert loaded.config.predictor == "mlp" and loaded.predictor.body[0].out_features == 12
    with pytest.raises(ValueError, match="predictor: the checkpoint has 'mlp', this model has"):
        tiny_model().load_state_dict(model.state_dict())


def test_checkpoints_from_before_the_predictor_field_load_as_grus(data):
    state = tiny_model(data[1]).state_dict()
    for name in ("predictor", "predictor_hidden"):
        del state["_extra_state"]["config"][name]  # what the shipped GRU checkpoints hold
    assert WorldModel.from_state_dict(state).config == TINY
    tiny_model().load_state_dict(state)


def test_checkpoints_that_name_the_frame_size_and_channels_still_load(data):
    state = tiny_model(data[1]).state_dict()
    # what the shipped files hold: the frame's sizes were config fields, now constants
    state["_extra_state"]["config"].update(in_channels=2, image_size=65)
    assert WorldModel.from_state_dict(state).config == TINY
    tiny_model().load_state_dict(state)


def test_windows_with_stays_splice_still_steps_by_hand():
    from research.refit import windows_with_stays

    latents = torch.arange(2 * 6, dtype=torch.float32).view(2, 6, 1)  # frame t of n: 6n + t
    actions = torch.arange(2 * 5, dtype=torch.float32).view(2, 5, 1).repeat(1, 1, 2) + 100
    index, start = torch.tensor([0, 1]), torch.tensor([0, 2])
    stay = torch.tensor([[False, True, False], [True, True, False]])
    z0, taken, targets = windows_with_stays(latents, actions, index, start, stay)
    assert z0.squeeze(1).tolist() == [0, 8]
    # trajectory 0: move (a_0 -> frame 1), stay (0 -> frame 1), move (a_1 -> frame 2)
    # trajectory 1 from frame 2: stay, stay, move (a_2 -> frame 3)
    assert targets.squeeze(-1).tolist() == [[1, 1, 2], [8, 8, 9]]
    assert taken[..., 0].tolist() == [[100, 0, 101], [0, 0, 107]]


def test_refit_predictor_keeps_the_encoder_and_fits_a_new_step():
    from ebjepa_tutorial.models.world import WORLD_CONFIGS
    from research.refit import RefitConfig, refit_predictor

    torch.manual_seed(0)
    old = WorldModel(WORLD_CONFIGS["ci"]).fit_input_stats(
        generate_trajectories(8, seed=1).frames())
    config = RefitConfig(hidden=16, n_trajectories=24, steps=100, batch_size=32, lr=1e-2)
    new, history = refit_predictor(old, config, progress=False)
    assert new.config == replace(old.config, predictor="mlp", predictor_hidden=16)
    for name, value in old.state_dict().items():
        if name.startswith(("encoder.", "inverse_dynamics.", "input_")):
            assert torch.equal(new.state_dict()[name], value), name
    assert len(history["loss"]) == 3  # steps 0, 50 and the last
    # 8-step rollouts on the refit's trajectories, no still steps: the old predictor is
    # untrained (the identity), so the refit must beat "nothing moves"
    trajectories = generate_trajectories(24, seed=config.seed)
    latents = encode_trajectories(old, trajectories)[0].view(24, 17, -1)
    z0, actions, targets = latents[:, 0], trajectories.actions[:, :8], latents[:, 1:9]
    with torch.no_grad():
        still, fitted = ((m.rollout(z0, actions) - targets).pow(2).mean() for m in (old, new))
    assert fitted < 0.75 * still
    with pytest.raises(ValueError, match="stay_probability"):
        RefitConfig(stay_probability=1.0)


@pytest.mark.slow  # the command encodes the wall test's 400 trajectories twice
def test_refit_command_saves_the_base_config_and_refuses_training_options(tmp_path, capsys):
    from ebjepa_tutorial.models.world import WORLD_CONFIGS
    from ebjepa_tutorial.training.checkpoints import save_checkpoint
    from research import refit, train_world

    torch.manual_seed(0)
    old = WorldModel(WORLD_CONFIGS["ci"]).fit_input_stats(
        generate_trajectories(8, seed=1).frames())
    trained, out = tmp_path / "trained.pt", tmp_path / "refit.pt"
    base = world.identity(world.WorldTrainConfig(steps=7))
    save_checkpoint(trained, model=old.state_dict(), config=base, probe_px=3.0)
    train_world.main(["--refit", str(trained), "--out", str(out), "--steps", "2",
                      "--trajectories", "16", "--seed", "5", "--stay-probability", "0"])
    state = torch.load(out, weights_only=False)
    assert state["config"] == refit.refit_identity(
        refit.RefitConfig(steps=2, n_trajectories=16, seed=5, stay_probability=0.0), base)
    assert state["probe_px"] == 3.0
    assert world.load_world_model(out).config.predictor == "mlp"
    assert "the wall test stops" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        train_world.main(["--refit", str(trained), "--out", str(out), "--coeff", "temporal=1"])
    assert "--coeff cannot apply" in capsys.readouterr().err


def test_the_two_recipes_differ_only_in_how_they_train():
    from ebjepa_tutorial.course.presets import preset

    course_recipe, paper_recipe = world.course_recipe, world.paper_recipe
    paper = world.WorldTrainConfig()
    course = course_recipe(paper)
    assert paper_recipe(course) == paper and course_recipe(course) == course
    assert (course.coeffs, course.rollout_steps, course.lr) == (paper.coeffs, 8, paper.lr)
    assert (course.recipe.window, course.recipe.replay_steps, course.model.predictor) == (
        9, 3, "mlp")
    assert (paper.recipe, paper.model.predictor) == (world.Recipe(), "gru")
    # notebook 05 trains the course's way; chapter 06's long runs and `full`, the paper's
    assert preset("05", "class").train == course_recipe(replace(paper, steps=2800))
    long_world = preset("06", "class").longer.paper
    assert paper_recipe(long_world) == long_world
    assert paper_recipe(preset("05", "full").train) == preset("05", "full").train


def test_command_line_trains_the_run_of_a_scale(tmp_path, monkeypatch):
    from ebjepa_tutorial.course.presets import preset
    from research import train_world

    seen = {}

    def fake_train(config, checkpoint=None, device=None):
        seen["config"] = config
        return tiny_model(), {"loss": [1.0]}

    monkeypatch.setattr(train_world, "train_world_model", fake_train)
    monkeypatch.setattr(train_world, "probe_report",
                        lambda model, walls=1: {"probe_px": 1.5, "baseline_px": 20.0})
    train_world.main(["--scale", "ci", "--out", str(tmp_path / "ci.pt")])
    assert seen["config"] == preset("05", "ci").train
    # notebook 06's full-scale ablations, trained as docs/running.md says
    train_world.main(["--scale", "full", "--without", "variance", "--out", str(tmp_path / "v.pt")])
    assert seen["config"] == world.ablation_config(preset("06", "full").world, "variance")
    train_world.main(["--scale", "ci", "--out", str(tmp_path / "ci.pt"), "--paper-recipe",
                      "--window", "9", "--wall-fraction", "0.25"])
    assert seen["config"] == replace(world.paper_recipe(preset("05", "ci").train),
                                     recipe=world.Recipe(window=9, wall_fraction=0.25))
    long_run = ["--paper-recipe", "--steps", "10000", "--trajectories", "100000"]
    train_world.main(["--out", str(tmp_path / "long.pt"), *long_run])  # checkpoints/README.md
    assert seen["config"] == preset("06", "class").longer.paper
    train_world.main(["--out", str(tmp_path / "three.pt"), "--walls", "2"])  # checkpoints/README
    assert seen["config"] == replace(preset("05", "class").train, walls=2)
    train_world.main(["--out", str(tmp_path / "clip.pt"), "--grad-clip", "1"])
    train = preset("05", "class").train
    assert seen["config"] == replace(train, recipe=replace(train.recipe, grad_clip=1.0))
    train_world.main(["--out", str(tmp_path / "wide.pt"), "--predictor-hidden", "256"])
    assert seen["config"].model == replace(preset("05", "class").train.model, predictor_hidden=256)
    for option in (["--scale", "ci"], ["--window", "9"], ["--channels-last"], ["--paper-recipe"],
                   ["--walls", "2"], ["--predictor-hidden", "256"], ["--grad-clip", "1"]):
        with pytest.raises(SystemExit):
            train_world.main(["--refit", "x.pt", "--out", "y.pt", *option])
    for wrong in (["--steps", "0"], ["--predictor-hidden", "0"], ["--grad-clip", "-1"]):
        with pytest.raises(SystemExit):  # a usage message, not a traceback
            train_world.main(["--out", "y.pt", *wrong])


def test_an_identity_holds_the_fields_that_define_the_run():
    from ebjepa_tutorial.training.world import WorldTrainConfig, identity
    from research.refit import RefitConfig, refit_identity

    default = identity(WorldTrainConfig())
    # the fields named always, and nothing left at its default
    assert set(default) == {"steps", "batch_size", "lr", "n_trajectories", "rollout_steps",
                            "seed"}
    changed = identity(WorldTrainConfig(recipe=world.Recipe(decay_steps=4),
                                        coeffs=wl.WorldLossCoeffs(sigreg=0.05)))
    assert changed == {**default, "recipe": {"decay_steps": 4}, "coeffs": {"sigreg": 0.05}}
    assert default != changed
    refit = refit_identity(RefitConfig(), default)
    assert refit["base"] == default


def test_a_new_option_with_a_default_leaves_stored_identities_alone():
    from ebjepa_tutorial.training.checkpoints import run_identity

    @dataclass(frozen=True)
    class Before:
        steps: int = 10
        lr: float = 1e-3

    @dataclass(frozen=True)
    class After:  # Before with an option added since
        steps: int = 10
        lr: float = 1e-3
        new_option: bool = False

    assert run_identity(Before(steps=20), ("steps",)) == run_identity(After(steps=20), ("steps",))
    assert run_identity(After(steps=20, new_option=True), ("steps",))["new_option"] is True
    # a field named always is stored at its default too, so changing that default is seen
    assert run_identity(Before(), ("steps",)) == {"steps": 10}


# -- the device asked for ------------------------------------------------------------------
# With no GPU here, the other device is "meta": tensors with shapes and no numbers, which
# refuse to meet CPU tensors in an operation. A model or batch left on the CPU shows up.
def devices_of(model) -> set[str]:
    """The device types of every parameter and buffer of ``model``."""
    return {t.device.type for t in model.state_dict().values() if isinstance(t, torch.Tensor)}


def fit_that_records(seen: list):
    """A stand-in for ``research.fitting.fit`` (a meta loss has no value to log): it notes the
    devices of the model and of batch 0, and trains nothing."""
    from ebjepa_tutorial.training.loop import History

    def fit(model, optimizer, loss_fn, batch_fn, steps, **options):
        batch = [t for t in batch_fn(0) if isinstance(t, torch.Tensor)]
        seen.append(devices_of(model) | {t.device.type for t in batch})
        history = History()
        history.log(0, loss=0.0)
        return history
    return fit


def steps_that_record(seen: list):
    """A stand-in for the loop the world model trains in (a meta loss has no value to log): it
    notes the devices of batch 0, and trains nothing (the model's are checked on its return)."""

    def run_steps(update, batch_fn, steps, **options):
        seen.append({t.device.type for t in batch_fn(0) if isinstance(t, torch.Tensor)})
        return History(loss=[0.0])
    return run_steps


WORLD_RUN = world.WorldTrainConfig(model=WORLD_CONFIGS["ci"], n_trajectories=16, batch_size=4,
                                   steps=2, rollout_steps=2)


def test_train_or_load_returns_the_model_on_the_device_asked_for(tmp_path, monkeypatch):
    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path))
    nb = notebook()  # notebook 05's train_or_load, and its loop
    trained, _ = nb.train_or_load(WORLD_RUN, "run", world.world_model_step, "cpu")  # 2 steps
    assert devices_of(trained) == {"cpu"}
    loaded = world.load_run(WORLD_RUN, "run", device="meta")  # notebooks 06 and 07's entry
    assert devices_of(loaded) == {"meta"}  # read from the cache straight onto the device
    seen = []
    monkeypatch.setitem(nb.train_world_model.__globals__, "run_steps", steps_that_record(seen))
    on_meta, _ = nb.train_or_load(WORLD_RUN, "another_run", world.world_model_step, "meta")
    assert seen == [{"meta"}] and devices_of(on_meta) == {"meta"}  # every batch and the model


def test_a_run_that_is_only_loaded_names_what_makes_it(tmp_path, monkeypatch):
    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path))
    with pytest.raises(FileNotFoundError, match="no saved run of this configuration at .*"
                       "never_trained.pt \\(a file of another configuration is not used.*"
                       "Notebook 05.*checkpoints/README.md.*docs/running.md"):
        world.load_run(WORLD_RUN, "never_trained", device="cpu")
    assert not list(tmp_path.rglob("*.pt*"))  # nothing trained, nothing written


@pytest.mark.filterwarnings("ignore:for .*copying from a non-meta parameter")  # a no-op copy
def test_the_refit_works_on_the_device_asked_for_and_leaves_the_model_where_it_is(monkeypatch):
    from research import refit

    torch.manual_seed(0)
    old = WorldModel(WORLD_CONFIGS["ci"]).fit_input_stats(generate_trajectories(8, seed=1).frames())
    config = refit.RefitConfig(hidden=8, n_trajectories=8, steps=2, batch_size=4)
    new, _ = refit.refit_predictor(old, config, progress=False, device="cpu")
    assert devices_of(new) == {"cpu"}
    seen = []
    monkeypatch.setattr(refit, "fit", fit_that_records(seen))
    new, _ = refit.refit_predictor(old, config, progress=False, device="meta")
    assert seen == [{"meta"}] and devices_of(new) == {"meta"}  # the new model and its windows
    assert devices_of(old) == {"cpu"}  # it encoded where it was


def test_loading_a_world_model_names_what_is_wrong_and_the_command_that_makes_it(tmp_path):
    from ebjepa_tutorial.training.checkpoints import save_checkpoint

    path = save_checkpoint(tmp_path / "ci.pt", model=WorldModel(WORLD_CONFIGS["ci"]).state_dict())
    assert world.load_world_model(path).config == WORLD_CONFIGS["ci"]
    loaded = world.load_world_model(path, device="meta")  # on the device asked for
    assert devices_of(loaded) == {"meta"}
    other = save_checkpoint(tmp_path / "other.pt", model={"weight": torch.zeros(2)})
    with pytest.raises(ValueError, match="holds no world model"):
        world.load_world_model(other)
    with pytest.raises(FileNotFoundError, match="no checkpoint at .*\n.*made by: python -m x"):
        world.load_world_model(tmp_path / "missing.pt", made_by="python -m x")
    (tmp_path / "damaged.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="damaged.pt is damaged(.|\n)*made by: python -m x"):
        world.load_world_model(tmp_path / "damaged.pt", made_by="python -m x")


class MetaWorldModel(torch.nn.Module):
    """A world model on "meta" that refuses inputs from elsewhere and answers zeros on the CPU,
    as a copy back from a GPU would (meta tensors hold nothing to copy): latents ``(B, 4)``."""

    def __init__(self):
        super().__init__()
        self.unused = torch.nn.Parameter(torch.zeros((), device="meta"))

    def encode(self, frames):
        assert frames.is_meta, f"frames on {frames.device}, the model is on meta"
        return torch.zeros(*frames.shape[:-3], 4)

    def predict(self, z, actions):
        assert z.is_meta and actions.is_meta, f"{z.device} and {actions.device}, not meta"
        return torch.zeros(len(z), 4)


def test_probes_and_wall_tests_hand_the_model_its_inputs_on_its_device():
    model, trajectories = MetaWorldModel(), generate_trajectories(40, seed=778)
    latents, positions = encode_trajectories(model, trajectories)
    assert latents.shape == (40 * 17, 4) and latents.device.type == "cpu"
    assert middle_wall_test(model, trajectories)["n_stopped"] > 0
    assert len(wall_test_by_door_distance(model, trajectories)) == 5
    on_meta = fit_position_probe(latents.to("meta"), positions)  # a fit where the latents are
    assert devices_of(on_meta) == {"meta"}


def test_a_clipped_step_moves_the_weights_by_at_most_the_clip(data):
    trajectories, frames = data
    model = tiny_model(frames)
    before = [p.detach().clone() for p in model.parameters()]
    sgd = torch.optim.SGD(model.parameters(), lr=1.0)  # a step of lr x gradient
    config = world.WorldTrainConfig(model=TINY, batch_size=6, rollout_steps=2,
                                    recipe=world.Recipe(grad_clip=0.5))
    world.world_model_step(model, sgd, frames, trajectories.actions,
                           torch.Generator().manual_seed(0), config, 0)
    moved = torch.cat([(p.detach() - b).flatten() for p, b in zip(model.parameters(), before)])
    assert moved.norm().item() == pytest.approx(0.5)  # the whole gradient's norm was far above


def test_a_clipped_replay_update_steps_with_at_most_the_clipped_gradient(small_replay):
    recipe = world.Recipe(replay_steps=2, grad_clip=1e-3)  # far below the raw gradient's norm
    config = world.WorldTrainConfig(model=TINY, batch_size=4, rollout_steps=2, recipe=recipe)
    replay = world.LatentReplay(tiny_model(), config, frames=3, device="cpu")
    torch.manual_seed(0)
    replay.add(torch.randn(8, 3, 8), 3 * torch.randn(8, 2, 2))
    norms, step = [], replay.optimizer.step

    def watched(*args, **kwargs):  # the gradient each replayed update steps with
        grads = [p.grad.flatten() for p in replay.parameters if p.grad is not None]
        norms.append(torch.cat(grads).norm().item())
        return step(*args, **kwargs)

    replay.optimizer.step = watched
    replay(0)
    assert len(norms) == 2 and max(norms) == pytest.approx(1e-3, rel=1e-4)


def test_a_clipped_run_clips_the_step_the_course_recipe_takes(small_replay):
    config = world.course_recipe(world.WorldTrainConfig(
        model=WORLD_CONFIGS["ci"], n_trajectories=16, batch_size=4, steps=2))
    (plain, _), (clipped, history) = _two_runs(
        config, recipe=replace(config.recipe, grad_clip=1e-3))
    assert len(history["loss"]) == 2 and _differ(plain, clipped, "encoder.")


# -- scores by hand ----------------------------------------------------------------------------
def test_the_probe_error_is_the_mean_euclidean_distance_in_pixels():
    read = torch.tensor([[3.0, 4.0], [0.0, 0.0], [1.0, 1.0]])  # an identity probe reads these
    # distances 5, 0 and sqrt(2) from the origin: their mean, not the root mean square (3)
    assert probe_error_px(torch.nn.Identity(), read, torch.zeros(3, 2)) == pytest.approx(
        (5 + 2 ** 0.5) / 3, rel=1e-6)


def test_the_blind_baseline_answers_the_mean_training_position():
    train, test = torch.tensor([[0.0, 0.0], [0.0, 4.0]]), torch.tensor([[3.0, 6.0], [3.0, 6.0]])
    assert mean_baseline_px(train, test) == pytest.approx(5.0)  # from (0, 2): a 3-4-5 triangle


class _Noise(torch.nn.Module):
    """A latent that knows nothing: fresh Gaussian numbers for every frame."""

    def __init__(self):
        super().__init__()
        self.anchor, self.generator = torch.nn.Parameter(torch.zeros(())), torch.Generator()
        self.generator.manual_seed(0)

    def encode(self, frames):
        return torch.randn(*frames.shape[:-3], 64, generator=self.generator)


def test_the_probe_report_scores_frames_the_probe_never_saw():
    # 64 random numbers fit 3 x 17 frames' positions perfectly; on held-out frames they know
    # nothing, so the probe must score about the blind baseline, not the fit's near-zero error
    from ebjepa_tutorial.evaluation.position import probe_report

    report = probe_report(_Noise(), n_fit=3, n_test=20)
    assert report["probe_px"] > 0.8 * report["baseline_px"]


def test_a_restored_replay_writes_its_next_windows_where_the_saved_one_would(small_replay):
    first, second = _replay(), _replay()
    first.add(torch.randn(11, 3, 8), torch.randn(11, 2, 2))  # 11 windows into 8 rows: head 3
    second.load_state_dict(first.state_dict())
    assert (second.head, second.filled) == (3, 8)
    more = torch.randn(2, 3, 8), torch.randn(2, 2, 2)
    first.add(*more), second.add(*more)
    assert torch.equal(first.latents, second.latents)


def test_the_wall_test_keeps_steps_a_wall_cut_short_and_free_steps_of_full_length():
    from ebjepa_tutorial.envs.trajectories import roll_out
    from ebjepa_tutorial.evaluation.position import _wall_steps

    layouts = torch.tensor([[30, 40], [30, 40]])  # the wall's left face at x = 27.5
    starts = torch.tensor([[10.0, 10.0], [27.0, 10.0]])
    actions = torch.tensor([[[0.3, 0.0], [1.0, 0.0]],  # a short free step, then a full one
                            [[1.8, 0.0], [0.0, 1.0]]])  # into the wall (1.3 px lost), then down
    positions = roll_out(starts, actions, layouts)
    assert positions[1, 1].tolist() == [27.5, 10.0]
    door = torch.zeros(2, dtype=torch.bool)
    stopped, moved = _wall_steps(Trajectories(positions, actions, layouts, door))
    assert stopped.tolist() == [[False, False], [True, False]]
    assert moved.tolist() == [[False, True], [False, True]]  # 0.3 px is too short to count


def test_a_world_run_resumes_where_it_stopped_replay_included(tmp_path, monkeypatch):
    # the course recipe's run, saved every step, dies while rendering step 3's batch; the run
    # started again must train steps 3 and 4 only and end as the straight run ends (the replay
    # buffer, its write position and its Adam come back from the file with the model)
    monkeypatch.setattr(world, "REPLAY_BATCH", 8)
    monkeypatch.setattr(world, "REPLAY_CAPACITY", 5)  # 12 windows by step 3: it has wrapped
    recipe = world.Recipe(window=4, replay_steps=2, stay_probability=0.2, decay_steps=3)
    config = world.WorldTrainConfig(model=replace(TINY, predictor="mlp"), n_trajectories=16,
                                    batch_size=4, steps=5, rollout_steps=2, recipe=recipe)
    nb = notebook()
    cell = nb.train_world_model.__globals__  # the notebook cell's names
    run_steps = cell["run_steps"]
    monkeypatch.setitem(cell, "run_steps", lambda *args, **kw: run_steps(
        *args, **{**kw, "every": 1, "log_every": 1}))
    data = world.make_data(config)
    straight, history = nb.train_world_model(config, data, world.world_model_step, None, "cpu",
                                             False)
    render, calls = cell["envs"].render, []

    def dying_render(*args, **kwargs):
        calls.append(1)
        if len(calls) == 4:
            raise KeyboardInterrupt
        return render(*args, **kwargs)

    checkpoint = tmp_path / "run.pt"
    monkeypatch.setattr(cell["envs"], "render", dying_render)
    with pytest.raises(KeyboardInterrupt):
        nb.train_world_model(config, data, world.world_model_step, checkpoint, "cpu", False)
    monkeypatch.setattr(cell["envs"], "render", render)
    resumed, again = nb.train_world_model(config, data, world.world_model_step, checkpoint,
                                          "cpu", False)
    assert again["step"] == history["step"] and again["loss"] == history["loss"]
    assert all(torch.equal(a, b) for a, b in zip(straight.parameters(), resumed.parameters()))


def test_a_misspelt_predictor_is_refused_not_built_as_the_mlp():
    with pytest.raises(ValueError, match=r"predictor must be 'gru' or 'mlp', got 'GRU'"):
        WorldConfig(predictor="GRU")
