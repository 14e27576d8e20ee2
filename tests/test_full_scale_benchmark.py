"""What the GPU session (``research/benchmarks/gpu_session.sh``) runs works here first: a
GPU's minutes are too few to find out there. ``research.benchmarks.full_scale`` ends with the
line the session parses; the image command takes a warm-up short enough for a short run of
the full preset."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from research import launch, train_image

ROOT = Path(__file__).resolve().parents[1]
CHAPTERS = ("image", "sigreg", "video", "world")


@pytest.mark.slow
def test_full_scale_benchmark_times_a_step_and_prints_a_parseable_last_line():
    # two chapters of different training functions, at batch 2 (the video and ViT-S steps
    # take seconds each on one core); the others are left out and read nan. A step is timed as
    # T(warmup + steps) - T(warmup): 4 steps, so that a busy CI core's noise in building the
    # model (a 1-step difference read 0 s there) stays below the steps' own time
    command = [sys.executable, "-m", "research.benchmarks.full_scale", "--device", "cpu",
               "--threads", "1", "--batch", "2", "--steps", "4", "--warmup", "1",
               "--only", "image", "world"]
    environment = {**os.environ, "OMP_NUM_THREADS": "1", "OMP_WAIT_POLICY": "PASSIVE"}
    done = subprocess.run(command, cwd=ROOT, env=environment, capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.strip().splitlines()
    assert any("projected" in line for line in lines)  # the paper's schedule, never "measured"
    fields = dict(pair.split("=") for pair in lines[-1].split())
    assert fields["device"] == "cpu" and fields["ranks"] == "1"
    assert set(fields) == {"device", "ranks", *(f"{c}_s_per_step" for c in CHAPTERS)}
    for chapter in CHAPTERS:
        seconds = float(fields[f"{chapter}_s_per_step"])
        if chapter in ("image", "world"):
            assert math.isfinite(seconds) and seconds > 0, (chapter, seconds)
        else:
            assert math.isnan(seconds), (chapter, seconds)


def test_a_short_full_image_run_takes_a_shorter_warmup(monkeypatch, capsys):
    for name in launch.TORCHRUN_ENV:
        monkeypatch.delenv(name, raising=False)
    ran = []
    monkeypatch.setattr(train_image, "_train_and_save", lambda args, sizes, config, device:
                        ran.append(config))
    train_image.main(["--scale", "full", "--steps", "300", "--warmup-steps", "10", "--out", "x"])
    assert (ran[0].steps, ran[0].warmup_steps) == (300, 10)
    with pytest.raises(SystemExit):  # the preset's 1,950 warm-up steps do not fit in 300
        train_image.main(["--scale", "full", "--steps", "300", "--out", "x"])
    assert "warmup_steps" in capsys.readouterr().err


def test_a_step_the_noise_outweighed_reads_not_measured_rather_than_zero_seconds():
    from research.benchmarks import full_scale

    line = full_scale.row("image", None, 2, math.nan, math.nan, set())
    assert line.startswith("image       2  not measured") and "more --steps" in line
