"""Train (or load) and evaluate notebook 03's video JEPAs at a scale, printing AP per horizon.

    python -m research.train_video --scale class [--K 4] [--seed 0] [--ship]
    python -m research.train_video --scale class --long --K 4 --ship
    python -m research.train_video --scale class --K 4 --seed 0 \
        --unroll autoregressive --ship

On several devices, one process each (nccl on GPUs, gloo on CPUs; the training step averages
the gradients over the processes):

    torchrun --nproc_per_node=N -m research.train_video --scale full

The preset's batch size is the global batch: global batch = per-rank batch x N, so N must
divide it. The variance and covariance are those of the global batch, as on one device; batch
norm normalises over each process's clips. Rank 0 alone reads
and writes the checkpoints and evaluates; a stopped run resumes on any N.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import torch

from ebjepa_tutorial import distributed
from ebjepa_tutorial.course.presets import SCALES, preset
from ebjepa_tutorial.data.mnist import load_mnist
from ebjepa_tutorial.data.moving_mnist import split_digits
from ebjepa_tutorial.evaluation.detection import detection_report, evaluation_clips
from ebjepa_tutorial.losses.rollout import UNROLLS
from ebjepa_tutorial.models.video import VideoJEPA
from ebjepa_tutorial.training.checkpoints import checkpoint_paths, save_checkpoint, save_or_warn
from ebjepa_tutorial.training.loop import training_state
from ebjepa_tutorial.training.video import (
    VideoJEPAConfig,
    ablation_configs,
    identity,
    run_name,
    video_jepa_step,
)

from . import launch
from .from_notebook import definitions
from .shipping import float16_state


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description="Train and evaluate notebook 03's video JEPAs.")
    parser.add_argument("--scale", default="class", choices=SCALES,
                        help="the preset. Its batch size is the global batch over all "
                             "processes: global batch = per-rank batch x world size")
    parser.add_argument("--K", type=int, action="append", help="only these K (repeatable)")
    parser.add_argument("--seed", type=int, action="append", help="only these seeds (repeatable)")
    parser.add_argument("--ship", action="store_true",
                        help="also write each run, in float16, where the course ships its "
                             "checkpoints (checkpoints/<name>.pt)")
    parser.add_argument("--long", action="store_true",
                        help="the preset's long run instead (K 1 and 4, seed 0 unless --K and "
                             "--seed say otherwise), named video_jepa_<scale>_long_K<K>_seed<S>")
    parser.add_argument("--unroll", choices=sorted(UNROLLS),
                        help="train the K-step loss so instead of the preset's way (the paper's "
                             "parallel unroll); the runs are named video_jepa_<scale>_<unroll>_... "
                             "(the preset's own, parallel, keeps the plain name)")
    launch.add_flags(parser)
    return parser


def main(argv: list[str] | None = None) -> None:
    """Train (or load) and evaluate notebook 03's runs at a scale, printing AP per horizon.

    ``python -m research.train_video --scale class`` trains the K ablation
    (K 1, 2, 4, 8 times three seeds, 4-10 minutes each on a CPU; ``--long``: the preset's
    long runs, K 1 and 4, about an hour each on one thread; a run of one seed hands its
    K = 1 half to the seed's other K, which train only their second half) into
    ``data/cache/checkpoints/``, where the notebook finds them; an interrupted
    run resumes; ``--ship`` also writes float16 copies to ``checkpoints/``. Same digits,
    clips and probe protocol as the notebook. Under torchrun every process trains each run
    (global batch = per-rank batch x world size); rank 0 saves and evaluates.
    """
    parser = _parser()
    args = parser.parse_args(argv)
    cfg = preset("03", args.scale)
    try:
        configs = (cfg.long_runs(args.K, args.seed) if args.long else
                   ablation_configs(cfg.train, args.K or cfg.rollout_steps, args.seed or cfg.seeds))
    except ValueError as error:
        parser.error(str(error))  # checked before the data is loaded
    if args.unroll not in (None, cfg.train.unroll):
        configs = [replace(c, unroll=args.unroll) for c in configs]
    device = launch.join(parser, args, cfg.train.batch_size, [identity(c) for c in configs],
                         "research.train_video")
    try:
        _train_and_report(args, cfg, configs, device)
    finally:
        launch.shutdown()


def notebook():
    """Notebook 03's loop, ``train_video_jepa``, and its ``train_or_load``, read from its cells."""
    return definitions("03_video_jepa.ipynb", "train_video_jepa", "train_or_load")


def shares_start_with(config: VideoJEPAConfig, other: VideoJEPAConfig) -> bool:
    """Whether ``other`` is ``config`` with another K, hence the same run until the switch to K
    steps (the curriculum trains K = 1 first)."""
    return (other.rollout_steps != config.rollout_steps and config.switch_step > 0
            and replace(other, rollout_steps=config.rollout_steps) == config)


def not_started(siblings: list[tuple[VideoJEPAConfig, str]]) -> list[tuple[VideoJEPAConfig, Path]]:
    """``(config, its .partial)`` of the runs ``(config, name)`` with no file yet, shipped or
    cached."""
    waiting = []
    for config, name in siblings:
        cache_path, shipped = checkpoint_paths(name)
        partial = cache_path.with_suffix(".partial")
        if not any(path.exists() for path in (cache_path, shipped, partial)):
            waiting.append((config, partial))
    return waiting


def handover(config: VideoJEPAConfig, waiting: list[tuple[VideoJEPAConfig, Path]]):
    """``after`` for ``train_video_jepa``: at the switch, the state of the run ``config`` saved as
    that of each ``waiting`` run (``config`` with another K) to its path, so that those train
    only their K-step half."""
    for other, _ in waiting:
        if not shares_start_with(config, other):
            raise ValueError(f"a run can hand over its K = 1 half only to the same run with "
                             f"another K; got {other} for {config}")

    def after(done: int, parts, history) -> None:
        if done == config.switch_step:
            for other, path in waiting:
                save_or_warn(Path(path), **training_state(done, identity(other), history, *parts))

    return after


def _say(text: str) -> None:
    if distributed.is_main():  # one process prints
        print(text)


def _train_and_report(args, cfg, configs, device) -> None:
    train_digits, held_out = split_digits(load_mnist("test")[0], n_train=cfg.n_train_digits)
    probe_data, eval_data = evaluation_clips(train_digits, held_out, cfg.n_probe, cfg.n_eval,
                                             cfg.train.n_frames)
    _say(f"protocol: AP per horizon 1..{cfg.horizons} of a detection probe on frozen latents, "
         f"fitted on {cfg.n_probe} clips of training digits, scored on {cfg.n_eval} clips of "
         f"{len(held_out)} held-out MNIST test digits")
    torch.manual_seed(cfg.train.seed)
    runs = [("random init", VideoJEPA(cfg.train.model).eval())]
    scale = f"{args.scale}_long" if args.long else args.scale  # names the checkpoints
    if configs[0].unroll != cfg.train.unroll:  # --unroll: another way than the preset's
        scale += f"_{configs[0].unroll}"
    train_or_load = notebook().train_or_load
    for config in configs:
        start, name = time.perf_counter(), run_name(scale, config)
        # runs of this seed with another K start as this one: they resume from its switch
        waiting = not_started([(c, run_name(scale, c)) for c in configs
                               if shares_start_with(config, c)])
        model, history = train_or_load(config, name, train_digits, video_jepa_step, device,
                                       handover(config, waiting))
        if args.ship and distributed.is_main():
            shipped = checkpoint_paths(name)[1]
            save_checkpoint(shipped, model=float16_state(model), history=dict(history),
                            config=identity(config, train_digits),
                            seconds=getattr(history, "seconds", 0.0))
            _say(f"{name}: wrote {shipped} (float16)")
        _say(f"{name}: ready in {time.perf_counter() - start:.0f} s on "
             f"{distributed.world_size()} process(es)")
        runs.append((f"K={config.rollout_steps} seed={config.seed}", model))
    if not distributed.is_main():
        return
    for label, model in runs:
        for unroll in ("parallel", "autoregressive"):  # the paper's protocol, then a planner's
            report = detection_report(model.cpu(), probe_data, eval_data, cfg.horizons,
                                      cfg.probe_steps, unroll=unroll)
            aps = " ".join(f"{ap:.3f}" for ap in report["ap"].tolist())
            print(f"{label}, {unroll} protocol: mAP {report['map']:.3f} (AP {aps}; true "
                  f"encodings {report['map_encoded']:.3f}, copy {report['map_copy']:.3f})")


if __name__ == "__main__":
    main()
