"""Train notebook 01's or 02's CIFAR-10 run longer and save its encoder (float16).

    python -m research.train_image --loss vicreg --out FILE.pt

On several devices, one process each (DistributedDataParallel; nccl on GPUs, gloo on CPUs):

    torchrun --nproc_per_node=N -m research.train_image --scale full --out FILE.pt

The preset's batch size is the global batch: global batch = per-rank batch x N, so N must
divide it. VICReg's variance and covariance and SIGReg's statistic are computed on the global
batch, as on one device. Rank 0 alone writes the files; a stopped run resumes on any N.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import torch

from ebjepa_tutorial import distributed
from ebjepa_tutorial.course.presets import SCALES, preset
from ebjepa_tutorial.data import load_cifar10, random_subset
from ebjepa_tutorial.evaluation.classify import KNN_K, probe_encoder
from ebjepa_tutorial.training.checkpoints import save_checkpoint
from ebjepa_tutorial.training.image import ImageJEPAConfig, identity, train_image_jepa

from . import launch
from .shipping import float16_state


def protocol(config: ImageJEPAConfig, trained: bool = True) -> str:
    """The evaluation protocol of ``probe_encoder``, in words, to print beside its numbers
    (``trained=False``: of an encoder at its initial weights)."""
    size = config.eval_image_size
    native = "their native size, no resizing" if size == 32 else "resized from 32 px"
    views = f"; the encoder was trained on {config.image_size}-px views" if trained else ""
    return (f"linear probe (fit on the train split, scored on the test split) and kNN "
            f"(k = {KNN_K}) on frozen encoder features of un-augmented {size}-px images "
            f"({native}){views}")


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description="Train notebook 01's or 02's run for longer.")
    parser.add_argument("--loss", choices=("vicreg", "sigreg"), default="vicreg")
    parser.add_argument("--scale", default="class", choices=SCALES,
                        help="the preset. Its batch size is the global batch over all "
                             "processes: global batch = per-rank batch x world size")
    parser.add_argument("--steps", type=int, help="default: the scale's long run")
    parser.add_argument("--warmup-steps", type=int,
                        help="steps of linear warm-up (default: the preset's; the full "
                             "preset's 1,950 need a longer run: its ratio is 1 in 30)")
    parser.add_argument("--out", required=True, help="where to write the encoder (a .pt file)")
    launch.add_flags(parser)
    return parser


def main(argv: list[str] | None = None) -> None:
    """Train notebook 01's or 02's run longer and save its encoder: the documented command for
    the shipped ``checkpoints/<loss>_class_long.pt``. Resumable: rerun the same command after a
    stop; the stored minutes add up the training time of every part. Under torchrun it trains
    on every process (global batch = per-rank batch x world size); rank 0 probes and saves.
    """
    parser = _parser()
    args = parser.parse_args(argv)
    if args.steps is not None and args.steps < 1:  # as train_world: a usage error, not a run
        parser.error("--steps takes an int >= 1")
    sizes = preset("01" if args.loss == "vicreg" else "02", args.scale)
    try:
        long = sizes.long_config
        warmup = long.warmup_steps if args.warmup_steps is None else args.warmup_steps
        steps = long.steps if args.steps is None else args.steps
        config = replace(long, steps=steps, warmup_steps=warmup)
    except ValueError as error:
        parser.error(str(error))  # checked before the data is loaded
    device = launch.join(parser, args, config.batch_size, identity(config),
                         "research.train_image")
    try:
        _train_and_save(args, sizes, config, device)
    finally:
        launch.shutdown()


def _train_and_save(args, sizes, config, device) -> None:
    train = random_subset(*load_cifar10("train"), sizes.train_images)  # as the notebooks do
    test = random_subset(*load_cifar10("test"), sizes.test_images)
    partial = Path(args.out).with_suffix(".partial")
    model, history = train_image_jepa(config, train[0], checkpoint=partial, device=device)
    if not distributed.is_main():
        return
    minutes = history.seconds / 60
    scores = probe_encoder(model.encoder, config, train, test)
    save_checkpoint(args.out, model=float16_state(model.encoder), history=dict(history),
                    config=identity(config, encoder_only=True), minutes=round(minutes, 1),
                    threads=torch.get_num_threads(), processes=distributed.world_size(),
                    **scores)
    partial.unlink(missing_ok=True)  # gone if its folder could not be written
    print(f"saved {args.out}: {config.steps} steps in {minutes:.1f} min on "
          f"{distributed.world_size()} process(es), linear probe {scores['probe_acc']:.1%}, "
          f"kNN {scores['knn_acc']:.1%} ({protocol(config)})")


if __name__ == "__main__":
    main()
