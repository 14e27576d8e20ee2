"""The training loop: history, NaN guard, atomic checkpoints, exact resume, load-or-train."""

import linecache
import os
import tempfile
from pathlib import Path

import pytest
import torch

from ebjepa_tutorial.training import checkpoints, loop
from ebjepa_tutorial.training.loop import History


def _problem(seed=0):
    # A linear regression small enough to loop in milliseconds.
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


def fit(model, optimizer, loss_fn, batch, steps, *, checkpoint=None, checkpoint_every=100,
        config=None, log_every=1, progress=False):
    """The package's loop (``loop.run_steps``) on ``loss_fn``, resuming the run ``config`` from
    ``checkpoint`` and saving it there every ``checkpoint_every`` steps and at the end."""

    def update(xy, step):
        loss, terms = loss_fn(xy)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        return loss, terms

    return loop.run_steps(update, batch, steps, log_every=log_every, progress=progress,
                          checkpoint=checkpoint, parts=(model, optimizer), identity=config,
                          every=checkpoint_every)


def test_the_loop_logs_history_and_learns():
    model, optimizer, loss_fn, batch = _problem()
    history = fit(model, optimizer, loss_fn, batch, steps=60, progress=False)
    assert history["step"] == list(range(60))
    assert history.last("loss") < 1e-3 < history["loss"][0]


def test_the_loop_reads_the_loss_only_on_the_steps_it_logs():
    """Reading a number waits for a GPU to finish; between logged steps nothing is read."""
    model, optimizer, _, batch = _problem()
    reads = []

    class Counted(float):  # a term that records each time the loop reads it
        def __float__(self):
            reads.append(1)
            return float.__float__(self)

    def loss_fn(xy):
        return torch.nn.functional.mse_loss(model(xy[0]), xy[1]), {"term": Counted(1.0)}

    history = fit(model, optimizer, loss_fn, batch, steps=25, log_every=10, progress=False)
    assert history["step"] == [0, 10, 20, 24] and len(reads) == 4


def test_nan_loss_stops_with_a_clear_error():
    model, optimizer, _, batch = _problem()

    def nan_loss(xy):
        return model(xy[0]).sum() * float("nan"), {"term": 1.0}

    with pytest.raises(FloatingPointError, match="step 0 .*term=1"):
        fit(model, optimizer, nan_loss, batch, steps=3, progress=False)


def test_resumed_run_equals_uninterrupted_run(tmp_path):
    model, optimizer, loss_fn, batch = _problem()
    straight = fit(model, optimizer, loss_fn, batch, steps=10, progress=False)

    ckpt = tmp_path / "run.pt"
    model2, optimizer2, loss_fn2, batch2 = _problem()
    fit(model2, optimizer2, loss_fn2, batch2, steps=5, checkpoint=ckpt, progress=False)
    # A new kernel: fresh objects, state restored from the file.
    model3, optimizer3, loss_fn3, batch3 = _problem(seed=123)
    assert loop.resume(ckpt, *_problem(seed=1)[:2])[0] == 5
    history = fit(model3, optimizer3, loss_fn3, batch3, steps=10, checkpoint=ckpt,
                  progress=False)
    assert history["loss"] == pytest.approx(straight["loss"], rel=1e-6)
    assert torch.allclose(model3.weight, model.weight)


def test_resume_ignores_a_run_with_another_config(tmp_path, capsys):
    model, optimizer, loss_fn, batch = _problem()
    ckpt = tmp_path / "run.pt"
    fit(model, optimizer, loss_fn, batch, steps=3, checkpoint=ckpt, progress=False,
         config={"lr": 0.1})
    assert loop.resume(ckpt, model, optimizer, config={"lr": 0.1})[0] == 3
    assert loop.resume(ckpt, model, optimizer, config={"lr": 0.2}) == (0, {})
    assert "another configuration" in capsys.readouterr().out


def test_resume_without_checkpoint_starts_at_zero(tmp_path):
    model, optimizer, _, _ = _problem()
    assert loop.resume(tmp_path / "none.pt", model, optimizer) == (0, {})


def test_checkpoint_write_is_atomic(tmp_path, monkeypatch):
    path = tmp_path / "ckpt.pt"
    checkpoints.save_checkpoint(path, value=1)

    def broken_save(obj, f):
        f.write(b"half a checkpoint")
        raise OSError("disk full")

    monkeypatch.setattr(torch, "save", broken_save)
    with pytest.raises(OSError, match="disk full"):
        checkpoints.save_checkpoint(path, value=2)
    assert checkpoints.load_checkpoint(path)["value"] == 1  # the old file survives
    assert [p.name for p in tmp_path.iterdir()] == ["ckpt.pt"]  # no temp file left


def test_load_checkpoint_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        checkpoints.load_checkpoint(tmp_path / "missing.pt")


def test_load_or_train_trains_once_then_loads(tmp_path, capsys):
    path: Path = tmp_path / "model.pt"
    calls = []

    def run(model, optimizer, loss_fn, batch):
        calls.append(1)
        return model, fit(model, optimizer, loss_fn, batch, steps=20, progress=False)

    model, optimizer, loss_fn, batch = _problem()
    config = {"steps": 20, "lr": 0.1}
    _, first = loop.load_or_train(path, model, lambda _: run(model, optimizer, loss_fn, batch),
                                  config)
    assert "Trained and saved" in capsys.readouterr().out

    fresh, optimizer2, loss_fn2, batch2 = _problem(seed=9)
    _, again = loop.load_or_train(path, fresh, lambda _: run(fresh, optimizer2, loss_fn2, batch2),
                                  config)
    assert "Loaded" in capsys.readouterr().out
    assert len(calls) == 1 and again == first
    assert torch.equal(fresh.weight, model.weight)

    loop.load_or_train(path, fresh, lambda _: run(fresh, optimizer2, loss_fn2, batch2),
                       {"steps": 20, "lr": 0.2})
    assert "another configuration" in capsys.readouterr().out
    assert len(calls) == 2


def test_load_or_train_prefers_a_matching_shipped_checkpoint(tmp_path, capsys):
    model, optimizer, loss_fn, batch = _problem()
    history = fit(model, optimizer, loss_fn, batch, steps=5, progress=False)
    shipped = checkpoints.save_checkpoint(tmp_path / "shipped.pt", model=model.state_dict(),
                                    history=dict(history), config={"steps": 5})
    fresh = _problem(seed=3)[0]
    loop.load_or_train(tmp_path / "cache.pt", fresh, lambda _: 1 / 0, {"steps": 5},
                       shipped=shipped)
    assert "Loaded" in capsys.readouterr().out
    assert torch.equal(fresh.weight, model.weight)
    assert not (tmp_path / "cache.pt").exists()
    # another run's shipped file (5 steps, not 6) is neither loaded nor touched: this run trains
    before = shipped.read_bytes()
    trained = _problem(seed=4)[0]
    loaded, _ = loop.load_or_train(tmp_path / "cache.pt", _problem(seed=3)[0],
                                   lambda partial: (trained, History()), {"steps": 6},
                                   shipped=shipped)
    assert "Trained and saved" in capsys.readouterr().out
    assert torch.equal(loaded.weight, trained.weight) and not torch.equal(loaded.weight,
                                                                         model.weight)
    assert shipped.read_bytes() == before and (tmp_path / "cache.pt").exists()


def test_checkpoint_paths_separate_cache_and_shipped(monkeypatch, tmp_path):
    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path))
    cache, shipped = checkpoints.checkpoint_paths("vicreg_class")
    assert cache == tmp_path / "checkpoints" / "vicreg_class.pt"
    assert shipped.parent.name == "checkpoints" and shipped.name == "vicreg_class.pt"


# --- safety and durability (damaged, unsafe, unwritable, overwritten files) ---


class _RunsCode:
    """A pickle payload: unpickling it would create ``marker`` (a stand-in for any command)."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def test_a_checkpoint_that_would_run_code_is_refused_and_named(tmp_path):
    marker, path = tmp_path / "ran", tmp_path / "cache" / "model.pt"
    path.parent.mkdir()
    torch.save({"model": {}, "config": {"steps": 20}, "payload": _RunsCode(marker)}, path)
    with pytest.raises(checkpoints.UnsafeCheckpointError, match=f"{path}.*not loaded"):
        checkpoints.load_checkpoint(path)
    model, optimizer, loss_fn, batch = _problem()
    with pytest.raises(checkpoints.UnsafeCheckpointError, match="model.pt"):  # as a notebook loads
        loop.load_or_train(path, model, lambda _: 1 / 0, {"steps": 20})
    assert not marker.exists()


def test_a_failed_final_save_keeps_the_resumable_run(tmp_path, monkeypatch):
    path, partial = tmp_path / "model.pt", tmp_path / "model.partial"
    model, optimizer, loss_fn, batch = _problem()

    def run(checkpoint):
        history = fit(model, optimizer, loss_fn, batch, steps=6, checkpoint=checkpoint,
                      checkpoint_every=3, progress=False)

        def disk_full(*args, **kwargs):
            raise OSError(28, "No space left on device")

        monkeypatch.setattr(checkpoints, "save_checkpoint", disk_full)
        return model, history

    with pytest.warns(UserWarning, match="could not save to .*model.pt .*: the trained model "
                      "lives only in this session.*Set EBJEPA_CACHE"):
        loop.load_or_train(path, model, run, {"steps": 6})
    assert not path.exists()
    assert checkpoints.load_checkpoint(partial)["step"] == 6  # the run is still there to resume


def test_the_partial_file_goes_only_after_the_final_save(tmp_path):
    path, partial = tmp_path / "model.pt", tmp_path / "model.partial"
    model, optimizer, loss_fn, batch = _problem()
    loop.load_or_train(path, model, lambda checkpoint: (model, fit(
        model, optimizer, loss_fn, batch, steps=4, checkpoint=checkpoint, progress=False)),
        {"steps": 4})
    assert path.is_file() and not partial.exists()


def test_an_unwritable_checkpoint_folder_warns_once_and_training_goes_on(tmp_path, monkeypatch):
    def read_only(*args, **kwargs):
        raise OSError(30, "Read-only file system")

    monkeypatch.setattr(tempfile, "mkstemp", read_only)
    model, optimizer, loss_fn, batch = _problem()
    with pytest.warns(UserWarning, match="Read-only") as warned:
        history = fit(model, optimizer, loss_fn, batch, steps=20, checkpoint=tmp_path /
                       "run.pt", checkpoint_every=5, progress=False)
    saves = [str(w.message) for w in warned if "could not save" in str(w.message)]
    assert len(saves) == 1 and "an interruption will not be resumable" in saves[0]
    assert len(history["loss"]) == 20 and history.last("loss") < 1e-3


@pytest.mark.parametrize("damage", ["empty", "truncated", "not a checkpoint"])
def test_a_damaged_checkpoint_is_named_moved_aside_and_retrained(tmp_path, damage, capsys):
    path = tmp_path / "model.pt"
    model, optimizer, loss_fn, batch = _problem()
    checkpoints.save_checkpoint(path, model=model.state_dict(), history={}, config={"steps": 3})
    data = path.read_bytes()
    path.write_bytes({"empty": b"", "truncated": data[: len(data) // 2],
                      "not a checkpoint": b"hello"}[damage])
    with pytest.raises(checkpoints.CheckpointError, match=f"{path} is damaged"):
        checkpoints.load_checkpoint(path)
    def run(_):
        return model, fit(model, optimizer, loss_fn, batch, steps=3, progress=False)

    loop.load_or_train(path, model, run, {"steps": 3})
    out = capsys.readouterr().out
    assert "is damaged; moved it to" in out and "Trained and saved" in out
    assert (tmp_path / "model.pt.damaged").is_file()
    assert checkpoints.load_checkpoint(path)["config"] == {"steps": 3}  # the next run loads it


def test_a_damaged_shipped_checkpoint_is_reported_and_left_in_place(tmp_path):
    shipped = tmp_path / "shipped.pt"
    shipped.write_bytes(b"version https://git-lfs.github.com/spec/v1\n")  # an LFS pointer
    model, optimizer, loss_fn, batch = _problem()
    def run(_):
        return model, fit(model, optimizer, loss_fn, batch, steps=3, progress=False)

    with pytest.warns(UserWarning, match=r"shipped.pt is damaged.*restore it with `git "
                                         r"checkout -- .*shipped.pt`"):
        loop.load_or_train(tmp_path / "cache.pt", model, run, {"steps": 3}, shipped=shipped)
    assert shipped.is_file() and (tmp_path / "cache.pt").is_file()


def test_another_runs_checkpoint_is_kept_and_found_again(tmp_path, capsys):
    path = tmp_path / "model.pt"
    calls = []

    def run(steps):
        def train_it(_):
            calls.append(steps)
            return model, fit(model, optimizer, loss_fn, batch, steps=steps, progress=False)

        model, optimizer, loss_fn, batch = _problem()
        return train_it

    model = _problem()[0]
    loop.load_or_train(path, model, run(3), {"steps": 3})
    loop.load_or_train(path, model, run(5), {"steps": 5})
    kept = checkpoints.kept_path(path, {"steps": 3})
    assert f"moved it to {kept}" in capsys.readouterr().out
    assert checkpoints.load_checkpoint(kept)["config"] == {"steps": 3}
    assert checkpoints.load_checkpoint(path)["config"] == {"steps": 5}
    loop.load_or_train(path, model, run(3), {"steps": 3})  # back to the first config
    assert calls == [3, 5]  # found again, not retrained
    assert checkpoints.load_checkpoint(path)["config"] == {"steps": 3}
    kept_five = checkpoints.kept_path(path, {"steps": 5})
    assert checkpoints.load_checkpoint(kept_five)["config"] == {"steps": 5}


def test_stale_temporaries_of_killed_writers_are_removed(tmp_path):
    path = tmp_path / "run.partial"
    stale, fresh = tmp_path / ".run.partial.ab12.part", tmp_path / ".run.partial.cd34.part"
    other = tmp_path / ".notes.ab12.part"
    for file in (stale, fresh, other):
        file.write_bytes(b"x" * 10)
    old = stale.stat().st_mtime - 2 * 3600  # older than remove_stale_temporaries' hour
    os.utime(stale, (old, old))
    os.utime(other, (old, old))
    checkpoints.save_checkpoint(path, value=1)
    assert not stale.exists() and fresh.exists() and other.exists()


def test_training_time_adds_up_over_resumed_parts(tmp_path):
    ckpt = tmp_path / "run.pt"
    model, optimizer, loss_fn, batch = _problem()
    first = fit(model, optimizer, loss_fn, batch, steps=5, checkpoint=ckpt, progress=False)
    step, history = loop.resume(ckpt, model, optimizer)
    assert history.seconds == pytest.approx(first.seconds) and first.seconds > 0
    history = fit(model, optimizer, loss_fn, batch, steps=10, checkpoint=ckpt, progress=False)
    assert history.seconds > first.seconds
    assert checkpoints.load_checkpoint(ckpt)["seconds"] == pytest.approx(history.seconds)


def test_the_shipped_checkpoints_are_found_beside_the_package():
    assert checkpoints.checkpoint_paths("world_model_class")[1].is_file()


def test_an_infinite_loss_stops_with_a_clear_error():
    """An overflowing loss (inf, not NaN) stops the run too: one more step would fill the
    weights with NaN."""
    model, optimizer, _, batch = _problem()

    def inf_loss(xy):
        return model(xy[0]).sum() * 0 + float("inf"), {"term": 2.0}

    with pytest.raises(FloatingPointError, match="became inf at step 0"):
        fit(model, optimizer, inf_loss, batch, steps=3, progress=False)


def test_step_generators_of_other_seeds_draw_other_batches():
    """Each (seed, step) pair draws a batch of its own: a run with another seed never replays
    this run's batches a few steps apart; the same pair draws the same batch again."""
    draws = {(seed, step): tuple(torch.rand(4, generator=loop.step_generator(seed, step)).tolist())
             for seed in range(4) for step in range(50)}
    assert len(set(draws.values())) == len(draws)
    again = torch.rand(4, generator=loop.step_generator(3, 7))
    assert tuple(again.tolist()) == draws[3, 7]


def test_a_kept_run_is_found_again_whatever_the_order_of_its_identity(tmp_path, capsys):
    """A run moved aside is found again by its identity's content, not by the order its keys
    were written in (a config rebuilt with its fields in another order is the same run)."""
    path = tmp_path / "model.pt"
    written = {"steps": 3, "lr": 0.1, "model": {"width": 4, "depth": 2}}
    reordered = {"model": {"depth": 2, "width": 4}, "lr": 0.1, "steps": 3}
    checkpoints.save_checkpoint(checkpoints.kept_path(path, written), model={}, config=written)
    found = checkpoints.find_run(path, reordered, "cpu")
    assert found is not None and found[0]["config"] == written and found[1] == path
    assert "moved it back" in capsys.readouterr().out and path.is_file()
    assert checkpoints.kept_path(path, written) != checkpoints.kept_path(path, {**written,
                                                                               "lr": 0.2})


CELL = '''
def inner(x):
    return x + 1

def middle(x):
    return inner(x)

def step(x):
    return middle(x)

def step_in_a_lambda(xs):
    return list(map(lambda x: inner(x), xs))
'''


def _notebook_cell(source: str) -> dict:
    """The functions ``source`` defines, as a notebook cell would: in ``__main__``, source
    readable by ``inspect``."""
    filename = f"<cell {abs(hash(source))}>"
    linecache.cache[filename] = (len(source), None, source.splitlines(True), filename)
    space = {"__name__": "__main__"}
    exec(compile(source, filename, "exec"), space)
    return space


def test_an_unchecked_edit_is_seen_through_helpers_and_lambdas():
    """A run's identity holds every notebook function its step reads, also through another
    helper or inside a lambda: an edit there is a run of its own, which never loads the
    unedited run's checkpoint."""
    cell, edited = _notebook_cell(CELL), _notebook_cell(CELL.replace("x + 1", "x + 2"))

    def identity(space, name):
        return checkpoints.step_identity(space[name], space[name]).get("calls", {})

    assert set(identity(cell, "step")) == {"middle", "inner"}
    assert identity(cell, "step") != identity(edited, "step")
    assert set(identity(cell, "step_in_a_lambda")) == {"inner"}
    assert identity(cell, "step_in_a_lambda") != identity(edited, "step_in_a_lambda")
