"""Benchmarks: each prints speed and quality figures and ends with one ``key=value`` line that
scripts parse; ``--record`` stores a figure, with its command, in ``checkpoints/reference.json``.

Run each from the repository root as a module, ``python -m research.benchmarks.NAME --help``;
``research/benchmarks/gpu_session.sh`` runs ``full_scale`` and a short image run on a lent GPU.
"""

import sys


def command_line(module: str) -> str:
    """This run's command as a reader types it, ``python -m MODULE ARGS`` (under ``-m``,
    ``sys.argv[0]`` is the file's full path, which would name this machine's folders)."""
    return " ".join(["python", "-m", module, *sys.argv[1:]])
