"""Encoders and projector: shapes, the CIFAR stem, clear errors, and one VICReg training step;
the video and world models' layers, each checked on an input whose answer is known."""

import math
from dataclasses import replace

import pytest
import torch

from ebjepa_tutorial.augment import build_augmentation, two_views
from ebjepa_tutorial.losses import vicreg_loss
from ebjepa_tutorial.models.encoders import ResidualBlock, ResNet18, build_projector
from ebjepa_tutorial.models.video import VIDEO_MODEL_CONFIGS, VideoJEPA, detection_head
from ebjepa_tutorial.models.world import ResidualBlock as ImpalaBlock
from ebjepa_tutorial.models.world import WorldConfig, WorldModel
from ebjepa_tutorial.utils import as_generator

SMALL = (8, 16, 32, 64)
TINY_WORLD = WorldConfig(widths=(4, 8), blocks=1, input_size=17, latent_dim=8,
                         action_embed_dim=8, idm_hidden=16)


def test_resnet18_shapes_and_width():
    torch.manual_seed(0)
    encoder = ResNet18(widths=SMALL)
    x = torch.randn(2, 3, 32, 32)
    assert encoder(x).shape == (2, 64) and encoder.out_dim == 64
    # The 3x3 stride-1 stem with padding 1 keeps 32x32 (padding 2 would give 34x34);
    # three stride-2 stages then give 4x4 maps.
    assert encoder.stem(x).shape == (2, 8, 32, 32)
    assert encoder.stages(encoder.stem(x)).shape == (2, 64, 4, 4)
    assert ResNet18().out_dim == 512


def test_resnet18_has_the_resnet18_layout():
    encoder = ResNet18()
    convs = [m for m in encoder.modules() if isinstance(m, torch.nn.Conv2d)]
    # 1 stem + 8 blocks x 2 convolutions + 3 shortcut projections.
    assert len(convs) == 1 + 16 + 3
    assert not any(isinstance(m, torch.nn.MaxPool2d) for m in encoder.modules())
    params = sum(p.numel() for p in encoder.parameters())
    assert 11.0e6 < params < 11.3e6  # the CIFAR ResNet-18 has about 11.2 M parameters


def test_projector_layers_and_identity():
    projector = build_projector(64, hidden_dim=128, out_dim=32, depth=3)
    assert isinstance(projector, torch.nn.Sequential)
    kinds = [type(m).__name__ for m in projector]
    assert kinds == ["Linear", "BatchNorm1d", "ReLU"] * 2 + ["Linear"]
    # a bias before batch norm is subtracted again at once; only the output layer keeps one
    assert [m.bias is not None for m in projector if isinstance(m, torch.nn.Linear)] == [
        False, False, True]
    assert projector(torch.randn(4, 64)).shape == (4, 32) and projector.out_dim == 32
    identity = build_projector(64, 0, 0, depth=0)
    x = torch.randn(4, 64)
    assert torch.equal(identity(x), x) and identity.out_dim == 64


def test_bad_inputs_are_named():
    encoder = ResNet18(widths=SMALL)
    for bad in (torch.randn(2, 1, 32, 32), torch.randn(3, 32, 32),
                torch.zeros(2, 3, 32, 32, dtype=torch.uint8)):
        with pytest.raises(ValueError, match=r"float images \(batch, 3, height, width\)"):
            encoder(bad)


def test_one_vicreg_training_step_runs():
    torch.manual_seed(0)
    encoder = ResNet18(widths=SMALL)
    projector = build_projector(encoder.out_dim, hidden_dim=64, out_dim=32, depth=3)
    params = list(encoder.parameters()) + list(projector.parameters())
    optimizer = torch.optim.SGD(params, lr=0.01)
    images = torch.randint(0, 256, (8, 3, 32, 32), dtype=torch.uint8, generator=as_generator(0))
    view_a, view_b = two_views(images, build_augmentation(), as_generator(1))
    z = projector(encoder(torch.cat([view_a, view_b])))  # both views in one batch
    loss, terms = vicreg_loss(*z.chunk(2), inv_coeff=25.0, std_coeff=25.0, cov_coeff=1.0)
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    assert torch.isfinite(loss) and set(terms) == {"invariance", "variance", "covariance"}
    assert all(p.grad is not None and torch.isfinite(p.grad).all() for p in params)
    for _ in range(2):  # the same views again: steps down the gradient lower their loss
        z = projector(encoder(torch.cat([view_a, view_b])))
        later, _ = vicreg_loss(*z.chunk(2), inv_coeff=25.0, std_coeff=25.0, cov_coeff=1.0)
        optimizer.zero_grad()
        later.backward()
        optimizer.step()
    assert later.item() < loss.item() - 0.1, (loss.item(), later.item())


def test_a_residual_block_adds_its_shortcut_and_rectifies_only_when_asked():
    # with the second convolution's weights at zero the residual branch adds nothing, so the
    # block is its shortcut: relu(x) for an identity shortcut, x itself with relu_out=False
    x = torch.randn(2, 4, 6, 6, generator=as_generator(0))
    for relu_out, expected in ((True, torch.relu(x)), (False, x)):
        block = ResidualBlock(4, 4, relu_out=relu_out).eval()
        torch.nn.init.zeros_(block.conv2.weight)
        assert torch.allclose(block(x), expected, atol=1e-6)
    # a block that changes the width or the side projects the shortcut (a 1x1 conv with stride)
    block = ResidualBlock(4, 8, stride=2).eval()
    torch.nn.init.zeros_(block.conv2.weight)
    assert torch.allclose(block(x), torch.relu(block.shortcut(x)), atol=1e-6)
    assert block(x).shape == (2, 8, 3, 3)


def test_a_residual_blocks_branch_rectifies_between_its_convolutions():
    """Both convolutions the identity (a centred 1 per channel), batch norm at its initial
    running statistics: the branch is relu(x), so the unrectified block gives x + relu(x);
    a branch without its inner ReLU would give 2x."""
    x = torch.randn(2, 4, 6, 6, generator=as_generator(0))
    block = ResidualBlock(4, 4, relu_out=False).eval()
    with torch.no_grad():
        for conv in (block.conv1, block.conv2):
            conv.weight.zero_()
            conv.weight[range(4), range(4), 1, 1] = 1.0
    assert torch.allclose(block(x), x + torch.relu(x), atol=1e-4)


def test_the_features_are_the_spatial_average_of_the_last_map():
    """Global average pooling, as the docstring and the CIFAR ResNet have it: each feature is
    the mean over the 4x4 positions of the last stage's map (a max would keep one position)."""
    encoder = ResNet18(widths=SMALL).eval()
    x = torch.randn(2, 3, 32, 32, generator=as_generator(0))
    last_map = encoder.stages(encoder.stem(x))
    assert last_map.shape[2:] == (4, 4)
    assert torch.allclose(encoder(x), last_map.mean(dim=(2, 3)), atol=1e-6)
    assert not torch.allclose(encoder(x), last_map.amax(dim=(2, 3)), atol=1e-3)


def test_convolutions_start_with_he_initialisation_by_fan_out():
    """kaiming_normal_ in fan_out mode, as in the original ResNet: a 3x3 convolution's weights
    have std sqrt(2 / (9 c_out)); by fan-in the stem's (3 -> 64) would be 4.6 times wider."""
    torch.manual_seed(0)
    encoder = ResNet18()
    for conv in (encoder.stem[0], encoder.stages[1][0].conv1):  # 3 -> 64, 64 -> 128
        expected = math.sqrt(2 / (9 * conv.out_channels))
        assert conv.weight.std().item() == pytest.approx(expected, rel=0.1), conv


# -- the video model -----------------------------------------------------------------------
def test_video_encode_keeps_each_frame_in_its_clip_and_time_slot():
    """encode() on clips (B, T, 1, 64, 64) gives at [b, t] the frame encoder's latent of frame
    [b, t] alone: batching the frames must not shuffle clips and times."""
    model = VideoJEPA(VIDEO_MODEL_CONFIGS["ci"]).eval()
    clips = torch.rand(2, 3, 1, 64, 64, generator=as_generator(0))
    with torch.no_grad():
        z = model.encode(clips)
        for b, t in ((0, 1), (1, 0), (1, 2)):
            assert torch.allclose(z[b, t], model.encoder(clips[b, t][None])[0], atol=1e-5)


def test_video_latents_are_not_rectified():
    """The frame encoder's last residual block leaves its sum un-rectified (relu_out=False),
    so latents take negative values too, as targets of a predictor that can move them."""
    model = VideoJEPA(VIDEO_MODEL_CONFIGS["ci"]).eval()
    with torch.no_grad():
        z = model.encode(torch.rand(1, 2, 1, 64, 64, generator=as_generator(0)))
    assert (z < 0).float().mean() > 0.2


def test_the_video_projector_reads_one_locations_channels_per_row():
    """project() of latents (B, T, C, S, S) has one row per clip, frame and location, in that
    order, projecting the C channels at that location (in eval mode a row does not depend on
    the others); a reshape without moving C last would mix channels and locations."""
    model = VideoJEPA(VIDEO_MODEL_CONFIGS["ci"]).eval()
    z = torch.randn(2, 3, 8, 8, 8, generator=as_generator(0))  # C = S = 8
    with torch.no_grad():
        rows = model.project(z)
        for b, t, i, j in ((0, 0, 0, 1), (1, 2, 3, 5), (0, 1, 7, 0)):
            row = ((b * 3 + t) * 8 + i) * 8 + j
            alone = model.projector(z[b, t, :, i, j][None])[0]
            assert torch.allclose(rows[row], alone, atol=1e-5), (b, t, i, j)


def test_the_detection_head_averages_a_finer_latent_down_to_its_grid():
    """A 16x16 latent is average-pooled to the 8x8 grid first: +1s and -1s alternating inside
    each 2x2 cell average to nothing, so its logits are those of a zero latent (a max pool
    would read the +1s)."""
    head = detection_head(4, grid=8)
    board = ((torch.arange(16)[:, None] + torch.arange(16)) % 2).float() * 2 - 1
    with torch.no_grad():
        logits = head(board.expand(2, 4, 16, 16))
        assert torch.allclose(logits, head(torch.zeros(2, 4, 16, 16)), atol=1e-6)


# -- the world model -----------------------------------------------------------------------
def test_an_impala_block_rectifies_its_input_before_the_first_convolution():
    """x + conv2(relu(conv1(relu(x)))): with conv1 minus the identity and conv2 the identity,
    relu(-relu(x)) is 0 and the block returns x; without the first ReLU it would add relu(-x)
    wherever x is negative."""
    block = ImpalaBlock(3)
    with torch.no_grad():
        for conv, sign in ((block.conv1, -1.0), (block.conv2, 1.0)):
            conv.weight.zero_()
            conv.bias.zero_()
            conv.weight[range(3), range(3), 1, 1] = sign
        x = torch.randn(2, 3, 5, 5, generator=as_generator(0))
        assert torch.equal(block(x), x)


def test_the_impala_encoders_linear_layer_reads_rectified_features():
    """IMPALA's head: a ReLU on the last stack's output, then the Linear, which therefore
    never reads a negative feature (the last residual sum has some)."""
    model = WorldModel(TINY_WORLD)
    seen = []
    hook = model.encoder.linear.register_forward_hook(lambda m, args, out: seen.append(args[0]))
    frames = torch.rand(3, 2, 65, 65, generator=as_generator(0))
    with torch.no_grad():
        model.encode(frames)
        stacked = model.encoder.stacks(model.normalize(frames))
    hook.remove()
    assert stacked.min() < 0 and seen[0].min() >= 0 and seen[0].max() > 0


def test_the_gru_predictor_keeps_the_latent_as_its_hidden_state():
    """z' = z + W GRUCell(e, z): the latent is the GRU's hidden state and the action embedding
    its input. With the update gate held at 1 (h' = h) and W the identity, z' = 2 z whatever
    the action; with the two swapped the action embedding would come through instead."""
    model, d = WorldModel(TINY_WORLD), TINY_WORLD.latent_dim
    with torch.no_grad():
        model.predictor.cell.bias_ih[d:2 * d] = 50.0  # gates r, z, n: z = sigmoid(50) = 1
        model.predictor.out.weight.copy_(torch.eye(d))
        z = torch.randn(4, d, generator=as_generator(0))
        actions = torch.randn(4, 2, generator=as_generator(1))
        assert torch.allclose(model.predict(z, actions), 2 * z, atol=1e-5)


def test_world_frames_are_average_pooled_to_the_input_size():
    """normalize() shrinks 65x65 frames to input_size by averaging (a dot keeps its mass): a
    checkerboard of 0s and 1s becomes grey, 4/9 to 5/9 in 2- and 3-pixel windows, not the
    white of a max pool. Unfitted statistics (mean 0, std 1) leave the values as they are."""
    model = WorldModel(replace(TINY_WORLD, input_size=33))
    board = ((torch.arange(65)[:, None] + torch.arange(65)) % 2).float()
    out = model.normalize(board.expand(1, 2, 65, 65))
    assert out.shape == (1, 2, 33, 33) and out.min() > 0.4 and out.max() < 0.6


def test_input_stats_of_a_channel_that_never_changes_stay_finite():
    """Frames whose wall channel is empty everywhere (a world without walls) have std 0 there:
    the std is floored at 1e-6, so normalised frames and latents stay finite, not 0 / 0."""
    frames = torch.zeros(3, 2, 65, 65)
    frames[:, 0, 30:33, 30:33] = 1.0  # a dot, no wall
    model = WorldModel(TINY_WORLD).fit_input_stats(frames)
    with torch.no_grad():
        assert torch.isfinite(model.normalize(frames)).all()
        assert torch.isfinite(model.encode(frames)).all()


def test_the_shipped_world_model_reads_its_weights_as_they_were_trained():
    """The shipped class model on fresh trajectories: its inverse dynamics, given (z_t,
    z_t+1) in that order, recovers the actions, and its MLP predictor, given [z, e], beats
    copying the latent. An input order changed in the code builds and trains as well, but
    reads every trained checkpoint wrongly."""
    from ebjepa_tutorial.envs import generate_trajectories
    from ebjepa_tutorial.training.checkpoints import SHIPPED_DIR
    from ebjepa_tutorial.training.world import load_world_model

    model = load_world_model(SHIPPED_DIR / "world_model_class.pt", device="cpu")
    trajectories = generate_trajectories(16, steps=8, seed=0)
    actions = trajectories.actions
    with torch.no_grad():
        z = model.encode(trajectories.frames())
        inferred = model.predict_actions(z[:, :-1], z[:, 1:])
        predicted = model.rollout(z[:, 0], actions)
    assert (inferred - actions).pow(2).mean() < 0.3 * actions.pow(2).mean()
    assert (predicted - z[:, 1:]).pow(2).mean() < 0.5 * (z[:, :1] - z[:, 1:]).pow(2).mean()
