"""Two Rooms benchmark: data generation speed, world-model training speed, probe error.

Run: ``python -m research.benchmarks.two_rooms [--n 4096] [--batch 256] [--threads 2] [--steps N]
[--out PATH] [--record]``.
Prints trajectories per second (17 frames, 16 actions) for the states alone
and with every 65x65x2 frame rendered (float32, in batches into one reused
buffer, as a training loop would); then trains notebook 05's class run (the
course's recipe) from scratch for ``--steps`` steps (default: the preset's,
about 9-15 minutes on 2 cores, ``world_train_min`` in ``checkpoints/reference.json``;
``--steps 0`` skips it) and reports training
trajectories per second, the linear position probe's error on held-out
trajectories (pixels) by notebook 05's protocol, and notebook 06's one-step
wall test. ``--out PATH``
saves the model for ``python -m research.benchmarks.planning --checkpoint PATH``.
Last line: ``traj_per_s=... train_traj_per_s=... probe_px=...``.
``--record`` (class preset's steps) stores the probe error in
``checkpoints/reference.json``, which notebook 05 prints beside the learner's.
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace

import torch

from ebjepa_tutorial.course.presets import preset
from ebjepa_tutorial.envs import generate_trajectories
from ebjepa_tutorial.evaluation.position import middle_wall_test, probe_report
from ebjepa_tutorial.training.checkpoints import save_checkpoint
from ebjepa_tutorial.training.world import identity
from research.benchmarks import command_line
from research.train_world import train_world_model
from tools import figures

CLASS_RUN = preset("05", "class")  # notebook 05's run, and its probe: fit seed 101, test 102


def _median_seconds(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def data_generation_speed(n: int = 4096, batch: int = 256, repeats: int = 3) -> dict[str, float]:
    """Trajectories per second: states only, rendering only, and both (all for 17 frames)."""
    data = generate_trajectories(n, seed=0)  # warm-up, and the data to render
    t_states = _median_seconds(lambda: generate_trajectories(n, seed=1), repeats)

    buffer = torch.empty(batch, 17, 2, 65, 65)  # reused, as a training loop would

    def render_all():
        for i in range(0, n - batch + 1, batch):
            data.frames(slice(i, i + batch), out=buffer)

    t_render = _median_seconds(render_all, repeats) * n / (n // batch * batch)
    return {
        "states_traj_per_s": n / t_states,
        "render_traj_per_s": n / t_render,
        "traj_per_s": n / (t_states + t_render),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=4096, help="trajectories per measurement")
    parser.add_argument("--batch", type=int, default=256, help="trajectories rendered at once")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument("--steps", type=int, default=CLASS_RUN.train.steps,
                        help="world-model training steps (0: data generation only)")
    parser.add_argument("--out", help="save the trained model here (for planning.py --checkpoint)")
    parser.add_argument("--record", action="store_true",
                        help="store the probe error in checkpoints/reference.json")
    args = parser.parse_args()
    if args.record and args.steps != CLASS_RUN.train.steps:
        parser.error("--record stores the class recipe's figure: drop --steps")
    torch.set_num_threads(args.threads)
    speed = data_generation_speed(args.n, args.batch)
    print(f"Two Rooms data, {args.n} trajectories of 17 frames, {args.threads} threads:")
    print(f"  states only (positions, actions, layouts): {speed['states_traj_per_s']:,.0f} traj/s")
    print(f"  rendering only (float32, batches of {args.batch}): "
          f"{speed['render_traj_per_s']:,.0f} traj/s")
    if args.steps == 0:
        print(f"traj_per_s={speed['traj_per_s']:.0f}")
        return
    config = replace(CLASS_RUN.train, steps=args.steps)
    start = time.perf_counter()
    model, history = train_world_model(config, device="cpu")
    seconds = time.perf_counter() - start
    train_speed = config.steps * config.batch_size / seconds
    report = probe_report(model, n_fit=CLASS_RUN.n_probe, n_test=CLASS_RUN.n_test, seed=101,
                          test_steps=CLASS_RUN.horizon)
    walls = middle_wall_test(model, generate_trajectories(400, seed=778))  # notebook 06's
    print(f"world model, {config.steps} steps of {config.batch_size} trajectories "
          f"in {seconds / 60:.1f} min: "
          f"{train_speed:.0f} traj/s; position probe {report['probe_px']:.2f} px (mean-position "
          f"baseline {report['baseline_px']:.2f} px); wall test: stopped {walls['stopped']:.0%} "
          f"of {walls['n_stopped']} wall-stopped steps, moved {walls['moved']:.0%} of "
          f"{walls['n_moved']} free steps")
    if args.out:
        save_checkpoint(args.out, model=model.state_dict(), history=dict(history),
                        config=identity(config), probe_px=report["probe_px"])
        print(f"saved {args.out}: play it with python -m research.benchmarks.planning --checkpoint "
              f"{args.out}")
    print(f"traj_per_s={speed['traj_per_s']:.0f} train_traj_per_s={train_speed:.1f} "
          f"probe_px={report['probe_px']:.3f}")
    if args.record:
        where = dict(threads=args.threads, command=command_line(__spec__.name))
        figures.record("world_probe_px", report["probe_px"], **where,
                       protocol=f"{config.steps} steps; linear probe fitted on "
                                f"{CLASS_RUN.n_probe} trajectories, scored on "
                                f"{CLASS_RUN.n_test} held-out ones of {CLASS_RUN.horizon} steps")
        figures.record("world_probe_baseline_px", report["baseline_px"], **where,
                       protocol=f"always answering the mean position of the probe's "
                                f"{CLASS_RUN.n_probe} fitting trajectories, scored on the same "
                                f"{CLASS_RUN.n_test} held-out ones (no model involved)")
        figures.record("world_train_min", seconds / 60, **where,
                       protocol=f"{config.steps} steps, training alone (no probe), idle cores")


if __name__ == "__main__":
    main()
