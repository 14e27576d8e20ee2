"""Train the Two Rooms world model of a scale and save it, or refit a trained model's predictor.

    python -m research.train_world --out FILE.pt [--steps N] [--without TERM]
    python -m research.train_world --paper-recipe --steps 10000 --out FILE.pt
    python -m research.train_world --refit TRAINED.pt --out FILE.pt

On several devices, one process each (DistributedDataParallel; nccl on GPUs, gloo on CPUs):

    torchrun --nproc_per_node=N -m research.train_world --scale full --out FILE.pt

The preset's batch size is the global batch: global batch = per-rank batch x N, so N must
divide it. Every loss term is that of the global batch, as on one device (the model has no
batch norm). Rank 0 alone writes the files; a stopped run resumes on any N. The refit runs in
one process.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import fields, replace
from pathlib import Path

import torch

from ebjepa_tutorial import distributed
from ebjepa_tutorial.course.presets import SCALES, preset
from ebjepa_tutorial.envs import generate_trajectories
from ebjepa_tutorial.envs.two_rooms import WALL_X_RANGES
from ebjepa_tutorial.evaluation.position import middle_wall_test, probe_report
from ebjepa_tutorial.losses.world import WorldLossCoeffs
from ebjepa_tutorial.models.world import WorldConfig
from ebjepa_tutorial.training.checkpoints import (
    CheckpointError,
    load_checkpoint,
    save_checkpoint,
)
from ebjepa_tutorial.training.world import (
    ABLATABLE_TERMS,
    WorldTrainConfig,
    ablation_config,
    identity,
    load_world_model,
    make_data,
    paper_recipe,
    world_model_step,
)
from ebjepa_tutorial.utils import get_device

from . import launch
from .from_notebook import definitions
from .refit import RefitConfig, refit_identity, refit_predictor


def _parser() -> argparse.ArgumentParser:
    """The command line: how a new model trains, or ``--refit`` with the refit's options."""
    parser = argparse.ArgumentParser(description="Train the Two Rooms world model.")
    parser.add_argument("--out", required=True, help="where to write the trained model")
    parser.add_argument("--scale", choices=SCALES,
                        help="train notebook 05's run of this scale (default: class). Its batch "
                             "size is the global batch over all processes: global batch = "
                             "per-rank batch x world size")
    parser.add_argument("--refit", metavar="TRAINED.pt",
                        help="fit a new MLP predictor on this trained model's frozen latents")
    parser.add_argument("--paper-recipe", action="store_true",
                        help="train the scale's model the paper's way (whole trajectories, GRU "
                             "predictor, no replay; chapter 06's long runs) instead of the "
                             "course's (training.world.course_recipe)")
    parser.add_argument("--steps", type=int,
                        help=f"default: the scale's ({preset('05', 'class').train.steps} at "
                             f"class; {RefitConfig.steps} with --refit)")
    parser.add_argument("--trajectories", type=int,
                        help=f"size of the offline data set (the paper: 100,000); default "
                             f"{preset('05', 'class').train.n_trajectories} at class "
                             f"({RefitConfig.n_trajectories} with --refit)")
    parser.add_argument("--decay-steps", type=int,
                        help="lower the learning rate linearly to 0 over the last N steps")
    parser.add_argument("--without", action="append", default=[], choices=ABLATABLE_TERMS,
                        help="an ablation: set this term's coefficient to 0 (repeatable)")
    parser.add_argument("--no-inverse-dynamics", action="store_true",
                        help="the same as --without inverse_dynamics")
    parser.add_argument("--coeff", action="append", default=[], metavar="NAME=VALUE",
                        help="set one loss weight, e.g. covariance=1 (repeatable)")
    parser.add_argument("--wall-fraction", type=float,
                        help="the share of trajectories that start in front of the middle wall, "
                             "heading into it (0: the paper's data)")
    parser.add_argument("--window", type=int,
                        help="train on windows of this many frames cut at random offsets "
                             "(0: whole 17-frame trajectories)")
    parser.add_argument("--channels-last", action="store_true",
                        help="convolutions in channels_last (faster on CPUs too; changes the sums)")
    parser.add_argument("--predictor", choices=("gru", "mlp"),
                        help="the one-step predictor (default: the recipe's)")
    parser.add_argument("--predictor-hidden", type=int,
                        help="width of the MLP predictor's two hidden layers (default "
                             f"{WorldConfig.predictor_hidden})")
    parser.add_argument("--stay-probability", type=float,
                        help="the share of imagined steps that are still (zero action); "
                             f"with --refit, the refit's (default {RefitConfig.stay_probability})")
    parser.add_argument("--replay-steps", type=int,
                        help="predictor-only updates on replayed latents after each step "
                             "(0: none)")
    parser.add_argument("--grad-clip", type=float,
                        help="scale each update's gradient down to at most this norm (0: none)")
    parser.add_argument("--walls", type=int, choices=sorted(WALL_X_RANGES),
                        help="1: Two Rooms (default); 2: Three Rooms in a row (chapter 07)")
    parser.add_argument("--seed", type=int,
                        help=f"default {WorldTrainConfig.seed} ({RefitConfig.seed} with --refit)")
    launch.add_flags(parser)
    return parser


def _options(args) -> tuple[dict, dict]:
    """The given config fields and recipe fields (only those set on the command line)."""
    given = {name: value for name, value in (("steps", args.steps), ("seed", args.seed),
                                              ("n_trajectories", args.trajectories),
                                              ("walls", args.walls))
             if value is not None}
    recipe = {name: value for name, value in (("wall_fraction", args.wall_fraction),
                                               ("window", args.window),
                                               ("channels_last", args.channels_last or None),
                                               ("stay_probability", args.stay_probability),
                                               ("replay_steps", args.replay_steps),
                                               ("decay_steps", args.decay_steps),
                                               ("grad_clip", args.grad_clip))
              if value is not None}
    return given, recipe


def _refit(parser, args, given: dict, recipe: dict) -> None:
    """``--refit``: refuse the options that choose how a new model trains, then refit."""
    if "stay_probability" in recipe:  # the refit's still steps
        given["stay_probability"] = recipe.pop("stay_probability")
    training_only = {"--scale": args.scale, "--paper-recipe": args.paper_recipe,
                     "--without": args.without,
                     "--no-inverse-dynamics": args.no_inverse_dynamics,
                     "--coeff": args.coeff, "--predictor": args.predictor,
                     "--predictor-hidden": args.predictor_hidden is not None,
                     "--walls": args.walls is not None,
                     **{"--" + name.replace("_", "-"): True for name in recipe}}
    refused = [flag for flag, value in training_only.items() if value]
    if refused:
        parser.error(f"--refit keeps the trained model's encoder, so {', '.join(refused)} "
                     "cannot apply: they choose how a new model trains")
    if args.ddp or launch.launched_by_torchrun():
        parser.error("--refit runs in one process (a small MLP on precomputed latents): "
                     "start it with python -m, without torchrun or --ddp")
    try:  # checked before anything is fitted, as the training path's options are
        config = RefitConfig(**given)
        refit_base(args.refit)
    except (ValueError, FileNotFoundError, CheckpointError) as error:  # a missing or bad file
        parser.error(str(error))  # a usage message, not a traceback
    refit_main(args.refit, args.out, config)


def _config(args, given: dict, recipe: dict) -> WorldTrainConfig:
    """The run the options describe: the scale's preset, changed as asked (ValueError if not
    possible)."""
    base = preset("05", args.scale or "class").train
    if args.paper_recipe:
        base = paper_recipe(base)
    if args.predictor:
        base = replace(base, model=replace(base.model, predictor=args.predictor))
    if args.predictor_hidden is not None:
        if args.predictor_hidden < 1:
            raise ValueError(f"--predictor-hidden must be >= 1, got {args.predictor_hidden}")
        base = replace(base, model=replace(base.model, predictor_hidden=args.predictor_hidden))
    # one replace: a decay longer than the scale's steps must meet the new step count
    config = with_coeffs(replace(base, recipe=replace(base.recipe, **recipe), **given),
                         args.coeff)
    if config.steps < 1 or config.recipe.grad_clip < 0:
        raise ValueError("--steps takes an int >= 1, --grad-clip a number >= 0")
    return config


def main(argv: list[str] | None = None) -> None:
    """Train a world model at a scale and save it: the documented command for the checkpoint.

    ``--refit TRAINED.pt`` instead refits that model's predictor
    (:func:`~research.refit.refit_predictor`); ``--steps``, ``--trajectories``, ``--seed``
    and ``--stay-probability`` then set the refit's, and the training-only options are refused.
    """
    parser = _parser()
    args = parser.parse_args(argv)
    given, recipe = _options(args)
    if args.refit:
        return _refit(parser, args, given, recipe)
    try:
        config = _config(args, given, recipe)
    except ValueError as error:
        parser.error(str(error))  # a usage message, not a traceback
    without = args.without + (["inverse_dynamics"] if args.no_inverse_dynamics else [])
    config = ablation_config(config, *without)
    device = launch.join(parser, args, config.batch_size, identity(config),
                         "research.train_world")
    try:
        _train_and_save(args.out, config, device)
    finally:
        launch.shutdown()


def with_coeffs(config: WorldTrainConfig, pairs: list[str]) -> WorldTrainConfig:
    """``config`` with loss weights set from ``"name=value"`` strings, e.g. ``["covariance=1"]``."""
    names = [f.name for f in fields(WorldLossCoeffs)]
    values = {}
    for pair in pairs:
        name, sep, value = pair.partition("=")
        if not sep or name not in names:
            raise ValueError(f"--coeff wants name=value with a name from {names}, got {pair!r}")
        try:
            values[name] = float(value)
        except ValueError:
            raise ValueError(f"--coeff {pair!r}: {value!r} is not a number") from None
        if not math.isfinite(values[name]) or values[name] < 0:
            raise ValueError(f"--coeff {pair!r}: a loss weight must be finite and >= 0")
    return replace(config, coeffs=replace(config.coeffs, **values))


def _train_and_save(out: str, config: WorldTrainConfig, device) -> None:
    """Train ``config`` (every process) and save it to ``out`` with its probe error (rank 0)."""
    partial = Path(out).with_suffix(".partial")  # resumable while training
    model, history = train_world_model(config, checkpoint=partial, device=device)
    if not distributed.is_main():
        return
    report = probe_report(model, walls=config.walls)
    save_checkpoint(out, model=model.state_dict(), history=dict(history),
                    config=identity(config), probe_px=report["probe_px"],
                    processes=distributed.world_size())
    partial.unlink(missing_ok=True)  # gone if its folder could not be written
    print(f"saved {out}: probe error {report['probe_px']:.2f} px (mean-position baseline "
          f"{report['baseline_px']:.2f} px) on {distributed.world_size()} process(es)")


def notebook():
    """Notebook 05's loop, ``train_world_model``, and its ``train_or_load``, read from its cells."""
    return definitions("05_world_model.ipynb", "train_world_model", "train_or_load")


def train_world_model(config: WorldTrainConfig, checkpoint=None, device=None,
                      step=world_model_step, progress: bool = True):
    """``config`` trained on its trajectories by notebook 05's loop (every shipped world model's)
    with ``step``: ``(model in eval mode, history)``, resumable from ``checkpoint``."""
    return notebook().train_world_model(config, make_data(config), step, checkpoint, device,
                                        progress)


def refit_base(trained: str) -> dict:
    """The checkpoint at ``trained``, if a refit can use it (ValueError if not)."""
    base = load_checkpoint(trained)
    if base.get("config", {}).get("walls", 1) != 1:  # the refit's data and wall test: Two Rooms
        raise ValueError(f"{trained} was trained in a world of {base['config']['walls']} walls; "
                         "the refit fits and tests Two Rooms data only")
    return base


def refit_main(trained: str, out: str, config: RefitConfig) -> None:
    """Refit the predictor of the model saved at ``trained``; save it to ``out`` with the
    trained model's stored config (``"base"``), and print the wall test before and after.
    Both models are on the best available device (cuda, mps, cpu)."""
    base = refit_base(trained)
    device = get_device()
    model = load_world_model(trained, device=device)  # it encodes every refit trajectory
    new, history = refit_predictor(model, config, device=device)
    walls = generate_trajectories(400, seed=778)  # notebook 06's wall test
    with torch.no_grad():
        before, after = middle_wall_test(model, walls), middle_wall_test(new, walls)
    save_checkpoint(out, model=new.state_dict(), history=dict(history),
                    config=refit_identity(config, base["config"]),
                    probe_px=base.get("probe_px"))
    print(f"saved {out}: the wall test stops {after['stopped']:.0%} of the wall's steps and "
          f"moves {after['moved']:.0%} of the free ones (before: {before['stopped']:.0%} and "
          f"{before['moved']:.0%})")


if __name__ == "__main__":
    main()
