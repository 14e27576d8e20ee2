"""Chapter 03 at the paper's scale: clips per second and mAP after each epoch (for a GPU).

    python -m research.benchmarks.video_full [--epochs 3] [--budget SECONDS] [--scale full]

Trains notebook 03's ``full`` preset (K = 4, seed 0: the paper's 18,000 clips of 10 frames,
batch 64, Adam at a constant 1e-3) and, after each epoch, scores it by the notebook's
protocol at that scale (detection probe on frozen latents, AP per horizon on clips of
held-out digits). The rate is constant, so the first epochs of this run are the first
epochs of the paper's 50. It starts no epoch that the mean epoch time so far (evaluation
included) predicts would end past ``--budget`` seconds. ``--scale ci`` runs the same on the ci
preset, to test this script on a CPU.
Needs the MNIST test digits (``EBJEPA_DATA``). Last line:
``epochs=... clips_per_s=... map=... ap3=...`` (ap3: AP three steps ahead).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace

from ebjepa_tutorial.course.presets import preset
from ebjepa_tutorial.data.mnist import load_mnist
from ebjepa_tutorial.data.moving_mnist import split_digits
from ebjepa_tutorial.evaluation.detection import detection_report, evaluation_clips
from ebjepa_tutorial.training.video import make_clips, video_jepa_step
from ebjepa_tutorial.utils import get_device
from research.train_video import notebook


class _OutOfTime(Exception):
    """Raised at an epoch's end when the next epoch would start past the budget."""


class EpochReport:
    """``after`` for ``train_video_jepa``: at each epoch's end, times and scores the model."""

    def __init__(self, steps_per_epoch: int, cfg, probe_data, eval_data, budget: float):
        self.steps_per_epoch, self.cfg, self.budget = steps_per_epoch, cfg, budget
        self.probe_data, self.eval_data = probe_data, eval_data
        self.started = self.epoch_started = time.perf_counter()
        self.last = None

    def __call__(self, done: int, parts, history) -> None:
        if done % self.steps_per_epoch:
            return
        model, epoch, trained = parts[0], done // self.steps_per_epoch, time.perf_counter()
        clips_per_s = self.steps_per_epoch * self.cfg.train.batch_size / (
            trained - self.epoch_started)
        report = detection_report(model, self.probe_data, self.eval_data, self.cfg.horizons,
                                  self.cfg.probe_steps)
        model.train()
        aps = " ".join(f"{ap:.3f}" for ap in report["ap"].tolist())
        self.last = (epoch, clips_per_s, report["map"], float(report["ap"][2]))
        print(f"epoch {epoch}: {clips_per_s:.0f} clips/s training, mAP {report['map']:.3f} "
              f"(AP {aps}; true encodings {report['map_encoded']:.3f}), evaluated in "
              f"{time.perf_counter() - trained:.0f} s", flush=True)
        self.epoch_started = time.perf_counter()
        per_epoch = (self.epoch_started - self.started) / epoch
        if self.epoch_started - self.started + per_epoch > self.budget:
            raise _OutOfTime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--epochs", type=int, default=3)
    parser.add_argument("--budget", type=float, default=float("inf"),
                        help="wall seconds; no epoch starts that would end past it")
    parser.add_argument("--scale", default="full", choices=("ci", "full"))
    args = parser.parse_args()
    cfg = preset("03", args.scale)
    steps_per_epoch = max(1, cfg.train.n_clips // cfg.train.batch_size)
    config = replace(cfg.train, steps=args.epochs * steps_per_epoch)
    device = get_device()
    train_digits, held_out = split_digits(load_mnist("test", download=False)[0],
                                          n_train=cfg.n_train_digits)
    probe_data, eval_data = evaluation_clips(train_digits, held_out, cfg.n_probe, cfg.n_eval,
                                             config.n_frames)
    clips = make_clips(config, train_digits)
    print(f"{args.scale} preset on {device}: {len(clips)} clips, batch {config.batch_size}, "
          f"{steps_per_epoch} steps an epoch, at most {args.epochs} epochs; probe "
          f"{cfg.n_probe} clips ({cfg.probe_steps} steps), AP on {cfg.n_eval} clips of "
          f"{len(held_out)} held-out digits", flush=True)
    report = EpochReport(steps_per_epoch, cfg, probe_data, eval_data, args.budget)
    try:
        notebook().train_video_jepa(config, clips, video_jepa_step, device=device, after=report)
    except _OutOfTime:
        pass
    epoch, clips_per_s, mean_ap, ap3 = report.last or (0, float("nan"), float("nan"),
                                                       float("nan"))
    print(f"epochs={epoch} clips_per_s={clips_per_s:.1f} map={mean_ap:.3f} ap3={ap3:.3f}")


if __name__ == "__main__":
    main()
