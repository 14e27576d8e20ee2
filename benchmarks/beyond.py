"""Chapter 07 benchmark: flat, short-horizon, learned-cost and two-level planners.

Run: ``python benchmarks/beyond.py [--walls 1 2] [--episodes 200] [--first-seed 12600]
[--threads 2] [--batch 10]``.

Protocol: for each world (``--walls 1``: Two Rooms with chapter 05's shipped
class model; ``2``: Three Rooms with ``checkpoints/world_model_three_rooms_class.pt``)
one episode per seed from ``--first-seed`` (layout, start and goal in the outer
rooms, and the planner's noise all come from the seed); success when the dot
ends within 4.5 px of the goal within the world's step budget (``STEPS``). The
cost head and the coarse model are loaded from ``checkpoints/`` or the cache,
or fitted on the world model's frozen latents (minutes). Each row: the success
rate, its Wilson 95% interval and the process CPU seconds per episode (all
threads counted). Last line, for the last world played:
``world=... flat=... short=... learned_cost=... two_level=... s_per_episode=...``
(s_per_episode: the best new planner's).
"""

from __future__ import annotations

import argparse
import dataclasses

import torch

from ebjepa_tutorial.envs import MAX_STEP
from ebjepa_tutorial.models.cost import WithLearnedCost
from ebjepa_tutorial.planning import PlannerConfig, TwoLevel, run_episodes
from ebjepa_tutorial.training.checkpoints import load_checkpoint, stored_identity
from ebjepa_tutorial.training.cost import CostConfig, cost_head_or_load
from ebjepa_tutorial.training.hierarchy import CoarseConfig, coarse_or_load
from ebjepa_tutorial.training.world import load_world_model, upgrade_identity

WORLDS = {1: ("two_rooms", "checkpoints/world_model_class.pt"),
          2: ("three_rooms", "checkpoints/world_model_three_rooms_class.pt")}
STEPS = {1: None, 2: None}  # None: the world's own budget (200, 300 steps)
SHORT = PlannerConfig(horizon=16, samples=100, elites=10)
LEARNED = dataclasses.replace(SHORT, cost="learned", temperature=1.0)
# the two-level planner (chosen on seeds 10,600-10,699): a lower level of 8 steps aiming at
# the coarse plan's latent 2 coarse steps (8 steps) ahead; the coarse plan looks 16 coarse
# steps (64 steps) ahead in Two Rooms, and 24 (96 steps) with more samples in Three Rooms
LOW = PlannerConfig(horizon=8, samples=50, elites=5, warm_iterations=2)
STRIDE = CoarseConfig.stride
HIGH = PlannerConfig(horizon=16, samples=50, elites=5, warm_iterations=2, execute=1,
                     noise_period=2, action_bound=STRIDE * MAX_STEP, init_std=STRIDE * 1.5,
                     max_std=STRIDE * 2.0, stop_px=0)
HIGHS = {1: HIGH, 2: dataclasses.replace(HIGH, horizon=24, samples=100, elites=10,
                                         warm_iterations=3)}
NEW = ("learned_cost", "two_level")


def planners(model, base: dict, walls: int, name: str) -> dict:
    """Each planner of the comparison: ``(model to plan with, PlannerConfig, two_level)``."""
    head = cost_head_or_load(model, base, CostConfig(walls=walls), f"cost_head_{name}_class")
    coarse = coarse_or_load(model, base, CoarseConfig(walls=walls), f"coarse_{name}_class")
    return {"flat": (model, PlannerConfig(), None),
            "short": (model, SHORT, None),
            "learned_cost": (WithLearnedCost(model, head), LEARNED, None),
            "two_level": (model, LOW, TwoLevel(coarse, HIGHS[walls], lookahead=2))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--walls", type=int, nargs="+", choices=sorted(WORLDS), default=[1, 2])
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--first-seed", type=int, default=12_600)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--batch", type=int, default=10)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    seeds = list(range(args.first_seed, args.first_seed + args.episodes))
    for walls in args.walls:
        name, path = WORLDS[walls]
        model = load_world_model(path)
        base = stored_identity(load_checkpoint(path), upgrade_identity)
        rates, cpu = {}, {}
        for planner, (imagine, config, two_level) in planners(model, base, walls, name).items():
            result = run_episodes(imagine, seeds, config, steps=STEPS[walls], batch=args.batch,
                                  walls=walls, two_level=two_level)
            rates[planner], cpu[planner] = result.success_rate, result.cpu_seconds_per_episode
            print(f"{name:11s} {planner:12s} {result.summary()}", flush=True)
        best = max(NEW, key=rates.get)
        print(f"world={name} " + " ".join(f"{k}={v:.3f}" for k, v in rates.items())
              + f" s_per_episode={cpu[best]:.2f}")


if __name__ == "__main__":
    main()
