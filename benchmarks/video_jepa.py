"""Chapter 03 benchmark: Moving MNIST generation speed, video JEPA training speed and mAP.

    python benchmarks/video_jepa.py [--clips 4000] [--frames 10] [--repeats 5] [--threads 2]
                                    [--train-steps 100] [--batch 16] [--eval-clips 500] [--split]

Prints one line per generator repeat, the time of one class-scale training
step at batch 64 and at ``--batch``, a short training run (``--train-steps``
of the class config at ``--batch``) and its detection mAP over horizons 1-7
on clips of held-out digits (with the random-init model's mAP beside it),
then a last line ``clips_per_s=... train_clips_per_s=... map=...`` that
scripts can parse. ``--train-steps 0`` skips the model part (``nan``). Uses
the MNIST test digits when they are on disk (``load_mnist("test",
download=False)``), else random digits with a note: the generator's speed
does not depend on what the digits look like (the mAP does). ``--split``
first prints where one class-scale step's time goes (encoder, rollout,
projector and regulariser, backward, optimiser).
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace

import torch

from ebjepa_tutorial.data.mnist import load_mnist
from ebjepa_tutorial.data.moving_mnist import generate_moving_mnist, split_digits
from ebjepa_tutorial.data.paths import DataNotFoundError
from ebjepa_tutorial.evaluation.detection import detection_report
from ebjepa_tutorial.losses import variance_and_covariance
from ebjepa_tutorial.losses.rollout import rollout_loss
from ebjepa_tutorial.models.video import VideoJEPA
from ebjepa_tutorial.training.video import VIDEO_CONFIGS, train_video_jepa, video_jepa_loss
from ebjepa_tutorial.utils import print_parts, time_parts


def load_digits() -> torch.Tensor:
    """The 10,000 MNIST test digits (N, 1, 28, 28) uint8, or random stand-ins if absent."""
    try:
        return load_mnist("test", download=False)[0]
    except DataNotFoundError:
        print("MNIST not found (see data/README.md); timing with random digits instead")
        return torch.randint(0, 256, (10_000, 1, 28, 28), dtype=torch.uint8)


def time_generator(digits: torch.Tensor, clips: int, frames: int, seed: int) -> float:
    """Clips per second for one call of ``generate_moving_mnist`` (2 digits, 64x64)."""
    start = time.perf_counter()
    batch = generate_moving_mnist(digits, n_clips=clips, n_frames=frames, seed=seed)
    elapsed = time.perf_counter() - start
    assert batch.clips.shape == (clips, frames, 1, 64, 64)
    return clips / elapsed


def time_step(batch_size: int, repeats: int = 3) -> float:
    """Seconds of one class-scale training step on ``batch_size`` clips of 10 frames (best of)."""
    config = replace(VIDEO_CONFIGS["class"], batch_size=batch_size)
    model = VideoJEPA(config.model)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
    frames = torch.randint(0, 256, (batch_size, 10, 1, 64, 64), dtype=torch.uint8)
    times = []
    for _ in range(repeats + 1):  # the first call warms up
        start = time.perf_counter()
        loss, _ = video_jepa_loss(model, frames, config)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        times.append(time.perf_counter() - start)
    return min(times[1:])


def step_split(batch_size: int) -> dict[str, float]:
    """Median seconds of each part of one class-scale training step (forward parts, backward)."""
    config = replace(VIDEO_CONFIGS["class"], batch_size=batch_size)
    model = VideoJEPA(config.model)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
    frames = torch.randint(0, 256, (batch_size, 10, 1, 64, 64), dtype=torch.uint8)

    def step(repeat: int):
        z = model.encode(frames)
        yield "encoder"
        prediction = rollout_loss(model.predictor, z, config.model.context,
                                  config.rollout_steps, config.tbptt)
        yield "rollout"
        variance, covariance = variance_and_covariance(model.project(z))
        loss = prediction + config.std_coeff * variance + config.cov_coeff * covariance
        yield "projector+regulariser"
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        yield "backward"
        optimizer.step()
        yield "optimiser"

    return time_parts(step)


def model_benchmark(train_digits, held_out, steps: int, batch_size: int, eval_clips: int):
    """Train ``steps`` class-scale steps; return (training clips per second, mAP)."""
    for size in (64, batch_size):
        print(f"one class-scale step at batch {size} x 10 frames: {time_step(size):.2f} s")
    config = replace(VIDEO_CONFIGS["class"], steps=steps, batch_size=batch_size)
    clips = generate_moving_mnist(train_digits, 2000, 10, seed=1).clips
    start = time.perf_counter()
    model, history = train_video_jepa(config, clips, progress=False)
    rate = steps * batch_size / (time.perf_counter() - start)
    probe_data = generate_moving_mnist(train_digits, eval_clips, 10, seed=2)
    eval_data = generate_moving_mnist(held_out, eval_clips, 10, seed=3)
    report = detection_report(model, probe_data, eval_data)
    torch.manual_seed(config.seed)
    baseline = detection_report(VideoJEPA(config.model).eval(), probe_data, eval_data)
    print(f"{steps} steps at batch {batch_size}: {rate:.1f} clips/s, prediction loss "
          f"{history['prediction'][0]:.3f} -> {history['prediction'][-1]:.3f}")
    for name, r in (("trained", report), ("random init", baseline)):
        aps = " ".join(f"{ap:.3f}" for ap in r["ap"].tolist())
        print(f"{name}: AP per horizon {aps}; mAP {r['map']:.3f} (true encodings "
              f"{r['map_encoded']:.3f}, copy last frame {r['map_copy']:.3f})")
    return rate, report["map"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clips", type=int, default=4000, help="clips per timed call")
    parser.add_argument("--frames", type=int, default=10, help="frames per clip")
    parser.add_argument("--repeats", type=int, default=5, help="timed calls; the median is kept")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument("--train-steps", type=int, default=100, help="0 skips the model part")
    parser.add_argument("--batch", type=int, default=VIDEO_CONFIGS["class"].batch_size)
    parser.add_argument("--eval-clips", type=int, default=500, help="probe and evaluation clips")
    parser.add_argument("--split", action="store_true", help="where one training step goes")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.split:
        print_parts(f"one class-scale step at batch {args.batch} x 10 frames",
                    step_split(args.batch))

    train_digits, held_out = split_digits(load_digits(), n_train=8000)
    time_generator(train_digits, 64, args.frames, seed=0)  # warm-up
    rates = []
    for repeat in range(args.repeats):
        rate = time_generator(train_digits, args.clips, args.frames, seed=repeat)
        rates.append(rate)
        print(
            f"generator repeat {repeat}: {args.clips} clips x {args.frames} frames, "
            f"{rate:,.0f} clips/s"
        )
    train_rate, mean_ap = float("nan"), float("nan")
    if args.train_steps > 0:
        train_rate, mean_ap = model_benchmark(train_digits, held_out, args.train_steps,
                                              args.batch, args.eval_clips)
    print(f"clips_per_s={statistics.median(rates):.0f} train_clips_per_s={train_rate:.1f} "
          f"map={mean_ap:.3f}")


if __name__ == "__main__":
    main()
