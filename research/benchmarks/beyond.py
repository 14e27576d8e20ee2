"""Chapter 07 benchmark: flat, short-horizon, learned-cost and two-level planners.

Run: ``python -m research.benchmarks.beyond [--walls 1 2] [--episodes 200] [--first-seed 12600]
[--threads 2] [--batch 10] [--planners flat short learned_cost two_level] [--record]``.

Protocol: for each world (``--walls 1``: Two Rooms with chapter 05's shipped
class model; ``2``: Three Rooms with ``checkpoints/world_model_three_rooms_class.pt``)
one episode per seed from ``--first-seed`` (layout, start and goal in the outer
rooms, and the planner's noise all come from the seed); success when the dot
ends within 4.5 px of the goal at the end of the world's step budget (200 and
120 steps). The planners are notebook 07's at class scale
(``course.presets.preset("07", "class")``); the cost heads and the coarse models
are the shipped ones (notebook 07's ``load_fit``; ``research.fit_beyond`` makes
them). Each row: the success rate, its Wilson 95% interval and the process CPU
seconds per episode (all threads counted). Last line, for
the last world played:
``world=... flat=... short=... learned_cost=... two_level=... s_per_episode=...``
(s_per_episode: the best new planner's). ``--record`` (200 episodes, the recorded protocol's
size) stores every rate in ``checkpoints/reference.json`` as the figures notebook 07 prints
beside its own.
"""

from __future__ import annotations

import argparse

import torch

from ebjepa_tutorial.course.presets import preset
from ebjepa_tutorial.planning import run_episodes
from ebjepa_tutorial.training.world import identity, load_run
from research import fit_beyond
from research.benchmarks import command_line
from research.beyond_fits import NOTEBOOK as NB
from tools import figures

WORLDS = {walls: world for world, walls in fit_beyond.WORLDS.items()}  # 1: "two_rooms", ...
NEW = ("learned_cost", "two_level")
RECORDED_EPISODES = 200  # a world's rates in reference.json: 200 episodes from each first seed
PLANNERS = ["flat", "short", *NEW]


def planners(walls: int) -> dict:
    """Each planner of the comparison: ``name: (model to plan with, PlannerConfig, two_level)``."""
    cfg, world = preset("07", "class"), WORLDS[walls]
    _, config, name = fit_beyond.world_run(world)
    model = load_run(config, name, device="cpu")
    head = NB.load_fit("cost_head", world, NB.CostToGo(model.latent_dim), identity(config))
    coarse = NB.load_fit("coarse", world, NB.CoarseModel(model.latent_dim), identity(config))
    two = cfg.two_level
    return {"flat": (model, cfg.flat, None), "short": (model, cfg.short, None),
            "learned_cost": (NB.WithLearnedCost(model, head), cfg.learned, None),
            "two_level": (model, two.low, NB.TwoLevel(coarse, two.high[walls - 1], two.lookahead,
                                                      two.reach_px))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--walls", type=int, nargs="+", choices=sorted(WORLDS), default=[1, 2])
    parser.add_argument("--episodes", type=int, default=RECORDED_EPISODES)
    parser.add_argument("--first-seed", type=int, default=12_600)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--batch", type=int, default=10)
    parser.add_argument("--planners", nargs="+", choices=PLANNERS, default=PLANNERS,
                        help="play only these (the last line then lacks the others)")
    parser.add_argument("--record", action="store_true",
                        help="store the rates as notebook 07's reference figures")
    args = parser.parse_args()
    if args.record and args.episodes != RECORDED_EPISODES:  # a smaller run's rate is too noisy
        parser.error(f"--record stores the recorded protocol's rates: {RECORDED_EPISODES} "
                     "episodes (drop --episodes)")
    torch.set_num_threads(args.threads)
    seeds = list(range(args.first_seed, args.first_seed + args.episodes))
    for walls in args.walls:
        name, rates, cpu = WORLDS[walls], {}, {}
        for planner, (imagine, config, two_level) in planners(walls).items():
            if planner not in args.planners:
                continue
            result = run_episodes(imagine, seeds, config, batch=args.batch, walls=walls,
                                  two_level=two_level)
            rates[planner], cpu[planner] = result.success_rate, result.cpu_seconds_per_episode
            print(f"{name:11s} {planner:12s} {result.summary()}", flush=True)
            if args.record:
                figures.record(
                    f"beyond_{name}_{planner}", result.success_rate, threads=args.threads,
                    command=command_line(__spec__.name),
                    protocol=f"{name}, {len(seeds)} episodes, seeds {seeds[0]}-{seeds[-1]}; "
                             "the world's step budget; success within 4.5 px; notebook 07's "
                             f"class planners; {cpu[planner]:.2f} s CPU per episode")
        played = [planner for planner in NEW if planner in rates]
        best = f" s_per_episode={cpu[max(played, key=rates.get)]:.2f}" if played else ""
        print(f"world={name} " + " ".join(f"{k}={v:.3f}" for k, v in rates.items()) + best)


if __name__ == "__main__":
    main()
