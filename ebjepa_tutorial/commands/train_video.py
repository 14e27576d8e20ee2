"""Train (or load) and evaluate notebook 03's video JEPAs at a scale, printing AP per horizon.

    python -m ebjepa_tutorial.commands.train_video --scale class [--K 4] [--seed 0]
"""

from __future__ import annotations

import argparse
import time

import torch

from ..course.presets import SCALES, preset
from ..data.mnist import load_mnist
from ..data.moving_mnist import split_digits
from ..evaluation.detection import detection_report, evaluation_clips
from ..models.video import VideoJEPA
from ..training.video import ablation_configs, run_name, train_or_load


def main(argv: list[str] | None = None) -> None:
    """Train (or load) and evaluate notebook 03's runs at a scale, printing AP per horizon.

    ``python -m ebjepa_tutorial.commands.train_video --scale class`` trains the K ablation
    (K 1, 2, 4 times three seeds, about ten minutes each on 2 CPU cores) into
    ``data/cache/checkpoints/``, where the notebook finds them; an interrupted
    run resumes. Same digits, clips and probe protocol as the notebook.
    """
    parser = argparse.ArgumentParser(description="Train and evaluate notebook 03's video JEPAs.")
    parser.add_argument("--scale", default="class", choices=SCALES)
    parser.add_argument("--K", type=int, action="append", help="only these K (repeatable)")
    parser.add_argument("--seed", type=int, action="append", help="only these seeds (repeatable)")
    args = parser.parse_args(argv)
    cfg = preset("03", args.scale)
    train_digits, held_out = split_digits(load_mnist("test")[0], n_train=cfg.n_train_digits)
    probe_data, eval_data = evaluation_clips(train_digits, held_out, cfg.n_probe, cfg.n_eval,
                                             cfg.train.n_frames)
    print(f"protocol: AP per horizon 1..{cfg.horizons} of a detection probe on frozen latents, "
          f"fitted on {cfg.n_probe} clips of training digits, scored on {cfg.n_eval} clips of "
          f"{len(held_out)} held-out MNIST test digits")
    torch.manual_seed(cfg.train.seed)
    runs = [("random init", VideoJEPA(cfg.train.model).eval())]
    for config in ablation_configs(cfg.train, args.K or cfg.rollout_steps, args.seed or cfg.seeds):
        start = time.perf_counter()
        model, _ = train_or_load(config, run_name(args.scale, config), train_digits)
        print(f"{run_name(args.scale, config)}: ready in {time.perf_counter() - start:.0f} s")
        runs.append((f"K={config.rollout_steps} seed={config.seed}", model))
    for label, model in runs:
        report = detection_report(model.cpu(), probe_data, eval_data, cfg.horizons,
                                  cfg.probe_steps)
        aps = " ".join(f"{ap:.3f}" for ap in report["ap"].tolist())
        print(f"{label}: mAP {report['map']:.3f} (AP {aps}; true encodings "
              f"{report['map_encoded']:.3f}, copy last frame {report['map_copy']:.3f})")


if __name__ == "__main__":
    main()
