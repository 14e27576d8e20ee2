"""Benchmarks: each prints speed and quality figures and ends with one ``key=value`` line that
scripts parse; ``--record`` stores a figure, with its command, in ``checkpoints/reference.json``.

Run each from the repository root as a module, ``python -m research.benchmarks.NAME --help``;
``research/benchmarks/gpu_session.sh`` runs ``full_scale`` and a short image run on a lent GPU.
"""

import platform
import sys


def command_line(module: str) -> str:
    """This run's command as a reader types it, ``python -m MODULE ARGS`` (under ``-m``,
    ``sys.argv[0]`` is the file's full path, which would name this machine's folders)."""
    return " ".join(["python", "-m", module, *sys.argv[1:]])


def cpu_name() -> str:
    """The CPU's model name (Linux), for a timing's protocol: speeds differ between hosts."""
    try:
        with open("/proc/cpuinfo") as info:
            return next(line.split(":", 1)[1].strip() for line in info
                        if line.startswith("model name"))
    except (OSError, StopIteration):
        return platform.processor() or platform.machine() or "an unnamed CPU"
