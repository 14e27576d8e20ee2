"""Full-scale benchmark: what a training step of each chapter's ``full`` preset costs here.

    python -m research.benchmarks.full_scale [--only image video ...] [--steps 5] [--warmup 1]
        [--batch N | --batch-scale F] [--threads T] [--device cpu]
    torchrun --nproc_per_node=N -m research.benchmarks.full_scale --ddp      # N GPUs of one machine

Each chapter's ``full`` preset (the paper's configuration) is trained by the package's own
training function, unchanged but for the number of steps and the batch, on synthetic data of
the right shapes, so nothing is downloaded: random uint8 images for CIFAR-10, Moving MNIST
clips of random digits, generated Two Rooms trajectories. The chapters:

- ``image``: notebook 01, VICReg with the full-width ResNet-18;
- ``sigreg``: notebook 02, the same network with SIGReg (2048-128 projector);
- ``video``: notebook 03, the paper's video JEPA;
- ``world``: notebook 05, the paper's world model.

Printed per chapter: seconds per step, samples per second, epochs per hour, peak GPU memory,
and the wall time of the paper's whole schedule at that speed: a PROJECTION from a few steps
(no data loading from disk, no evaluation, no checkpoints), not a measured run. An epoch is
CIFAR-10's 50,000 training images, the paper's 18,000 Moving MNIST clips, or its 100,000 Two
Rooms trajectories. The batch is the preset's (the global batch under torchrun) on a GPU; on a
CPU, 1/32 of it unless ``--batch``/``--batch-scale`` says otherwise (a full batch there takes
up to a minute a step and tens of GB). A projection from a smaller batch assumes the
throughput does not depend on the batch, which on a GPU is far from true: measure there at
the real batch.

Under torchrun every process trains its share of each global batch (DistributedDataParallel,
see ``ebjepa_tutorial.distributed``) and rank 0 prints the global throughput. The last line
is for scripts: ``device=... ranks=... image_s_per_step=... sigreg_s_per_step=...
video_s_per_step=... world_s_per_step=...`` (ranks: the processes; ``nan`` for a chapter left
out).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import torch

from ebjepa_tutorial import distributed
from ebjepa_tutorial.course.presets import image_preset, preset
from ebjepa_tutorial.data.moving_mnist import generate_moving_mnist
from ebjepa_tutorial.envs import generate_trajectories
from ebjepa_tutorial.training import image, video, world
from ebjepa_tutorial.utils import get_device
from research import launch, train_world
from research.train_video import notebook

CHAPTERS = ("image", "sigreg", "video", "world")
CPU_BATCH_SCALE = 1 / 32  # the default on a CPU: full batches there are for patient people


@dataclass(frozen=True)
class Chapter:
    """One chapter's full run: how to train it for a few steps, and how long the paper's is."""

    title: str
    batch: int  # the preset's batch (the global batch under torchrun)
    schedule_steps: int  # the paper's run, in steps of ``batch``
    epoch: int  # samples in one epoch
    unit: str  # what a sample is: "images", "clips", "trajectories"
    train: Callable[[int, int, torch.device], object]  # (steps, batch, device): from scratch


# -- synthetic data, made once per size: the step's cost does not depend on what it shows ----
@functools.cache
def random_images(n: int) -> torch.Tensor:
    """uint8 ``(n, 3, 32, 32)`` noise: CIFAR-10's shape."""
    generator = torch.Generator().manual_seed(0)
    return torch.randint(0, 256, (n, 3, 32, 32), dtype=torch.uint8, generator=generator)


@functools.cache
def random_clips(n: int, frames: int) -> torch.Tensor:
    """uint8 ``(n, frames, 1, 64, 64)`` Moving MNIST clips of random 28-px "digits"."""
    digits = torch.randint(0, 256, (64, 1, 28, 28), dtype=torch.uint8,
                           generator=torch.Generator().manual_seed(0))
    return generate_moving_mnist(digits, n, frames).clips


@functools.cache
def trajectories(n: int):
    """``n`` Two Rooms trajectories of the training length (17 frames)."""
    return generate_trajectories(n, world.TRAJECTORY_ACTIONS, seed=0)


# -- the chapters: each one the package's training function on its full preset -------------
def image_chapter(config: image.ImageJEPAConfig, title: str) -> Chapter:
    def train(steps, batch, device):  # warm-up 0: the rate's schedule costs nothing to time
        run = replace(config, steps=steps, warmup_steps=0, batch_size=batch)
        return image.train_image_jepa(run, random_images(batch), device=device, progress=False)

    epoch = image_preset("full", config.method).train_images  # CIFAR-10's 50,000
    return Chapter(title, config.batch_size, config.steps, epoch, "images", train)


def video_chapter() -> Chapter:
    config, loop = preset("03", "full").train, notebook().train_video_jepa  # read once

    def train(steps, batch, device):
        run = replace(config, n_clips=batch, batch_size=batch, steps=steps)
        return loop(run, random_clips(batch, config.n_frames), video.video_jepa_step,
                    device=device)

    return Chapter("video JEPA (03)", config.batch_size, config.steps, config.n_clips, "clips",
                   train)


def world_chapter() -> Chapter:
    config, loop = preset("05", "full").train, train_world.notebook().train_world_model

    def train(steps, batch, device):
        run = replace(config, n_trajectories=batch, batch_size=batch, steps=steps)
        return loop(run, trajectories(batch), world.world_model_step, device=device,
                    progress=False)

    return Chapter("world model (05)", config.batch_size, config.steps, config.n_trajectories,
                   "trajectories", train)


def chapters() -> dict[str, Chapter]:
    vicreg = image_preset("full", "vicreg").config
    return {
        "image": image_chapter(vicreg, "VICReg ResNet-18 (01)"),
        "sigreg": image_chapter(image_preset("full", "sigreg").config, "SIGReg ResNet-18 (02)"),
        "video": video_chapter(),
        "world": world_chapter(),
    }


# -- timing -------------------------------------------------------------------------------
def synchronize(device: torch.device) -> None:
    """Wait for the device's queued work: a GPU returns from calls before it has run them."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


@contextlib.contextmanager
def output_dtypes():
    """The set of dtypes that modules output while the block runs: what the networks computed
    in (``bfloat16`` among them under autocast), read off the run rather than assumed."""
    seen: set[torch.dtype] = set()

    def hook(module, inputs, output):
        if isinstance(output, torch.Tensor) and output.is_floating_point():
            seen.add(output.dtype)

    handle = torch.nn.modules.module.register_module_forward_hook(hook)
    try:
        yield seen
    finally:
        handle.remove()


def time_steps(chapter: Chapter, batch: int, steps: int, warmup: int,
               device: torch.device) -> tuple[float, set[torch.dtype]]:
    """Wall seconds of one training step, ``(T(warmup + steps) - T(warmup)) / steps`` (nan if
    not positive: the noise outweighed the steps), and the dtypes its networks computed in.

    Every run starts from a fresh model, so building it and its first (slow) steps cancel
    in the difference. A first, untimed run pays the process's one-time costs (the CUDA
    context, cuDNN's autotuning, the allocator's growth), which would otherwise read as
    negative time, and records the dtypes (its hooks would slow a timed run).
    """
    def timed(n: int) -> float:
        synchronize(device)
        start = time.perf_counter()
        chapter.train(n, batch, device)
        synchronize(device)
        return time.perf_counter() - start

    with output_dtypes() as dtypes:
        chapter.train(warmup, batch, device)
    seconds = (timed(warmup + steps) - timed(warmup)) / steps
    return (seconds if seconds > 0 else math.nan), dtypes  # nan: noise outweighed the steps


def chosen_batch(chapter: Chapter, args, ranks: int) -> int:
    """``--batch``, else the preset's batch times the scale, as a multiple of the ranks."""
    wanted = args.batch or round(chapter.batch * args.batch_scale)
    return max(2 * ranks, round(wanted / ranks) * ranks)


# -- printing ----------------------------------------------------------------------------
HEADER = (f"{'chapter':<7}{'batch':>6}{'s/step':>10}{'samples/s':>11}{'epochs/h':>10}"
          f"{'peak GiB':>9}  {'compute':<10} the paper's schedule at this speed")
SHORT = {torch.float32: "fp32", torch.bfloat16: "bf16", torch.float16: "fp16",
         torch.float64: "fp64"}


def duration(seconds: float) -> str:
    if seconds < 3600:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h" if seconds < 72 * 3600 else f"{seconds / 86400:.1f} days"


def row(name: str, chapter: Chapter, batch: int, s_per_step: float, peak_gib: float,
        dtypes: set[torch.dtype]) -> str:
    """One line of the table; the schedule's wall time assumes this many samples per second."""
    if not s_per_step > 0:
        return (f"{name:<7}{batch:>6}  not measured: the timed steps took less than the timing's "
                "noise (building a model on busy cores); time more --steps")
    rate = batch / s_per_step
    epochs = chapter.schedule_steps * chapter.batch / chapter.epoch  # e.g. 300 of CIFAR-10
    projected = "projected" if batch == chapter.batch else (
        f"projected from batch {batch}, not the paper's {chapter.batch}")
    compute = "+".join(sorted(SHORT.get(d, str(d)) for d in dtypes))  # e.g. bf16+fp32
    return (f"{name:<7}{batch:>6}{s_per_step:>10.4f}{rate:>11.1f}"
            f"{3600 * rate / chapter.epoch:>10.2f}{peak_gib:>9.2f}  {compute:<10} "
            f"{epochs:.0f} epochs of {chapter.epoch:,} {chapter.unit}: "
            f"{duration(epochs * chapter.epoch / rate)} ({projected})")


def describe(device: torch.device, args) -> str:
    """What the figures were measured with: device, torch, threads, dtypes, timing, batch."""
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    dtype = str(torch.get_default_dtype()).removeprefix("torch.")
    batch = f"{args.batch} for every chapter" if args.batch else (
        f"the presets' x {args.batch_scale:g}")
    return (f"device: {name} ({device}), {distributed.world_size()} process(es)\n"
            f"torch {torch.__version__}, {torch.get_num_threads()} CPU thread(s), parameters "
            f"{dtype}, float32 matmul precision {torch.get_float32_matmul_precision()}; compute: "
            "the dtypes the layers output (bf16 under the training's autocast)\n"
            f"timing: {args.warmup} warm-up step(s), then {args.steps} timed step(s), each run "
            f"from a fresh model; batch (global): {batch}")


def peak_gib(device: torch.device) -> float:
    """The most memory the device held since the last reset, in GiB (nan off a GPU)."""
    if device.type != "cuda":
        return math.nan
    peak = torch.cuda.max_memory_allocated(device) / 2**30
    torch.cuda.empty_cache()  # the next chapter starts from an empty cache
    return peak


def run(wanted: dict[str, Chapter], batches: dict[str, int], args,
        device: torch.device) -> dict[str, float]:
    """Time each chapter (rank 0 prints its row as soon as it has it): seconds per step."""
    show = distributed.is_main()
    if show:
        print(describe(device, args), HEADER, sep="\n", flush=True)
    results = {}
    for name, chapter in wanted.items():
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        try:
            seconds, dtypes = time_steps(chapter, batches[name], args.steps, args.warmup, device)
        except torch.OutOfMemoryError:  # the next chapter may still fit
            print(f"{name}: out of memory at batch {batches[name]}; try --batch-scale 0.5")
            continue
        results[name], peak = seconds, peak_gib(device)
        if show:
            print(row(name, chapter, batches[name], seconds, peak, dtypes), flush=True)
    if show:
        print("chapters: " + "; ".join(f"{name}: {c.title}" for name, c in wanted.items()))
        print("epochs: CIFAR-10's 50,000 training images; the paper's 18,000 Moving MNIST "
              "clips; its 100,000 Two Rooms trajectories. Projected: steps timed here, without "
              "data loading, evaluation or checkpoints.")
    return results


def parse(argv: list[str] | None = None) -> tuple[argparse.ArgumentParser, argparse.Namespace]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="+", choices=CHAPTERS, default=list(CHAPTERS),
                        help="the chapters to time (default: all)")
    parser.add_argument("--steps", type=int, default=5, help="timed steps per chapter")
    parser.add_argument("--warmup", type=int, default=1,
                        help="steps before the timed ones (at least 1)")
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--batch", type=int, help="one (global) batch for every chapter")
    size.add_argument("--batch-scale", type=float,
                      help=f"the presets' batches times this (default 1 on a GPU, "
                           f"{CPU_BATCH_SCALE:g} on a CPU)")
    parser.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    parser.add_argument("--device", help="cpu, cuda, mps (default: the best there is)")
    parser.add_argument("--matmul-precision", choices=("highest", "high", "medium"),
                        help="torch.set_float32_matmul_precision: high allows TF32 on a GPU "
                             "(default: torch's, highest)")
    launch.add_flags(parser)
    args = parser.parse_args(argv)
    if args.steps < 1 or args.warmup < 1:
        parser.error("--steps and --warmup must be at least 1")
    if args.device and (args.ddp or launch.launched_by_torchrun()):
        parser.error("--device picks one device; under torchrun each process takes its own")
    if args.batch_scale is None:  # on a CPU, a small share of the batch unless told
        cpu = get_device(args.device).type == "cpu"
        args.batch_scale = CPU_BATCH_SCALE if cpu else 1.0
    return parser, args


def main(argv: list[str] | None = None) -> None:
    parser, args = parse(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.matmul_precision:
        torch.set_float32_matmul_precision(args.matmul_precision)
    wanted = {name: c for name, c in chapters().items() if name in args.only}
    several = args.ddp or launch.launched_by_torchrun()
    ranks = int(os.environ.get("WORLD_SIZE", "1")) if several else 1
    batches = {name: chosen_batch(c, args, ranks) for name, c in wanted.items()}
    device = launch.join(parser, args, math.gcd(*batches.values()), batches,
                         "research.benchmarks.full_scale")
    device = get_device(args.device) if args.device else device
    show = distributed.is_main()
    try:
        results = run(wanted, batches, args, device)
    finally:
        launch.shutdown()
    if show:
        fields = " ".join(f"{name}_s_per_step={results.get(name, math.nan):.4g}"
                          for name in CHAPTERS)
        print(f"device={device.type} ranks={ranks} {fields}")


if __name__ == "__main__":
    main()
