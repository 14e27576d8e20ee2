"""Image-JEPA benchmark: training speed and linear-probe / kNN accuracy on CIFAR-10.

Run: ``python -m research.benchmarks.image_jepa [--scale class] [--loss vicreg] [--steps N]
[--seed S] [--eval-size PX] [--split]``. Trains the notebook's configuration at that scale from
scratch (no checkpoint), then evaluates the frozen encoder on un-augmented
images at the preset's ``eval_image_size`` (32 px, CIFAR-10's native size, at
class and full scale, whatever size the training views had; 16 px at ci scale;
``--eval-size 16`` gives the earlier 16-px protocol): a linear probe and a kNN
classifier fitted on the train split and scored on the test split (CIFAR-10,
the JPEG copy where ``EBJEPA_DATA`` points at it). The random-init encoder is
scored the same way for comparison. Last line:
``images_per_s=... minutes=... probe_acc=... knn_acc=...``. ``--record`` (class
scale, no overrides) stores the probe accuracies in ``checkpoints/reference.json``,
which notebooks 01 and 02 print beside the learner's; on a CPU without bf16 it
stores only the float32 run's minutes (``{loss}_float32_train_min``), leaving
the bf16 figures as they are. ``--split`` prints where
one training step's time goes (augmentation, forward, loss, backward,
optimiser) and, on a CPU with bf16, how much longer the step takes in float32
(``--split --record``, VICReg's step only, stores that ratio), and stops.
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace

import torch

from ebjepa_tutorial.augment import AugmentConfig, build_augmentation, two_views
from ebjepa_tutorial.course.presets import SCALES, image_preset
from ebjepa_tutorial.data import load_cifar10, random_subset
from ebjepa_tutorial.evaluation.classify import probe_encoder
from ebjepa_tutorial.evaluation.sweeps import shorten
from ebjepa_tutorial.losses.sigreg import sigreg_loss
from ebjepa_tutorial.losses.vicreg import vicreg
from ebjepa_tutorial.training.image import (
    LR,
    WEIGHT_DECAY,
    AllViews,
    ImageJEPA,
    SIGReg,
    VICReg,
    train_image_jepa,
)
from ebjepa_tutorial.training.optim import split_decay_params
from ebjepa_tutorial.utils import at_least_float32, mixed_precision
from research.benchmarks import command_line, cpu_name
from research.benchmarks.timing import (
    backward_and_step,
    precision_name,
    print_parts,
    time_parts,
)
from research.train_image import protocol
from tools import figures


def training_loss(config, z_a, z_b, generator) -> torch.Tensor:
    """The loss of two embedded views that ``config``'s training step computes."""
    weights = VICReg(1.0, 0.0, 0.0) if config.loss is None else config.loss
    if isinstance(weights, SIGReg):
        return sigreg_loss(z_a, z_b, weights.lam, weights.slices, generator, weights.scale_by_n)[0]
    return vicreg(z_a, z_b, weights.inv_coeff, weights.std_coeff, weights.cov_coeff)


def step_split(config, images: torch.Tensor, bf16: bool = True) -> dict[str, float]:
    """Median seconds of each part of one training step of ``config`` on uint8 ``images``,
    the networks in bf16 where the CPU computes it (``bf16=False``: float32)."""
    model = AllViews(ImageJEPA(config))
    optimizer = torch.optim.AdamW(split_decay_params(model, WEIGHT_DECAY), lr=LR)
    pipeline = build_augmentation(AugmentConfig(size=config.image_size))

    def step(repeat: int):
        generator = torch.Generator().manual_seed(repeat)
        index = torch.randint(0, len(images), (config.batch_size,), generator=generator)
        views = two_views(images[index], pipeline, generator)
        yield "augmentation"
        with mixed_precision("cpu", cpu=bf16):  # bf16=True: as train_image_jepa computes it
            z_a, z_b = map(at_least_float32, model(*views))
        yield "forward"
        loss = training_loss(config, z_a, z_b, generator)
        yield "loss"
        yield from backward_and_step(optimizer, loss)

    return time_parts(step)


def split_and_precision(config, images: torch.Tensor, args, rounds: int = 7) -> None:
    """Print where one step's time goes and, where the CPU has bf16, the float32 step's time
    over the bf16 step's (median of ``rounds`` interleaved pairs); ``args.record`` stores it."""
    title = f"one step of {config.batch_size} images x 2 views of {config.image_size} px"
    print_parts(title, step_split(config, images))
    if precision_name("cpu", cpu=True) == "float32":
        return print("this CPU computes the networks in float32 only: no ratio to measure")
    ratios = [sum(step_split(config, images, bf16=False).values())
              / sum(step_split(config, images).values()) for _ in range(rounds)]
    ratio = statistics.median(ratios)
    print(f"float32 step / bf16 step: {ratio:.2f} (pairs: {', '.join(f'{r:.2f}' for r in ratios)})")
    if args.record:
        figures.record("image_float32_step_ratio", ratio, command_line(__spec__.name),
                       f"one class-recipe {args.loss} training step (augmentation, forward, loss, "
                       f"backward, AdamW), float32 over bf16 autocast, median of {rounds} "
                       "interleaved pairs (each side: the sum of its parts' medians over 5 timed "
                       f"steps after a warm-up), on {cpu_name()}; spread: the lowest and highest "
                       "pair ratio", args.threads,
                       spread=(min(ratios), max(ratios)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scale", choices=SCALES, default="class")
    parser.add_argument("--loss", choices=("vicreg", "sigreg", "invariance"), default="vicreg")
    parser.add_argument("--steps", type=int, default=None,
                        help="override the preset's steps (warm-up: at most a tenth of them)")
    parser.add_argument("--seed", type=int, default=None,
                        help="override the preset's seed (weights, batches, augmentations)")
    parser.add_argument("--eval-size", type=int, default=None,
                        help="side in px of the images the probe and kNN see (class preset: 32)")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument("--split", action="store_true", help="where one training step goes")
    parser.add_argument("--record", action="store_true",
                        help="store the result in checkpoints/reference.json (class recipe only)")
    args = parser.parse_args()
    if args.record and (args.scale, args.steps, args.eval_size, args.seed) != (
            "class", None, None, None):
        parser.error("--record stores the class recipe's figures: drop --scale, --steps, "
                     "--eval-size, --seed")
    if args.split and args.record and args.loss != "vicreg":  # the pages: a VICReg step's ratio
        parser.error("--split --record stores the ratio of a VICReg step: drop --loss")
    torch.set_num_threads(args.threads)

    preset = image_preset(args.scale, args.loss)
    config = preset.config if args.steps is None else shorten(preset.config, args.steps)
    if args.loss == "invariance":  # no regulariser: the run that collapses
        config = replace(config, loss=None)
    if args.seed is not None:
        config = replace(config, seed=args.seed)
    if args.eval_size is not None:
        config = replace(config, eval_image_size=args.eval_size)
    train = random_subset(*load_cifar10("train"), preset.train_images)
    test = random_subset(*load_cifar10("test"), preset.test_images)
    print(f"{args.scale} scale, {config}")
    if args.split:
        split_and_precision(config, train[0], args)
        return
    precision = precision_name("cpu", cpu=True)  # what train_image_jepa does
    print(f"evaluation: {protocol(config)}; training networks in {precision}")

    torch.manual_seed(config.seed)  # the weights training starts from, as in the notebooks
    random_init = probe_encoder(ImageJEPA(config).encoder, config, train, test)
    start = time.perf_counter()
    model, _ = train_image_jepa(config, train[0])
    seconds = time.perf_counter() - start
    trained = probe_encoder(model.encoder, config, train, test)

    images_per_s = config.steps * config.batch_size / seconds  # each image seen as 2 views
    print(f"random init: probe {random_init['probe_acc']:.3f}, kNN {random_init['knn_acc']:.3f}")
    print(f"trained {config.steps} steps in {seconds / 60:.1f} min ({images_per_s:.0f} images/s): "
          f"probe {trained['probe_acc']:.3f}, kNN {trained['knn_acc']:.3f}")
    print(f"images_per_s={images_per_s:.1f} minutes={seconds / 60:.2f} "
          f"probe_acc={trained['probe_acc']:.4f} knn_acc={trained['knn_acc']:.4f}")
    if args.record and args.loss != "invariance":
        where = dict(command=command_line(__spec__.name), threads=args.threads,
                     protocol=f"{config.steps} steps in {precision}; {protocol(config)}")
        if precision == "float32":  # the pages' class figures are bf16 runs: this CPU's own
            return figures.record(f"{args.loss}_float32_train_min", seconds / 60, **where | dict(
                protocol=f"{config.steps} steps in float32 (this CPU has no bf16), training "
                f"alone, {args.threads} threads of an idle {cpu_name()} "
                f"({torch.backends.cpu.get_cpu_capability()} kernels), torch "
                f"{torch.__version__.split('+')[0]}; that run's {protocol(config)}: "
                f"{trained['probe_acc']:.2%} (kNN {trained['knn_acc']:.2%})"))
        figures.record(f"{args.loss}_probe_acc", trained["probe_acc"], **where)
        figures.record(f"{args.loss}_random_init_probe_acc", random_init["probe_acc"],
                       **where | dict(protocol="no training: the class encoder at its initial "
                                      f"weights (torch.manual_seed({config.seed})); "
                                      f"{protocol(config, trained=False)}"))
        figures.record(f"{args.loss}_train_min", seconds / 60, **where)


if __name__ == "__main__":
    main()
