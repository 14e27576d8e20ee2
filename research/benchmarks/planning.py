"""Planning benchmark: success rate of a planner with a world-model checkpoint in Two Rooms.

Run: ``python -m research.benchmarks.planning
[--checkpoint checkpoints/world_model_class_course_long.pt] [--method mppi|cem]
[--cost sum|last] [--episodes 100] [--batch 10] [--threads 2]``.

Protocol: one episode per seed ``first_seed .. first_seed + episodes - 1``
(layout, start and goal in opposite rooms, and the planner's noise all come
from that seed); success when the dot ends within 4.5 px of the goal after
200 steps. ``--walls 2`` plays Three Rooms instead (start and goal in the
outer rooms, 120 steps; ``--steps`` sets another length) with a model
trained there. Episodes run ``--batch`` at a time. Prints the success rate with
its Wilson 95% interval, the mean first-arrival step (episodes that
arrived), and process CPU seconds per episode (all threads counted). Last
line: ``success=... ci_low=... ci_high=... s_per_episode=...``. ``--record``
(one of the seven models of ``RECORDED``, the chapter's planner, first seed 10,000)
stores the success rate in ``checkpoints/reference.json``: notebook 06 prints the
first three models' beside the learner's, RESULTS.md states the four ablations'.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import torch

from ebjepa_tutorial.envs.two_rooms import WALL_X_RANGES
from ebjepa_tutorial.planning import METHODS, PlannerConfig, run_episodes
from ebjepa_tutorial.training.checkpoints import load_checkpoint
from ebjepa_tutorial.training.world import load_world_model
from research.benchmarks import command_line
from tools import figures

# the checkpoints whose success rates notebook 06 prints beside the learner's, and chapter 05's
# class run without one loss term (the paper's Table 4 at class length, RESULTS.md)
RECORDED = {"world_model_class.pt": "planning_success_class",
            "world_model_class_course_long.pt": "planning_success_shipped",
            "world_model_class_long20k_mlp.pt": "planning_success_refit",
            **{f"world_model_class_{suffix}.pt": f"planning_success_{suffix}"
               for suffix in ("no_variance", "no_covariance", "no_temporal", "no_idm")}}
# the planner settings with a fixed set of values: a typo is a usage error. No "learned" cost:
# it needs a cost head (chapter 07's), which this command does not load
CHOICES = {"method": METHODS, "cost": ("sum", "last")}


def _yes_no(text: str) -> bool:
    if text.lower() not in ("true", "false", "yes", "no", "1", "0"):
        raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}")
    return text.lower() in ("true", "yes", "1")


def _settings(config, prefix: str = "") -> dict:
    """``{flag name: default}`` of every setting of ``config``; a nested group's are named
    ``group_field`` (``noise_period`` for ``noise.period``)."""
    out = {}
    for field in dataclasses.fields(config):
        value, name = getattr(config, field.name), prefix + field.name
        out.update(_settings(value, name + "_") if dataclasses.is_dataclass(value)
                   else {name: value})
    return out


def _chosen(config, args, prefix: str = ""):
    """``config`` with every setting the flags of :func:`_settings` chose."""
    def value(field):
        inner = getattr(config, field.name)
        if dataclasses.is_dataclass(inner):
            return _chosen(inner, args, f"{prefix}{field.name}_")
        return getattr(args, prefix + field.name)

    return dataclasses.replace(config, **{f.name: value(f) for f in dataclasses.fields(config)})


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", default="checkpoints/world_model_class_course_long.pt",
                        help="world model (default: chapter 05's recipe trained longer in one "
                             "stage; chapter 05's: world_model_class.pt; the paper's recipe "
                             "trained as long as the paper with its predictor refitted: "
                             "world_model_class_long20k_mlp.pt)")
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--batch", type=int, default=10,
                        help="episodes planned at once (small batches stay in a CPU cache)")
    parser.add_argument("--first-seed", type=int, default=10_000)
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument("--walls", type=int, choices=sorted(WALL_X_RANGES), default=1,
                        help="1: Two Rooms; 2: Three Rooms (a model trained with --walls 2)")
    parser.add_argument("--steps", type=int, default=None,
                        help="episode length (default: the world's budget, 200 or 120)")
    for name, default in _settings(PlannerConfig()).items():  # --method, ..., --noise-period
        kind = _yes_no if isinstance(default, bool) else type(default)
        parser.add_argument(f"--{name.replace('_', '-')}", type=kind, default=default,
                            choices=CHOICES.get(name))
    parser.add_argument("--record", action="store_true",
                        help="store the success rate in checkpoints/reference.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    config = _chosen(PlannerConfig(), args)
    key = RECORDED.get(Path(args.checkpoint).name)
    if args.record and (key is None or config != PlannerConfig() or args.first_seed != 10_000
                        or args.walls != 1 or args.steps is not None):
        parser.error(f"--record stores the chapter's planner (no planner options, first seed "
                     f"10000, Two Rooms at its 200 steps) with one of {sorted(RECORDED)}")
    model = load_world_model(args.checkpoint)
    # a model's identity records its world's walls where they are not Two Rooms' one (a refit,
    # "base" alone, is Two Rooms only); a file without an identity cannot be checked
    stored = load_checkpoint(args.checkpoint).get("config")
    if stored is not None and stored.get("walls", 1) != args.walls:
        parser.error(f"{args.checkpoint} was trained with --walls {stored.get('walls', 1)}; "
                     f"it cannot plan in a world of --walls {args.walls}")
    seeds = list(range(args.first_seed, args.first_seed + args.episodes))
    result = run_episodes(model, seeds, config, steps=args.steps, batch=args.batch,
                          walls=args.walls)
    low, high = result.interval()
    print(f"{args.checkpoint}, {config}")
    print(f"{result.summary()}; {result.wall_seconds / len(seeds):.2f} s wall per episode "
          f"on {args.threads} threads")
    print(f"success={result.success_rate:.3f} ci_low={low:.3f} ci_high={high:.3f} "
          f"s_per_episode={result.cpu_seconds_per_episode:.2f}")
    if args.record:
        figures.record(key, result.success_rate, threads=args.threads,
                         command=command_line(__spec__.name),
                         protocol=f"{args.checkpoint}; {len(seeds)} episodes, seeds "
                                  f"{seeds[0]}-{seeds[-1]}; 200 steps; success within 4.5 px; "
                                  f"{agent(config)}")


def agent(config: PlannerConfig) -> str:
    """The planner in a few words, for the record's protocol."""
    warm = config.warm().iterations
    stop_px = config.habits.stop_px
    stop = f"stands still within {stop_px:g} px" if stop_px else "never stops"
    return (f"{config.method.upper()} H{config.horizon} N{config.samples} "
            f"J{config.iterations} ({warm} warm), first spread {config.noise.std:g} px, "
            f"re-plan every {config.execute}, {stop}")


if __name__ == "__main__":
    main()
