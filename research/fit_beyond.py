"""Fit chapter 07's cost head and coarse model on a world model's frozen latents, and save them.

    python -m research.fit_beyond --world two_rooms --out-dir checkpoints
    python -m research.fit_beyond --world three_rooms --out-dir checkpoints

The world model is notebook 07's (chapter 05's class run on ``--world``: shipped, cached, or
trained first); the fits are ``research.beyond_fits``' (:func:`fit_configs`). Writes
``cost_head_<world>_class.pt`` and ``coarse_<world>_class.pt`` (``--fits coarse``: the second
alone), each with the identity of its fit and of the world model; notebook 07 loads them
(its ``load_fit``) after checking the world model's. ``--tiny`` fits in seconds, to
check that the command runs; ``--set`` and ``--walks-only`` make the notebook's exercises'
variants (in another ``--out-dir``).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import fields, replace
from pathlib import Path

from ebjepa_tutorial.course.presets import preset
from ebjepa_tutorial.training.checkpoints import SHIPPED_DIR, run_identity, save_checkpoint
from ebjepa_tutorial.training.world import identity, load_run

from .beyond_fits import (
    CoarseConfig,
    CoarseFit,
    CostConfig,
    fit_coarse_model,
    fit_coarse_with_visits,
    fit_cost_head,
)

WORLDS = {"two_rooms": 1, "three_rooms": 2}
FITS = ("coarse", "cost_head")
# --tiny: a few Adam steps on a few trajectories, and notebook 07's ci planners for the visits
TINY_COST = dict(n_trajectories=200, trajectory_steps=16, layouts=10, steps=30, batch_size=64,
                 hidden=32, dims=8)
TINY_COARSE = dict(n_trajectories=200, steps=30, batch_size=64, hidden=32)


def world_run(world: str):
    """``(walls, world model config, its file name)`` of notebook 07's ``world``."""
    cfg, walls = preset("07", "class"), WORLDS[world]
    name = "world_model_class" if walls == 1 else f"world_model_{world}_class"
    return walls, cfg.two_rooms if walls == 1 else cfg.three_rooms, name


def fit_configs(world: str, tiny: bool = False) -> tuple[CostConfig, CoarseFit]:
    """``(CostConfig, CoarseFit)``: the shipped fits for ``world`` (``tiny``: a quick check's)."""
    walls = WORLDS[world]
    two = preset("07", "ci" if tiny else "class").two_level
    cost = CostConfig(walls=walls, **(TINY_COST if tiny else {}))
    coarse = CoarseConfig(walls=walls, **(TINY_COARSE if tiny else {}))
    visits = dict(episodes=2, steps=16) if tiny else {}
    return cost, CoarseFit(coarse, two.low, two.high[walls - 1], two.lookahead, two.reach_px,
                           **visits)


def changed(config, settings: list[str]):
    """``config`` with the ``FIELD=VALUE`` of ``settings`` that name its fields (as their type)."""
    types = {f.name: type(getattr(config, f.name)) for f in fields(config)}
    pairs = [setting.split("=", 1) for setting in settings]
    return replace(config, **{k: types[k](v) for k, v in pairs if k in types})


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", choices=sorted(WORLDS), required=True)
    parser.add_argument("--out-dir", required=True, help="folder for the two files")
    parser.add_argument("--fits", nargs="+", choices=FITS, default=FITS,
                        help="fit only these (default: both)")
    parser.add_argument("--tiny", action="store_true", help="a few steps, to check it runs")
    parser.add_argument("--set", nargs="+", default=[], metavar="FIELD=VALUE",
                        help="change fields of CostConfig or CoarseConfig (research.beyond_fits), "
                             "e.g. consistency=0 trajectory_steps=16")
    parser.add_argument("--walks-only", action="store_true",
                        help="the coarse model on the random walks alone, without its planner's "
                             "episodes")
    args = parser.parse_args(argv)
    known = {f.name for config in (CostConfig, CoarseConfig) for f in fields(config)}
    unknown = [s for s in args.set if s.split("=", 1)[0] not in known or "=" not in s]
    if unknown:
        parser.error(f"--set {unknown}: not FIELD=VALUE of CostConfig or CoarseConfig")
    # the variants keep the shipped files' names: written there, they would replace the fits
    # notebook 07 loads (its load_fit checks only the world model's identity)
    variants = [flag for flag, given in (("--tiny", args.tiny), ("--set", args.set),
                                         ("--walks-only", args.walks_only)) if given]
    if variants and Path(args.out_dir).resolve() == SHIPPED_DIR.resolve():
        parser.error(f"{', '.join(variants)} would overwrite the shipped fits in {SHIPPED_DIR}: "
                     "give another --out-dir")
    _, config, name = world_run(args.world)
    model = load_run(config, name, device="cpu")
    cost, coarse = fit_configs(args.world, args.tiny)
    cost, coarse = changed(cost, args.set), replace(coarse, coarse=changed(coarse.coarse, args.set))
    jobs = {"cost_head": (fit_cost_head, cost),
            "coarse": (fit_coarse_model, coarse.coarse) if args.walks_only
            else (fit_coarse_with_visits, coarse)}
    for kind in args.fits:
        fit, fit_config = jobs[kind]
        start = time.perf_counter()
        fitted, history = fit(model, fit_config)
        seconds = time.perf_counter() - start
        path = Path(args.out_dir) / f"{kind}_{args.world}_class.pt"
        save_checkpoint(path, model=fitted.state_dict(), history=dict(history),
                        config=run_identity(fit_config, base=identity(config)), seconds=seconds)
        print(f"saved {path} ({seconds:.0f} s)")


if __name__ == "__main__":
    main()
