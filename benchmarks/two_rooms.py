"""Two Rooms benchmark: how fast the offline data is made (the model part comes later).

Run: ``python benchmarks/two_rooms.py [--n 4096] [--batch 256] [--threads 2]``.
Prints trajectories per second (17 frames, 16 actions) for the states alone
and with every 65x65x2 frame rendered (float32, in batches into one reused
buffer, as a training loop would),
and ends with ``traj_per_s=...`` (with rendering).
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from ebjepa_tutorial.envs import generate_trajectories


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
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    speed = data_generation_speed(args.n, args.batch)
    print(f"Two Rooms data, {args.n} trajectories of 17 frames, {args.threads} threads:")
    print(f"  states only (positions, actions, layouts): {speed['states_traj_per_s']:,.0f} traj/s")
    print(f"  rendering only (float32, batches of {args.batch}): "
          f"{speed['render_traj_per_s']:,.0f} traj/s")
    print(f"traj_per_s={speed['traj_per_s']:.0f}")


if __name__ == "__main__":
    main()
