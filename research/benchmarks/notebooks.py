"""How long each notebook takes, top to bottom, at one scale: the compute times the README's
chapter table and each notebook's first cell state.

    python -m research.benchmarks.notebooks --scale ci [--only 00 03] [--record]
    python -m research.benchmarks.notebooks --scale class --cold --record

Each notebook runs in a fresh kernel (nbclient) from ``notebooks/``, as a learner's Jupyter
would, with ``EBJEPA_SCALE`` set. ``--cold`` moves the cache's ``checkpoints`` and ``probes``
(``$EBJEPA_CACHE``, else ``data/cache``) aside first (and puts them back after), so chapters 01
and 02 train their class runs live, as on a learner's first run; the shipped ``checkpoints/``
always load. ``--record`` stores each wall time as ``notebook_NN_<scale>`` in
``checkpoints/reference.json``, in seconds. Time only on idle cores: a second job on a
2-core machine slows both by far more than hosts differ.
"""

from __future__ import annotations

import argparse
import os
import shutil
import time
from contextlib import contextmanager
from pathlib import Path

import torch

from ebjepa_tutorial.data.paths import cache_dir
from research.benchmarks import command_line, cpu_name
from tools import figures

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOKS = ROOT / "notebooks"
MOVABLE = ("checkpoints", "probes")  # what a first run has not made yet


def notebooks(only: list[str] | None = None) -> list[Path]:
    paths = sorted(NOTEBOOKS.glob("[0-9][0-9]_*.ipynb"))
    return [p for p in paths if only is None or p.name[:2] in only]


@contextmanager
def cold_cache(enabled: bool):
    """The cache's trained runs and scores moved aside while the block runs (the cache the
    kernels read: ``$EBJEPA_CACHE``, which they inherit, else ``data/cache``)."""
    moved = []
    try:
        for name in MOVABLE if enabled else ():
            path = cache_dir() / name
            if path.exists():
                aside = path.with_name(f"{name}.aside-{os.getpid()}")
                path.rename(aside)
                moved.append((aside, path))
        yield
    finally:
        for aside, path in moved:
            if path.exists():  # what the cold run made: drop it, keep the original
                shutil.rmtree(path)
            aside.rename(path)


def run_notebook(path: Path, scale: str, timeout: int = 3600) -> float:
    """Wall seconds to execute ``path`` top to bottom at ``scale`` in a fresh kernel."""
    import nbformat  # here: its validator takes seconds to import, and only a timing needs it
    from nbclient import NotebookClient

    os.environ["EBJEPA_SCALE"] = scale  # the kernel inherits this process's environment
    notebook = nbformat.read(path, as_version=4)
    client = NotebookClient(notebook, timeout=timeout, kernel_name="python3",
                            resources={"metadata": {"path": str(NOTEBOOKS)}})
    start = time.perf_counter()
    client.execute()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scale", choices=("ci", "class"), default="ci")
    parser.add_argument("--only", nargs="+", help="two-digit chapter numbers (default: all)")
    parser.add_argument("--cold", action="store_true",
                        help="move the cache's trained runs aside: a learner's first run")
    parser.add_argument("--record", action="store_true")
    args = parser.parse_args()
    host = f"{cpu_name()}, {os.cpu_count()} cores"
    paths = notebooks(args.only)
    with cold_cache(args.cold):
        for done, path in enumerate(paths):
            seconds = run_notebook(path, args.scale)
            print(f"{path.name}: {seconds:.0f} s at {args.scale}", flush=True)
            if args.record:
                earlier = ", ".join(p.name[:2] for p in paths[:done])  # they filled the cache
                if not args.cold:
                    state = "data/cache as left by earlier runs"
                elif earlier:
                    state = f"a first run after chapter(s) {earlier} in the same emptied cache"
                else:
                    state = "a first run (no trained runs in data/cache)"
                figures.record(f"notebook_{path.name[:2]}_{args.scale}", seconds,
                               command=command_line(__spec__.name),
                               protocol=f"one run top to bottom in a fresh kernel, "
                                        f"EBJEPA_SCALE={args.scale}, shipped checkpoints "
                                        f"loaded, {state}; {host}, idle",
                               threads=torch.get_num_threads())


if __name__ == "__main__":
    main()
