"""The training loop: history, NaN guard, atomic checkpoints, exact resume, load-or-train."""

from pathlib import Path

import pytest
import torch

from ebjepa_tutorial import train


def _problem(seed=0):
    # A linear regression small enough to train in milliseconds.
    torch.manual_seed(seed)
    model = torch.nn.Linear(3, 1)
    optimizer = torch.optim.SGD(model.parameters(), lr=0.1, momentum=0.5)
    target = torch.tensor([[1.0], [-2.0], [0.5]])

    def batch(step):
        x = torch.randn(16, 3, generator=torch.Generator().manual_seed(step))
        return x, x @ target

    def loss_fn(xy):
        loss = torch.nn.functional.mse_loss(model(xy[0]), xy[1])
        return loss, {"mse": loss.item()}

    return model, optimizer, loss_fn, batch


def test_fit_logs_history_and_learns():
    model, optimizer, loss_fn, batch = _problem()
    history = train.fit(model, optimizer, loss_fn, batch, steps=60, progress=False)
    assert history["step"] == list(range(60))
    assert history["loss"] == history["mse"]
    assert history.last("loss") < 1e-3 < history["loss"][0]


def test_nan_loss_stops_with_a_clear_error():
    model, optimizer, _, batch = _problem()

    def nan_loss(xy):
        return model(xy[0]).sum() * float("nan"), {"term": 1.0}

    with pytest.raises(FloatingPointError, match="step 0 .*term=1"):
        train.fit(model, optimizer, nan_loss, batch, steps=3, progress=False)


def test_resumed_run_equals_uninterrupted_run(tmp_path):
    model, optimizer, loss_fn, batch = _problem()
    straight = train.fit(model, optimizer, loss_fn, batch, steps=10, progress=False)

    ckpt = tmp_path / "run.pt"
    model2, optimizer2, loss_fn2, batch2 = _problem()
    train.fit(model2, optimizer2, loss_fn2, batch2, steps=5, checkpoint=ckpt, progress=False)
    # A new kernel: fresh objects, state restored from the file.
    model3, optimizer3, loss_fn3, batch3 = _problem(seed=123)
    step, history = train.resume(ckpt, model3, optimizer3)
    assert step == 5
    history = train.fit(model3, optimizer3, loss_fn3, batch3, steps=10, start_step=step,
                        history=history, checkpoint=ckpt, progress=False)
    assert history["loss"] == pytest.approx(straight["loss"], rel=1e-6)
    assert torch.allclose(model3.weight, model.weight)


def test_resume_ignores_a_run_with_another_config(tmp_path, capsys):
    model, optimizer, loss_fn, batch = _problem()
    ckpt = tmp_path / "run.pt"
    train.fit(model, optimizer, loss_fn, batch, steps=3, checkpoint=ckpt, progress=False,
              config={"lr": 0.1})
    assert train.resume(ckpt, model, optimizer, config={"lr": 0.1})[0] == 3
    assert train.resume(ckpt, model, optimizer, config={"lr": 0.2}) == (0, {})
    assert "another configuration" in capsys.readouterr().out


def test_resume_without_checkpoint_starts_at_zero(tmp_path):
    model, optimizer, _, _ = _problem()
    assert train.resume(tmp_path / "none.pt", model, optimizer) == (0, {})


def test_checkpoint_write_is_atomic(tmp_path, monkeypatch):
    path = tmp_path / "ckpt.pt"
    train.save_checkpoint(path, value=1)

    def broken_save(obj, f):
        f.write(b"half a checkpoint")
        raise OSError("disk full")

    monkeypatch.setattr(torch, "save", broken_save)
    with pytest.raises(OSError, match="disk full"):
        train.save_checkpoint(path, value=2)
    assert train.load_checkpoint(path)["value"] == 1  # the old file survives
    assert [p.name for p in tmp_path.iterdir()] == ["ckpt.pt"]  # no temp file left


def test_load_checkpoint_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        train.load_checkpoint(tmp_path / "missing.pt")


def test_load_or_train_trains_once_then_loads(tmp_path, capsys):
    path: Path = tmp_path / "model.pt"
    calls = []

    def run(model, optimizer, loss_fn, batch):
        calls.append(1)
        return train.fit(model, optimizer, loss_fn, batch, steps=20, progress=False)

    model, optimizer, loss_fn, batch = _problem()
    config = {"steps": 20, "lr": 0.1}
    first = train.load_or_train(path, model, lambda: run(model, optimizer, loss_fn, batch), config)
    assert "Trained and saved" in capsys.readouterr().out

    fresh, optimizer2, loss_fn2, batch2 = _problem(seed=9)
    again = train.load_or_train(path, fresh, lambda: run(fresh, optimizer2, loss_fn2, batch2),
                                config)
    assert "Loaded" in capsys.readouterr().out
    assert len(calls) == 1 and again == first
    assert torch.equal(fresh.weight, model.weight)

    train.load_or_train(path, fresh, lambda: run(fresh, optimizer2, loss_fn2, batch2),
                        {"steps": 20, "lr": 0.2})
    assert "another configuration" in capsys.readouterr().out
    assert len(calls) == 2


def test_load_or_train_prefers_a_matching_shipped_checkpoint(tmp_path, capsys):
    model, optimizer, loss_fn, batch = _problem()
    history = train.fit(model, optimizer, loss_fn, batch, steps=5, progress=False)
    shipped = train.save_checkpoint(tmp_path / "shipped.pt", model=model.state_dict(),
                                    history=dict(history), config={"steps": 5})
    fresh = _problem(seed=3)[0]
    train.load_or_train(tmp_path / "cache.pt", fresh, lambda: 1 / 0, {"steps": 5},
                        shipped=shipped)
    assert "Loaded" in capsys.readouterr().out
    assert torch.equal(fresh.weight, model.weight)
    assert not (tmp_path / "cache.pt").exists()


def test_checkpoint_paths_separate_cache_and_shipped(monkeypatch, tmp_path):
    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path))
    cache, shipped = train.checkpoint_paths("vicreg_class")
    assert cache == tmp_path / "checkpoints" / "vicreg_class.pt"
    assert shipped.parent.name == "checkpoints" and shipped.name == "vicreg_class.pt"
