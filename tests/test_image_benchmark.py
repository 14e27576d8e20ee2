"""``research.benchmarks.image_jepa``: the last line scripts parse, the seed it trains, what
--record refuses (chapters 01-02's class target is measured by this script)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from test_data import shared_data

ROOT = Path(__file__).resolve().parents[1]


def _benchmark(*arguments: str) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "research.benchmarks.image_jepa", *arguments]
    environment = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run(command, cwd=ROOT, env=environment, capture_output=True, text=True,
                          timeout=300)


def test_record_refuses_a_run_that_is_not_the_class_recipe(monkeypatch, capsys):
    from research.benchmarks import image_jepa  # in this process: a subprocess costs seconds

    monkeypatch.setattr(sys, "argv", ["image_jepa", "--record", "--seed", "1"])
    with pytest.raises(SystemExit) as done:
        image_jepa.main()
    assert done.value.code == 2  # before any data is read or anything trains
    assert "drop --scale, --steps, --eval-size, --seed" in capsys.readouterr().err


def test_split_record_refuses_a_step_that_is_not_vicregs(monkeypatch, capsys):
    from research.benchmarks import image_jepa

    # the pages state image_float32_step_ratio as a VICReg step's: SIGReg's would overwrite it
    monkeypatch.setattr(image_jepa, "load_cifar10", lambda split: pytest.fail("data read"))
    monkeypatch.setattr(sys, "argv", ["image_jepa", "--split", "--record", "--loss", "sigreg"])
    with pytest.raises(SystemExit) as done:
        image_jepa.main()
    assert done.value.code == 2  # before any data is read
    assert "ratio of a VICReg step" in capsys.readouterr().err


@pytest.mark.slow  # trains 3 steps at ci scale and probes twice on real CIFAR-10: seconds
def test_a_short_run_trains_the_seed_asked_for_and_ends_with_a_parseable_line():
    shared_data()  # the benchmark reads CIFAR-10: skip without a copy
    done = _benchmark("--scale", "ci", "--loss", "sigreg", "--steps", "3", "--seed", "1",
                      "--threads", "1")
    assert done.returncode == 0, done.stderr[-2000:]
    lines = done.stdout.strip().splitlines()
    assert "seed=1" in lines[0] and "steps=3" in lines[0]  # the config it trained
    fields = dict(pair.split("=") for pair in lines[-1].split())
    assert set(fields) == {"images_per_s", "minutes", "probe_acc", "knn_acc"}
    assert float(fields["images_per_s"]) > 0
    assert 0.0 <= float(fields["probe_acc"]) <= 1.0 and 0.0 <= float(fields["knn_acc"]) <= 1.0


def test_split_times_float32_against_bf16_and_records_the_median_ratio(monkeypatch, capsys):
    from argparse import Namespace

    from ebjepa_tutorial.course.presets import image_preset
    from research.benchmarks import image_jepa

    # step_split's parts per call: bf16 steps take 1 s, float32 steps 1.5, 2 and 4 s in turn
    float32_seconds = iter([1.5, 2.0, 4.0])
    monkeypatch.setattr(image_jepa, "step_split", lambda config, images, bf16=True: {
        "forward": 0.25, "backward": 0.75} if bf16 else {"all": next(float32_seconds)})
    monkeypatch.setattr(image_jepa, "precision_name", lambda device, cpu=False: "bf16 autocast")
    recorded = {}
    monkeypatch.setattr(image_jepa.figures, "record",
                        lambda key, value, *where, spread: recorded.update({key: (value, spread)}))
    args = Namespace(record=True, loss="vicreg", threads=2)
    config = image_preset("ci", "vicreg").config
    image_jepa.split_and_precision(config, None, args, rounds=3)
    assert "float32 step / bf16 step: 2.00 (pairs: 1.50, 2.00, 4.00)" in capsys.readouterr().out
    assert recorded == {"image_float32_step_ratio": (2.0, (1.5, 4.0))}
    # a CPU without bf16 has nothing to compare: it says so and records nothing
    monkeypatch.setattr(image_jepa, "precision_name", lambda device, cpu=False: "float32")
    recorded.clear()
    image_jepa.split_and_precision(config, None, args)
    assert "computes the networks in float32 only" in capsys.readouterr().out and not recorded


def test_the_untrained_encoders_figure_is_recorded_as_untrained(monkeypatch):
    """The random-init probe is stored with a protocol of its own: an encoder at its initial
    weights, not the trained run's "1600 steps ... trained on 16-px views"."""
    from research.benchmarks import image_jepa

    recorded = _fake_run(monkeypatch, image_jepa, "bf16 autocast")
    image_jepa.main()
    assert recorded["vicreg_probe_acc"].startswith("1600 steps in ")
    assert "trained on 16-px views" in recorded["vicreg_probe_acc"]
    untrained = recorded["vicreg_random_init_probe_acc"]
    assert untrained.startswith("no training: the class encoder at its initial weights")
    assert "steps" not in untrained and "trained on" not in untrained


def test_a_cpu_without_bf16_records_its_float32_minutes_and_keeps_the_bf16_figures(monkeypatch):
    """The pages state the class figures of bf16 runs: a float32 run stores its own minutes
    (and its accuracy in their protocol) under a key of its own, and nothing else."""
    from research.benchmarks import image_jepa

    recorded = _fake_run(monkeypatch, image_jepa, "float32")
    image_jepa.main()
    assert list(recorded) == ["vicreg_float32_train_min"]
    assert recorded["vicreg_float32_train_min"].startswith("1600 steps in float32 (this CPU")
    assert "50.00% (kNN 40.00%)" in recorded["vicreg_float32_train_min"]


def _fake_run(monkeypatch, image_jepa, precision: str) -> dict:
    """``image_jepa.main`` with ``--record`` made instant: no data, training or probe (scores
    0.5 and 0.4), networks in ``precision``; returns the dict its figures' protocols go to."""
    from types import SimpleNamespace

    monkeypatch.setattr(sys, "argv", ["image_jepa", "--record"])
    monkeypatch.setattr(image_jepa.torch, "set_num_threads", lambda n: None)  # this worker's
    monkeypatch.setattr(image_jepa, "precision_name", lambda device, cpu=False: precision)
    monkeypatch.setattr(image_jepa, "load_cifar10", lambda split: (None, None))
    monkeypatch.setattr(image_jepa, "random_subset", lambda images, labels, n: (images, labels))
    monkeypatch.setattr(image_jepa, "probe_encoder",
                        lambda encoder, config, train, test: {"probe_acc": 0.5, "knn_acc": 0.4})
    monkeypatch.setattr(image_jepa, "train_image_jepa",
                        lambda config, images: (SimpleNamespace(encoder=None), None))
    recorded = {}
    monkeypatch.setattr(image_jepa.figures, "record",
                        lambda key, value, **where: recorded.update({key: where["protocol"]}))
    return recorded
