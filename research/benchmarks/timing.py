"""Timing one training step part by part, for the image and video benchmarks."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Iterator

import torch

from ebjepa_tutorial.utils import network_dtype


def precision_name(device: torch.device | str, cpu: bool = False) -> str:
    """What ``utils.mixed_precision`` computes networks in, in words, for logs and protocols."""
    return "bf16 autocast" if network_dtype(device, cpu) == torch.bfloat16 else "float32"


def time_parts(step: Callable[[int], Iterator[str]], repeats: int = 5) -> dict[str, float]:
    """Median seconds of each part of a step: ``{part: seconds}``, in the step's order.

    ``step(repeat)`` is a generator that does one step and yields each part's
    name as that part ends. It runs ``repeats + 1`` times; the first warms up.
    """
    times: dict[str, list[float]] = {}
    for repeat in range(repeats + 1):
        start = time.perf_counter()
        for name in step(repeat):
            end = time.perf_counter()
            if repeat:
                times.setdefault(name, []).append(end - start)
            start = end
    return {name: statistics.median(seconds) for name, seconds in times.items()}


def backward_and_step(optimizer: torch.optim.Optimizer, loss: torch.Tensor) -> Iterator[str]:
    """The last two parts of a timed step (``yield from`` it): backward, then the optimiser."""
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    yield "backward"
    optimizer.step()
    yield "optimiser"


def print_parts(title: str, parts: dict[str, float]) -> None:
    """Print :func:`time_parts`' result under ``title``: seconds and share of each part."""
    total = sum(parts.values())
    print(f"{title}: {total:.3f} s")
    for name, seconds in parts.items():
        print(f"  {name:22s} {seconds:.3f} s  {100 * seconds / total:4.1f}%")
