"""The warm-up + cosine schedule and AdamW's parameter groups."""


import pytest
import torch

from ebjepa_tutorial.training.optim import (
    split_decay_params,
    warmup_cosine,
    warmup_cosine_scheduler,
)


def test_schedule_key_values():
    total, warmup = 100, 10

    def lr(step):
        return 2.0 * warmup_cosine(step, total, warmup)

    assert lr(0) == pytest.approx(0.2)  # warms up from the first step: base / warmup, not 0
    assert lr(4) == pytest.approx(1.0)
    assert lr(9) == pytest.approx(2.0)  # end of warm-up: the full base rate
    assert lr(9 + 45) == pytest.approx(1.0)  # halfway down the cosine
    assert lr(99) == pytest.approx(0.0)  # last step: 0
    assert all(lr(s) > lr(s + 1) for s in range(9, 99))  # decreasing after the peak
    assert warmup_cosine(0, 10, 0) == pytest.approx(1.0)  # no warm-up


def test_scheduler_sets_the_optimizer_lr():
    weight = torch.nn.Parameter(torch.ones(2, 2))
    optimizer = torch.optim.SGD([weight], lr=0.3)
    scheduler = warmup_cosine_scheduler(optimizer, total_steps=20, warmup_steps=5)
    seen = []
    for _ in range(20):
        seen.append(optimizer.param_groups[0]["lr"])
        weight.grad = torch.ones(2, 2)
        optimizer.step()
        scheduler.step()
    assert seen[0] == pytest.approx(0.3 / 5) and seen[4] == pytest.approx(0.3)
    assert seen[-1] == pytest.approx(0.0, abs=1e-12)
    for _ in range(5):  # a resumed or over-long run: the rate stays at 0, never climbs back
        scheduler.step()
        assert optimizer.param_groups[0]["lr"] == pytest.approx(0.0, abs=1e-12)


def test_split_decay_params():
    model = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.BatchNorm1d(4))
    decay, no_decay = split_decay_params(model, 0.05)
    assert [p.shape for p in decay["params"]] == [(4, 3)] and decay["weight_decay"] == 0.05
    assert len(no_decay["params"]) == 3 and no_decay["weight_decay"] == 0.0
    model[0].weight.requires_grad_(False)  # a frozen layer is in neither group
    decay, no_decay = split_decay_params(model, 0.05)
    assert decay["params"] == [] and len(no_decay["params"]) == 3


def test_a_one_step_run_without_warm_up_takes_the_full_rate():
    """A run of a single step and no warm-up (as a timing run makes) has no cosine to descend:
    its one step, and any step past it, use the full base rate."""
    assert warmup_cosine(0, 1, 0) == 1.0
    weight = torch.nn.Parameter(torch.ones(2))
    optimizer = torch.optim.SGD([weight], lr=0.3)
    scheduler = warmup_cosine_scheduler(optimizer, total_steps=1, warmup_steps=0)
    for _ in range(3):
        assert optimizer.param_groups[0]["lr"] == pytest.approx(0.3)
        weight.grad = torch.ones(2)
        optimizer.step()
        scheduler.step()


def test_a_frozen_layer_is_in_neither_group():
    """Freezing a whole layer (its weight and its bias) takes both out of the optimiser's
    groups, the 1-D bias as well as the matrix."""
    model = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.BatchNorm1d(4))
    model[0].requires_grad_(False)
    decay, no_decay = split_decay_params(model, 0.05)
    assert decay["params"] == []
    assert [p is q for p, q in zip(no_decay["params"], model[1].parameters())] == [True, True]
