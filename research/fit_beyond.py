"""Fit chapter 07's cost head and coarse model on a world model's frozen latents, and save them.

    python -m research.fit_beyond --world two_rooms --out-dir checkpoints
    python -m research.fit_beyond --world three_rooms --out-dir checkpoints

The world model is notebook 07's at ``--scale`` (shipped, cached, or trained first); the
fits are ``preset("07").cost`` and ``.coarse`` for that world. Writes
``cost_head_<world>_<scale>.pt`` and ``coarse_<world>_<scale>.pt`` (``--fits coarse``: the
second alone), each with the identity of its fit and of the world model, which notebook
07 checks before it loads a file.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

from ebjepa_tutorial.course.presets import SCALES, preset
from ebjepa_tutorial.planning import two_level_episodes
from ebjepa_tutorial.training.checkpoints import run_identity, save_checkpoint
from ebjepa_tutorial.training.cost import fit_cost_head
from ebjepa_tutorial.training.hierarchy import fit_coarse_with_visits
from ebjepa_tutorial.training.runs import train_or_load
from ebjepa_tutorial.training.world import identity

WORLDS = {"two_rooms": 1, "three_rooms": 2}
FITS = {"cost_head": fit_cost_head,
        "coarse": lambda model, fit: fit_coarse_with_visits(model, fit, two_level_episodes)}


def world_run(world: str, scale: str):
    """``(walls, world model config, its file name)`` of notebook 07's ``world`` at ``scale``."""
    cfg, walls = preset("07", scale), WORLDS[world]
    name = f"world_model_{scale}" if walls == 1 else f"world_model_{world}_{scale}"
    return walls, cfg.two_rooms if walls == 1 else cfg.three_rooms, name


def fit_configs(world: str, scale: str):
    """``(CostConfig, CoarseFit)``: notebook 07's fits for ``world`` at ``scale``."""
    cfg, walls = preset("07", scale), WORLDS[world]
    return replace(cfg.cost, walls=walls), cfg.coarse_fit(walls)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", choices=sorted(WORLDS), required=True)
    parser.add_argument("--scale", choices=SCALES, default="class")
    parser.add_argument("--out-dir", required=True, help="folder for the two files")
    parser.add_argument("--fits", nargs="+", choices=sorted(FITS), default=sorted(FITS),
                        help="refit only these (default: both)")
    args = parser.parse_args(argv)
    _, config, name = world_run(args.world, args.scale)
    model, _ = train_or_load(config, name, device="cpu")
    configs = dict(zip(("cost_head", "coarse"), fit_configs(args.world, args.scale)))
    for kind in args.fits:
        fit, fit_config = FITS[kind], configs[kind]
        start = time.perf_counter()
        fitted, history = fit(model, fit_config)
        seconds = time.perf_counter() - start
        path = Path(args.out_dir) / f"{kind}_{args.world}_{args.scale}.pt"
        save_checkpoint(path, model=fitted.state_dict(), history=dict(history),
                        config=run_identity(fit_config, base=identity(config)), seconds=seconds)
        print(f"saved {path} ({seconds:.0f} s)")


if __name__ == "__main__":
    main()
