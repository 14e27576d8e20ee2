"""Reference figures a notebook prints beside the learner's: the course's class run, recorded by
a benchmark's ``--record`` in ``checkpoints/reference.json``, and the paper's (EB-JEPA, Terver et
al., 2026, arXiv 2602.03604). In a notebook: ``print(compare("world_probe_px", error))``."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from ..training.checkpoints import SHIPPED_DIR
from .presets import current_scale

REFERENCE_FILE = SHIPPED_DIR / "reference.json"


@dataclass(frozen=True)
class Metric:
    """A key's label and format, the paper's figure and the benchmark recording ours, if any."""

    label: str
    fmt: str
    paper: float | None = None
    paper_setting: str = ""
    benchmark: str | None = None
    ours: str = "the course's class run"


_IMAGE = "python -m research.benchmarks.image_jepa"
_PLANNING = "python -m research.benchmarks.planning"
_CIFAR, _MPPI = "ResNet-18, 300 epochs on a GPU", "MPPI, a model trained on a GPU"
_PROBE, _SUCCESS = "linear probe accuracy", "planning success"
BEYOND_PLANNERS = ("flat", "short", "learned_cost", "two_level")  # notebook 07's comparison
METRICS = {  # the figures the notebooks print (the pages' others: tools/figures.py)
    "vicreg_probe_acc": Metric(_PROBE, "{:.1%}", 0.901, _CIFAR, _IMAGE),
    "sigreg_probe_acc": Metric(_PROBE, "{:.1%}", 0.910, _CIFAR, _IMAGE),
    **dict.fromkeys(["vicreg_random_init_probe_acc", "sigreg_random_init_probe_acc"],
                    Metric("random-init probe accuracy", "{:.1%}", benchmark=_IMAGE)),
    "video_map_class_K4": Metric("detection mAP, K = 4", "{:.3f}", 0.607,
                                 "K = 4, trained on a GPU"),
    "world_probe_px": Metric("position probe error", "{:.2f} px",
                             benchmark="python -m research.benchmarks.two_rooms"),
    "planning_success_class": Metric(_SUCCESS, "{:.0%}", 0.97, _MPPI, _PLANNING),
    "planning_success_shipped": Metric(_SUCCESS, "{:.0%}", 0.97, _MPPI, _PLANNING,
                                       "the course's shipped model"),
    "planning_success_refit": Metric(_SUCCESS, "{:.0%}", 0.97, _MPPI, _PLANNING,
                                     "the course's refitted model"),
} | {f"beyond_{world}_{planner}": Metric(_SUCCESS, "{:.1%}",
                                         benchmark="python -m research.benchmarks.beyond")
     for world in ("two_rooms", "three_rooms") for planner in BEYOND_PLANNERS}


def load(path: Path = REFERENCE_FILE) -> dict:
    """The recorded figures, ``{key: {"value", "command", "threads", "date", "protocol"}}``."""
    return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {}


def references(key: str, path: Path = REFERENCE_FILE) -> list[str]:
    """The course's recorded class run (where a benchmark records it) and the paper's figure."""
    metric, parts, ours = METRICS[key], [], load(path).get(key)
    fmt = metric.fmt.format
    if ours is not None:  # with its range where one was measured (seeds, runs, hosts)
        low, high = ours.get("spread", (None, None))
        spread = "" if low is None else f"range {fmt(low)} to {fmt(high)}, "
        threads = f"{ours['threads']} CPU thread{'s' * (ours['threads'] != 1)}"
        parts.append(f"{metric.ours} {fmt(ours['value'])} ({spread}{threads}, {ours['date']})")
    elif metric.benchmark is not None:
        parts.append(f"{metric.ours}: not recorded (run {metric.benchmark} --record)")
    if metric.paper is not None:
        parts.append(f"the paper {fmt(metric.paper)} ({metric.paper_setting})")
    return parts


def compare(key: str, yours: float, scale: str | None = None, path: Path = REFERENCE_FILE) -> str:
    """One line: your figure, the course's recorded class run and the paper's, each labelled."""
    metric = METRICS[key]
    line = " | ".join([f"{metric.label}: yours {metric.fmt.format(yours)}", *references(key, path)])
    if (scale or current_scale()) == "ci":
        line += "\n(a ci run is a smoke test, far too short for its figure to mean anything)"
    return line


def show(key: str, path: Path = REFERENCE_FILE) -> str:
    """The references alone, for a figure the notebook does not compute itself."""
    return f"{METRICS[key].label}: " + " | ".join(references(key, path))
