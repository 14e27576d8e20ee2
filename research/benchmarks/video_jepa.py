"""Chapter 03 benchmark: Moving MNIST generation speed, then notebook 03's class run and its AP.

    python -m research.benchmarks.video_jepa [--rollout-steps 4] [--seed 0] [--steps N]
        [--threads 2] [--clips 4000] [--frames 10] [--repeats 5] [--split]

Prints one line per generator repeat; then trains the class-scale run exactly
as notebook 03 does (``preset("03", "class")``: its clips, config and
evaluation protocol), with ``--rollout-steps K`` and ``--seed S`` choosing the
variant, and prints its AP per horizon beside the random-init model's, in the
paper's protocol (parallel unroll) and then autoregressively. The last line
is ``clips_per_s=... train_clips_per_s=... map=... ap3=...`` (the paper's
protocol; ap3: AP three steps ahead) for scripts. ``--steps`` shortens the run (a quick
check; the figures are then not the class run's); ``--steps 0`` skips the
model part (``nan``). ``--record`` stores the main run's (K = 4, seed 0) mAP as
``video_map`` in ``checkpoints/reference.json``, which no page or notebook prints
(notebook 03 prints ``video_map_class_K4``, the mean of ``research.train_video``'s seeds),
and its training minutes as ``video_train_min``, which the README, RESULTS.md and notebook 03
state.
``--split`` first prints where one class-scale step's time goes (encoder,
rollout, projector and regulariser, backward, optimiser).
Needs the MNIST test digits on disk (``load_mnist("test", download=False)``);
without them only the generator is timed, on random digits.
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace

import torch

from ebjepa_tutorial.course.presets import preset
from ebjepa_tutorial.data.mnist import load_mnist
from ebjepa_tutorial.data.moving_mnist import generate_moving_mnist, split_digits
from ebjepa_tutorial.data.paths import DataNotFoundError
from ebjepa_tutorial.distributed import variance_and_covariance
from ebjepa_tutorial.evaluation.detection import detection_report, evaluation_clips
from ebjepa_tutorial.losses.rollout import UNROLLS
from ebjepa_tutorial.models.video import VideoJEPA
from ebjepa_tutorial.training.video import (
    COV_COEFF,
    STD_COEFF,
    VIDEO_CONFIGS,
    make_clips,
    video_jepa_step,
)
from ebjepa_tutorial.utils import at_least_float32, mixed_precision
from research.benchmarks import command_line
from research.benchmarks.timing import (
    backward_and_step,
    precision_name,
    print_parts,
    time_parts,
)
from research.train_video import notebook
from tools import figures


def load_digits() -> torch.Tensor | None:
    """The 10,000 MNIST test digits (N, 1, 28, 28) uint8, or None (with a note) if absent."""
    try:
        return load_mnist("test", download=False)[0]
    except DataNotFoundError:
        print("MNIST not found (see data/README.md): timing the generator on random digits "
              "(its speed does not depend on them) and skipping the model")
        return None


def time_generator(digits: torch.Tensor, clips: int, frames: int, seed: int) -> float:
    """Clips per second for one call of ``generate_moving_mnist`` (2 digits, 64x64)."""
    start = time.perf_counter()
    batch = generate_moving_mnist(digits, n_clips=clips, n_frames=frames, seed=seed)
    elapsed = time.perf_counter() - start
    assert batch.clips.shape == (clips, frames, 1, 64, 64)
    return clips / elapsed


def step_split() -> dict[str, float]:
    """Median seconds of each part of one class-scale training step (forward parts, backward)."""
    config = VIDEO_CONFIGS["class"]
    layout = torch.channels_last if config.recipe.channels_last else torch.contiguous_format
    model = VideoJEPA(config.model).to(memory_format=layout)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr)
    frames = torch.randint(0, 256, (config.batch_size, config.n_frames, 1, 64, 64),
                           dtype=torch.uint8)

    def step(repeat: int):
        with mixed_precision("cpu", cpu=True):  # the networks as video_jepa_step runs them
            z = model.encode(frames)
            yield "encoder"
            prediction = UNROLLS[config.unroll](
                model.predictor, z, config.model.context, config.rollout_steps,
                config.recipe.detach_later_orders)
            yield "rollout"
            projected = model.project(z)
        variance, covariance = variance_and_covariance(at_least_float32(projected))
        loss = prediction + STD_COEFF * variance + COV_COEFF * covariance
        yield "projector+regulariser"
        yield from backward_and_step(optimizer, loss)

    return time_parts(step)


def model_benchmark(cfg, train_digits, held_out, rollout_steps: int, seed: int,
                    steps: int | None, precision: str):
    """Train notebook 03's class run (``cfg``, K, seed); return (training clips/s, report).

    ``precision``: what the networks train in here, for the log."""
    config = replace(cfg.train, rollout_steps=rollout_steps, seed=seed,
                     steps=steps or cfg.train.steps)
    clips = make_clips(config, train_digits)
    start = time.perf_counter()
    model, history = notebook().train_video_jepa(config, clips, video_jepa_step)
    seconds = time.perf_counter() - start
    probe_data, eval_data = evaluation_clips(train_digits, held_out, cfg.n_probe, cfg.n_eval,
                                             config.n_frames)
    reports = {u: detection_report(model, probe_data, eval_data, cfg.horizons, cfg.probe_steps,
                                   unroll=u) for u in ("parallel", "autoregressive")}
    torch.manual_seed(config.seed)
    baseline = detection_report(VideoJEPA(config.model).eval(), probe_data, eval_data,
                                cfg.horizons, cfg.probe_steps)
    print(f"K = {rollout_steps}, seed {seed}: {config.steps} steps of {config.batch_size} clips "
          f"in {seconds / 60:.1f} min on {torch.get_num_threads()} thread(s) in {precision}, "
          f"{config.unroll} unroll, prediction loss {history['prediction'][0]:.3f} -> "
          f"{history['prediction'][-1]:.3f}")
    print(f"protocol: detection probe fitted on {cfg.n_probe} clips of training digits, AP on "
          f"{cfg.n_eval} clips of {len(held_out)} held-out digits, horizons 1..{cfg.horizons}; "
          "the paper's parallel unroll unless said")
    for name, r in (("trained", reports["parallel"]), ("random init", baseline),
                    ("trained, autoregressive rollout", reports["autoregressive"])):
        aps = " ".join(f"{ap:.3f}" for ap in r["ap"].tolist())
        print(f"{name}: AP per horizon {aps}; mAP {r['map']:.3f} (true encodings "
              f"{r['map_encoded']:.3f}, copy last frame {r['map_copy']:.3f})")
    report = dict(reports["parallel"], seconds=seconds)
    return config.steps * config.batch_size / seconds, report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clips", type=int, default=4000, help="clips per timed call")
    parser.add_argument("--frames", type=int, default=10, help="frames per clip")
    parser.add_argument("--repeats", type=int, default=5, help="timed calls; the median is kept")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument("--rollout-steps", type=int, default=VIDEO_CONFIGS["class"].rollout_steps,
                        help="K of the class run")
    parser.add_argument("--seed", type=int, default=0, help="seed of the class run")
    parser.add_argument("--steps", type=int, default=None,
                        help="train this many steps instead of the class run's; 0 skips it")
    parser.add_argument("--split", action="store_true", help="where one training step goes")
    parser.add_argument("--record", action="store_true",
                        help="store the mAP in checkpoints/reference.json (the class run only)")
    args = parser.parse_args()
    cfg = preset("03", "class")
    if args.record and (args.steps, args.rollout_steps, args.seed) != (
            None, cfg.train.rollout_steps, cfg.train.seed):
        parser.error("--record stores notebook 03's main run: drop --steps, --rollout-steps "
                     "and --seed")
    torch.set_num_threads(args.threads)
    if args.split:
        print_parts(f"one class-scale step at batch {cfg.train.batch_size} x "
                    f"{cfg.train.n_frames} frames", step_split())

    digits = load_digits()
    train_digits, held_out = split_digits(
        torch.randint(0, 256, (10_000, 1, 28, 28), dtype=torch.uint8) if digits is None
        else digits, n_train=cfg.n_train_digits)
    time_generator(train_digits, 64, args.frames, seed=0)  # warm-up
    rates = []
    for repeat in range(args.repeats):
        rate = time_generator(train_digits, args.clips, args.frames, seed=repeat)
        rates.append(rate)
        print(
            f"generator repeat {repeat}: {args.clips} clips x {args.frames} frames, "
            f"{rate:,.0f} clips/s"
        )
    train_rate, mean_ap, ap3 = float("nan"), float("nan"), float("nan")
    if digits is not None and args.steps != 0:
        precision = precision_name("cpu", cpu=True)  # what video_jepa_step trains in here
        train_rate, report = model_benchmark(cfg, train_digits, held_out, args.rollout_steps,
                                             args.seed, args.steps, precision)
        mean_ap, ap3 = report["map"], float(report["ap"][2])
        if args.record:
            figures.record("video_map", mean_ap, command=command_line(__spec__.name),
                             threads=args.threads,
                             protocol=f"K = {args.rollout_steps}, seed {args.seed}, "
                             f"{precision}; detection "
                             f"probe fitted on {cfg.n_probe} clips of training digits, AP on "
                             f"{cfg.n_eval} clips of held-out digits, horizons 1..{cfg.horizons}, "
                             "the paper's parallel unroll")
            figures.record("video_train_min", report["seconds"] / 60,
                           command=command_line(__spec__.name), threads=args.threads,
                           protocol=f"K = {args.rollout_steps}, seed {args.seed}, {precision}, "
                                    f"{cfg.train.steps} steps, training alone, idle cores")
    print(f"clips_per_s={statistics.median(rates):.0f} train_clips_per_s={train_rate:.1f} "
          f"map={mean_ap:.3f} ap3={ap3:.3f}")


if __name__ == "__main__":
    main()
