"""Encoders and projector: shapes, the CIFAR stem, clear errors, and one VICReg training step."""

import pytest
import torch

from ebjepa_tutorial.augment import build_augmentation, two_views
from ebjepa_tutorial.losses import vicreg_loss
from ebjepa_tutorial.models.encoders import ResidualBlock, ResNet18, build_projector
from ebjepa_tutorial.utils import as_generator

SMALL = (8, 16, 32, 64)


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
