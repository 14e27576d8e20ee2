"""Notebook 02's sweeps: the plan of runs (research.sweep), the JSON file they are stored in,
resuming, and the shipped file the notebook reads (evaluation.sweeps)."""

import dataclasses
import json
from dataclasses import asdict

import pytest
import torch
from torch import nn

from ebjepa_tutorial.course import reference
from ebjepa_tutorial.course.presets import preset
from ebjepa_tutorial.evaluation.sweeps import SWEEP_LABELS, load_sweeps, shorten, tenfold_costs
from ebjepa_tutorial.training.checkpoints import SHIPPED_DIR
from ebjepa_tutorial.training.image import ImageJEPAConfig, SIGReg, VICReg
from research import sweep

TINY = ImageJEPAConfig(loss=SIGReg(slices=8), widths=(4, 4, 4, 4), projector=(8, 8),
                       batch_size=8, steps=2, warmup_steps=0)


def _data(n, seed):
    g = torch.Generator().manual_seed(seed)
    images = torch.randint(0, 256, (n, 3, 32, 32), generator=g, dtype=torch.uint8)
    return images, torch.arange(n) % 10


def _unique(runs):
    return {sweep.key(run.config, 0, 0) for run in runs}


def test_class_plan_sweeps_each_coefficient_alone():
    plan = sweep.sweep_plan("class")
    sensitivity, projector = plan["sensitivity"], plan["projector"]
    assert len(sensitivity) == 3 * len(sweep.FACTORS["class"]) and len(projector) == 8
    steps = preset("02", "class").sweep_steps
    for run in sensitivity + projector:
        assert run.config.steps == steps and run.config.warmup_steps <= steps // 10
    lambdas = [r for r in sensitivity if r.sweep == "sigreg_lambda"]
    assert [r.config.loss.lam for r in lambdas] == [0.0005, 0.005, 0.05, 0.5, 5.0]
    assert all(isinstance(r.config.loss, SIGReg) for r in lambdas)
    vicreg = preset("01", "class").config  # each VICReg weight is swept around its default
    covs = [r for r in sensitivity if r.sweep == "cov_coeff"]
    assert [r.config.loss.cov_coeff for r in covs] == pytest.approx(
        [f * vicreg.loss.cov_coeff for f in sweep.FACTORS["class"]])
    assert all(isinstance(r.config.loss, VICReg)
               and r.config.loss.std_coeff == vicreg.loss.std_coeff for r in covs)
    assert [r.config.projector for r in projector[:4]] == [None, (1024, 64), (1024, 256),
                                                           (1024, 1024)]
    # the default VICReg run is shared by the two VICReg sweeps, the defaults by both plans
    assert len(_unique(sensitivity)) == len(sensitivity) - 1
    assert len(_unique(sensitivity + projector)) == 20


def test_ci_plan_is_small():
    plan = sweep.sweep_plan("ci")
    assert len(_unique(plan["sensitivity"] + plan["projector"])) <= 11
    assert [r.value for r in plan["projector"]] == [None, 16, None, 16]  # SIGReg's own output


def test_run_sweep_writes_each_run_and_reloads_instead_of_training(tmp_path, monkeypatch):
    train, test = _data(48, 0), _data(20, 1)
    vicreg = dataclasses.replace(TINY, loss=VICReg())
    runs = sweep.sensitivity_runs(TINY, vicreg, (0.5, 2.0))[:2]  # two lambdas
    path = tmp_path / "sweep.json"
    rows = sweep.run_sweep(runs, train, test, path=path, progress=False)
    assert [r["value"] for r in rows] == [0.05, 0.2]
    assert all(0.0 <= r["probe_acc"] <= 1.0 and 0.0 <= r["knn_acc"] <= 1.0 for r in rows)
    stored = json.loads(path.read_text())
    assert len(stored["runs"]) == 2 and "32-px images" in stored["protocol"]
    assert all(row["config"]["eval_image_size"] == 32 for row in stored["runs"])

    def no_training(*args, **kwargs):
        raise AssertionError("a stored run was trained again")

    monkeypatch.setattr(sweep, "train_and_probe", no_training)
    again = sweep.run_sweep(runs, train, test, path=path, progress=False)
    assert [r["probe_acc"] for r in again] == [r["probe_acc"] for r in rows]
    # a stored row is relabelled for the sweep that asks for it
    relabelled = sweep.Run("other_sweep", 7, runs[0].config)
    assert sweep.run_sweep([relabelled], train, test, path=path)[0]["sweep"] == "other_sweep"


def _record_training(monkeypatch) -> list:
    """Replace training by a stub that records each run it is asked for; returns the record."""
    calls = []

    def fake(run, train, test, device="cpu", progress=True):
        calls.append(run)
        return {"probe_acc": 0.5, "knn_acc": 0.5, "seconds": 0.0, "n_train": len(train[0]),
                "n_test": len(test[0]), "config": asdict(run.config)}

    monkeypatch.setattr(sweep, "train_and_probe", fake)
    return calls


def test_rows_of_other_data_sizes_are_not_reused(tmp_path, monkeypatch):
    path = tmp_path / "sweep.json"
    runs = [sweep.Run("sigreg_lambda", 0.1, TINY, 1.0)]
    sweep.run_sweep(runs, _data(48, 0), _data(20, 1), path=path, progress=False)
    calls = _record_training(monkeypatch)
    sweep.run_sweep(runs, _data(40, 0), _data(20, 1), path=path, progress=False)
    assert len(calls) == 1
    assert len(sweep.load_results(path)) == 2


def test_a_run_two_sweeps_share_is_trained_once_and_not_counted_as_found(tmp_path, monkeypatch,
                                                                         capsys):
    calls = []

    def fake(run, train, test, device="cpu", progress=True):  # a row stored as the real one is
        calls.append(run)
        return {"probe_acc": 0.5, "knn_acc": 0.5, "seconds": 0.0, "n_train": len(train[0]),
                "n_test": len(test[0]), "config": sweep.run_identity(run.config)}

    monkeypatch.setattr(sweep, "train_and_probe", fake)
    shared = [sweep.Run("sigreg_lambda", 0.1, TINY, 1.0), sweep.Run("other", 7, TINY, 1.0)]
    path, train, test = tmp_path / "sweep.json", _data(48, 0), _data(20, 1)
    sweep.run_sweep(shared, train, test, path=path, progress=False)
    assert len(calls) == 1
    assert "0 of 2 runs found in" in capsys.readouterr().out  # nothing was stored before
    sweep.run_sweep(shared, train, test, path=path, progress=False)
    assert "2 of 2 runs found in" in capsys.readouterr().out and len(calls) == 1


def test_rows_probed_at_another_size_are_not_reused(tmp_path, monkeypatch):
    path = tmp_path / "sweep.json"
    train, test = _data(48, 0), _data(20, 1)
    sweep.run_sweep([sweep.Run("sigreg_lambda", 0.1, TINY, 1.0)], train, test, path=path,
                     progress=False)
    calls = _record_training(monkeypatch)
    at_16 = dataclasses.replace(TINY, eval_image_size=16)
    sweep.run_sweep([sweep.Run("sigreg_lambda", 0.1, at_16, 1.0)], train, test, path=path,
                     progress=False)
    assert [run.config.eval_image_size for run in calls] == [16]


def test_sweep_runs_are_probed_at_eval_image_size(monkeypatch):
    class Recorder(nn.Module):  # a stand-in for the trained encoder: keeps its input shapes
        def __init__(self):
            super().__init__()
            self.linear, self.shapes = nn.Linear(3, 4), []

        def forward(self, x):
            self.shapes.append(tuple(x.shape[1:]))
            return self.linear(x.mean(dim=(2, 3)))

    encoder = Recorder()
    model = nn.Module()
    model.encoder = encoder
    monkeypatch.setattr(sweep, "train_image_jepa", lambda *a, **k: (model, {"loss": [1.0]}))
    for size in (32, 24):
        encoder.shapes.clear()
        run = sweep.Run("sigreg_lambda", 0.1, dataclasses.replace(TINY, eval_image_size=size))
        row = sweep.train_and_probe(run, _data(40, 0), _data(20, 1), progress=False)
        assert set(encoder.shapes) == {(3, size, size)}
        assert row["config"]["eval_image_size"] == size


def test_command_trains_each_config_once_and_stores_every_run_in_plan_order(tmp_path,
                                                                           monkeypatch):
    monkeypatch.setattr(sweep, "load_cifar10", lambda split: _data(30, 0))
    calls = _record_training(monkeypatch)
    out = tmp_path / "sweeps_ci.json"
    sweep.main(["--scale", "ci", "--out", str(out)])
    plan = [run for group in sweep.sweep_plan("ci").values() for run in group]
    assert len(calls) == len(_unique(plan)) < len(plan)  # shared defaults trained once
    size = preset("02", "ci").config.eval_image_size
    assert all(run.config.eval_image_size == size for run in calls)
    meta, rows = load_sweeps(out)
    assert f"{size}-px images" in meta["protocol"] and meta["command"].endswith(str(out))
    stored = rows["sensitivity"] + rows["projector"]
    assert [(r["sweep"], r["value"]) for r in stored] == [(r.sweep, r.value) for r in plan]
    assert all(r["n_train"] == r["n_test"] == 30 for r in stored)


def test_the_shipped_file_holds_every_run_of_notebook_02():
    cfg = preset("02", "class")
    runs = [run for group in sweep.sweep_plan("class").values() for run in group]
    path = SHIPPED_DIR / "sweeps_class.json"
    assert path.is_file(), f"{path} is documented in checkpoints/README.md but missing"
    stored = [sweep.key(row["config"], row["n_train"], row["n_test"])
              for row in sweep.load_results(path)]
    assert stored == [sweep.key(run.config, cfg.train_images, cfg.test_images) for run in runs]
    meta, rows = load_sweeps(path)
    assert meta["scale"] == "class" and [len(rows[name]) for name in rows] == [15, 8]
    assert [(r["sweep"], r["value"], r["factor"]) for r in rows["sensitivity"] + rows["projector"]
            ] == [(run.sweep, run.value, run.factor) for run in runs]
    defaults = [r for r in rows["sensitivity"] if r["factor"] == 1.0]
    assert defaults[1]["probe_acc"] == defaults[2]["probe_acc"]  # VICReg's default, run once


def test_bad_scale_is_refused():
    with pytest.raises(SystemExit):
        sweep.main(["--scale", "huge", "--out", "x.json"])


def test_tenfold_costs_take_the_points_lost_at_a_tenth_and_ten_times_each_default():
    rows = [{"sweep": sweep_name, "factor": factor, "probe_acc": acc}
            for sweep_name, accs in (("sigreg_lambda", (0.1, 0.40, 0.50, 0.45, 0.2)),
                                     ("std_coeff", (0.1, 0.30, 0.60, 0.58, 0.1)),
                                     ("cov_coeff", (0.1, 0.59, 0.60, 0.50, 0.1)))
            for factor, acc in zip((0.01, 0.1, 1.0, 10.0, 100.0), accs)]
    costs = tenfold_costs(rows)  # a hundredfold either side is not counted
    assert costs["SIGReg"] == pytest.approx((5.0, 10.0))
    assert costs["VICReg"] == pytest.approx((1.0, 30.0))  # over both of VICReg's weights


def test_shorten_cuts_the_steps_and_keeps_a_warm_up_of_at_most_a_tenth():
    """A run cut to 1000 steps keeps its own warm-up when that is shorter than a tenth of
    them (50 stays 50, 0 stays 0), and a longer one is cut to the tenth (500 -> 100)."""
    short = shorten(dataclasses.replace(TINY, steps=5000, warmup_steps=50), 1000)
    assert (short.steps, short.warmup_steps) == (1000, 50)
    long_warm_up = dataclasses.replace(TINY, steps=5000, warmup_steps=500)
    assert shorten(long_warm_up, 1000).warmup_steps == 100
    assert shorten(TINY, 1000).warmup_steps == 0


def test_each_sweep_label_names_the_loss_and_the_weight_its_runs_vary():
    """Notebook 02 labels its axes and printout with ``SWEEP_LABELS``: each label names the
    loss the sweep's runs train with and, for a sensitivity sweep, the one weight of that
    loss the runs vary (VICReg's two weights swapped would mislabel both curves)."""
    plan = sweep.sweep_plan("class")
    terms = {"lam": "lambda", "std_coeff": "variance weight", "cov_coeff": "covariance weight"}
    for family in ("sensitivity", "projector"):
        for name in {run.sweep for run in plan[family]}:
            losses = [run.config.loss for run in plan[family] if run.sweep == name]
            label = SWEEP_LABELS[name]
            assert label.split(":")[0] == type(losses[0]).__name__, name
            varied = [terms[field.name] for field in dataclasses.fields(losses[0])
                      if len({getattr(loss, field.name) for loss in losses}) > 1]
            assert varied == ([] if family == "projector" else [label.split(": ")[1]]), name


def test_the_recorded_tenfold_costs_are_those_of_the_shipped_sweep():
    _, rows = load_sweeps(SHIPPED_DIR / "sweeps_class.json")
    recorded = reference.load()
    for method, (low, high) in tenfold_costs(rows["sensitivity"]).items():
        entry = recorded[f"sweep_{method.lower()}_tenfold_points"]  # what the pages print
        assert entry["spread"] == pytest.approx([low, high])
        assert entry["value"] == pytest.approx(high)


def test_record_stores_the_shipped_sweeps_tenfold_costs_and_refuses_other_scales(monkeypatch):
    stored = {}
    monkeypatch.setattr(sweep.figures, "record", lambda key, value, command, protocol, threads,
                        spread: stored.update({key: (value, spread, command)}))
    sweep.record_tenfold_costs(SHIPPED_DIR / "sweeps_class.json", "the command")
    _, rows = load_sweeps(SHIPPED_DIR / "sweeps_class.json")
    assert stored == {f"sweep_{method.lower()}_tenfold_points": (high, (low, high), "the command")
                      for method, (low, high) in tenfold_costs(rows["sensitivity"]).items()}
    with pytest.raises(SystemExit):  # before any data is read or any run trains
        sweep.main(["--scale", "ci", "--out", "x.json", "--record"])
