"""Run notebook 02's sensitivity and projector sweeps at a scale; store the results as JSON.

    python -m research.sweep --scale class --out checkpoints/sweeps_class.json
"""

from __future__ import annotations

import argparse
import time

import torch

from ebjepa_tutorial.course.presets import SCALES, preset, sweep_plan
from ebjepa_tutorial.data import data_dir, load_cifar10, random_subset
from ebjepa_tutorial.data.cifar10 import find_cifar10
from ebjepa_tutorial.evaluation.classify import protocol
from ebjepa_tutorial.evaluation.sweeps import key, run_sweep
from ebjepa_tutorial.utils import get_device


def describe_data() -> str:
    """Which copy of CIFAR-10 the loaders read: every accuracy depends on it."""

    source = find_cifar10(data_dir(), "train")
    if source is None:
        return "CIFAR-10 (not found)"
    jpeg = source.kind in ("tree", "packed")
    return f"CIFAR-10{' (JPEG copy)' if jpeg else ''}, read from {source.path}"


def main(argv: list[str] | None = None) -> None:
    """Run both sweeps (or one) at a scale and store the results: the documented command."""

    parser = argparse.ArgumentParser(description="Notebook 02's sensitivity and projector sweeps.")
    parser.add_argument("--scale", choices=SCALES, default="class")
    parser.add_argument("--out", required=True, help="the JSON file to write (and resume)")
    parser.add_argument("--only", choices=("sensitivity", "projector"), default=None)
    args = parser.parse_args(argv)
    sizes = preset("02", args.scale)
    train = random_subset(*load_cifar10("train"), sizes.train_images)
    test = random_subset(*load_cifar10("test"), sizes.test_images)
    runs = sweep_plan(args.scale)
    selected = [run for name, group in runs.items() if args.only in (None, name) for run in group]
    unique = list({key(run.config, 0, 0): run for run in selected}.values())  # shared defaults
    only = f" --only {args.only}" if args.only else ""
    meta = {"scale": args.scale, "data": describe_data(), "protocol": protocol(sizes.config),
            "command": f"python -m research.sweep --scale {args.scale} "
                       f"--out {args.out}"
                       f"{only}",
            "torch_threads": torch.get_num_threads()}
    start = time.perf_counter()
    run_sweep(unique, train, test, path=args.out, device=get_device(), meta=meta)
    print(f"done in {(time.perf_counter() - start) / 60:.1f} min; results in {args.out}")


if __name__ == "__main__":
    main()
