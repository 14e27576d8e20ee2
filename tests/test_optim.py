"""LARS against steps computed by hand, and the warm-up + cosine schedule."""

import math

import pytest
import torch

from ebjepa_tutorial.training.optim import (
    LARS,
    split_decay_params,
    warmup_cosine,
    warmup_cosine_scheduler,
)


def test_lars_two_steps_by_hand():
    weight = torch.nn.Parameter(torch.tensor([[3.0, 4.0]]))  # ||w|| = 5
    bias = torch.nn.Parameter(torch.tensor([1.0]))
    lr, wd, momentum, eta = 0.1, 0.01, 0.9, 0.001
    optimizer = LARS([weight, bias], lr=lr, weight_decay=wd, momentum=momentum, eta=eta)
    g_w, g_b = [0.3, 0.0], 0.5

    # By hand, in plain Python: the weight gets decay and the trust ratio, the bias neither.
    w, b, m_w, m_b = [3.0, 4.0], 1.0, [0.0, 0.0], 0.0
    for _ in range(2):
        weight.grad = torch.tensor([g_w])
        bias.grad = torch.tensor([g_b])
        optimizer.step()
        u = [g + wd * wi for g, wi in zip(g_w, w)]
        ratio = eta * math.hypot(*w) / math.hypot(*u)
        m_w = [momentum * m + ratio * ui for m, ui in zip(m_w, u)]
        w = [wi - lr * m for wi, m in zip(w, m_w)]
        m_b = momentum * m_b + g_b
        b = b - lr * m_b
        assert weight.detach()[0].tolist() == pytest.approx(w, rel=1e-6)
        assert bias.item() == pytest.approx(b, rel=1e-6)
    assert b == pytest.approx(1.0 - 0.1 * 0.5 - 0.1 * 0.95)  # 0.855: plain momentum SGD


def test_lars_moves_each_layer_by_the_same_relative_amount():
    small = torch.nn.Parameter(torch.full((4, 4), 0.01))
    large = torch.nn.Parameter(torch.full((4, 4), 10.0))
    optimizer = LARS([small, large], lr=1.0, weight_decay=0.0, eta=0.01)
    small.grad, large.grad = torch.ones(4, 4) * 5, torch.ones(4, 4) * 1e-3
    before = [small.detach().clone(), large.detach().clone()]
    optimizer.step()
    relative = [(p.detach() - p0).norm() / p0.norm() for p, p0 in zip((small, large), before)]
    assert relative[0].item() == pytest.approx(0.01, rel=1e-5)
    assert relative[1].item() == pytest.approx(0.01, rel=1e-5)


def test_lars_zero_weight_falls_back_to_plain_sgd():
    weight = torch.nn.Parameter(torch.zeros(2, 2))
    optimizer = LARS([weight], lr=0.5, weight_decay=0.1)
    weight.grad = torch.ones(2, 2)
    optimizer.step()
    assert torch.allclose(weight.detach(), torch.full((2, 2), -0.5))


def test_lars_rejects_bad_settings():
    with pytest.raises(ValueError, match="momentum"):
        LARS([torch.nn.Parameter(torch.ones(2, 2))], momentum=1.5)


def test_schedule_key_values():
    total, warmup = 100, 10

    def lr(step):
        return warmup_cosine(step, total, warmup, base_lr=2.0, final_lr=0.0)

    assert lr(0) == pytest.approx(0.2)  # warms up from the first step: base / warmup, not 0
    assert lr(4) == pytest.approx(1.0)
    assert lr(9) == pytest.approx(2.0)  # end of warm-up: the full base_lr
    assert lr(9 + 45) == pytest.approx(1.0)  # halfway down the cosine
    assert lr(99) == pytest.approx(0.0)  # last step: final_lr
    assert all(lr(s) > lr(s + 1) for s in range(9, 99))  # decreasing after the peak
    assert warmup_cosine(0, 10, 0, 1.0, 0.1) == pytest.approx(1.0)  # no warm-up
    assert warmup_cosine(9, 10, 0, 1.0, 0.1) == pytest.approx(0.1)
    with pytest.raises(ValueError, match="outside"):
        lr(100)


def test_scheduler_sets_the_optimizer_lr():
    weight = torch.nn.Parameter(torch.ones(2, 2))
    optimizer = LARS([weight], lr=0.3)
    scheduler = warmup_cosine_scheduler(optimizer, total_steps=20, warmup_steps=5)
    seen = []
    for _ in range(20):
        seen.append(optimizer.param_groups[0]["lr"])
        weight.grad = torch.ones(2, 2)
        optimizer.step()
        scheduler.step()
    assert seen[0] == pytest.approx(0.3 / 5) and seen[4] == pytest.approx(0.3)
    assert seen[-1] == pytest.approx(0.0, abs=1e-12)


def test_split_decay_params():
    model = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.BatchNorm1d(4))
    decay, no_decay = split_decay_params(model, 0.05)
    assert [p.shape for p in decay["params"]] == [(4, 3)] and decay["weight_decay"] == 0.05
    assert len(no_decay["params"]) == 3 and no_decay["weight_decay"] == 0.0
