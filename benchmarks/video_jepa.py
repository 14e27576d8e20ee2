"""Chapter 03 benchmark: how fast we make Moving MNIST clips (the model part comes later).

    python benchmarks/video_jepa.py [--clips 4000] [--frames 10] [--repeats 5] [--threads 2]

Prints one line per repeat, then a last line ``clips_per_s=...`` (the median
over repeats) that scripts can parse. Uses the MNIST test digits when they are
on disk (``load_mnist("test", download=False)``), else random digits with a
note: the generator's speed does not depend on what the digits look like.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from ebjepa_tutorial.data.mnist import load_mnist
from ebjepa_tutorial.data.moving_mnist import generate_moving_mnist, split_digits
from ebjepa_tutorial.data.paths import DataNotFoundError


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clips", type=int, default=4000, help="clips per timed call")
    parser.add_argument("--frames", type=int, default=10, help="frames per clip")
    parser.add_argument("--repeats", type=int, default=5, help="timed calls; the median is kept")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    train_digits, _ = split_digits(load_digits(), n_train=8000)
    time_generator(train_digits, 64, args.frames, seed=0)  # warm-up
    rates = []
    for repeat in range(args.repeats):
        rate = time_generator(train_digits, args.clips, args.frames, seed=repeat)
        rates.append(rate)
        print(
            f"generator repeat {repeat}: {args.clips} clips x {args.frames} frames, "
            f"{rate:,.0f} clips/s"
        )
    print(f"clips_per_s={statistics.median(rates):.0f}")


if __name__ == "__main__":
    main()
