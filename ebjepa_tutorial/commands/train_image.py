"""Train notebook 01's or 02's CIFAR-10 run longer and save its encoder (float16).

    python -m ebjepa_tutorial.commands.train_image --loss vicreg --steps 8000 --out FILE.pt
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import torch

from ..course.presets import SCALES, preset
from ..data import load_cifar10, random_subset
from ..evaluation.classify import probe_encoder, protocol
from ..training.checkpoints import save_checkpoint
from ..training.image import identity, train_image_jepa
from ..utils import get_device


def main(argv: list[str] | None = None) -> None:
    """Train notebook 01's or 02's run longer and save its encoder: the documented command for
    the shipped ``checkpoints/<loss>_class_long.pt``. Resumable: rerun the same command after a
    stop; the stored minutes add up the training time of every part.
    """
    parser = argparse.ArgumentParser(description="Train notebook 01's or 02's run for longer.")
    parser.add_argument("--loss", choices=("vicreg", "sigreg"), default="vicreg")
    parser.add_argument("--scale", default="class", choices=SCALES)
    parser.add_argument("--steps", type=int, help="default: the scale's long run")
    parser.add_argument("--out", required=True, help="where to write the encoder (a .pt file)")
    args = parser.parse_args(argv)
    sizes = preset("01" if args.loss == "vicreg" else "02", args.scale)
    try:
        config = replace(sizes.config, steps=args.steps or sizes.long_steps)
    except ValueError as error:
        parser.error(str(error))  # checked before the data is loaded
    train = random_subset(*load_cifar10("train"), sizes.train_images)  # as the notebooks do
    test = random_subset(*load_cifar10("test"), sizes.test_images)
    partial = Path(args.out).with_suffix(".partial")
    # the best device there is: the full scale is the paper's run, sized for a GPU
    model, history = train_image_jepa(config, train[0], checkpoint=partial, device=get_device())
    minutes = history.seconds / 60
    scores = probe_encoder(model.encoder, config, train, test)
    half = {k: (v.half() if v.is_floating_point() else v).cpu()  # float16 halves the file;
            for k, v in model.encoder.state_dict().items()}  # the probe barely moves
    save_checkpoint(args.out, model=half, history=dict(history),
                    config=identity(config, encoder_only=True), minutes=round(minutes, 1),
                    threads=torch.get_num_threads(), **scores)
    partial.unlink(missing_ok=True)  # gone if its folder could not be written
    print(f"saved {args.out}: {config.steps} steps in {minutes:.1f} min, linear probe "
          f"{scores['probe_acc']:.1%}, kNN {scores['knn_acc']:.1%} ({protocol(config)})")


if __name__ == "__main__":
    main()
