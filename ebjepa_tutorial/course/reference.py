"""Reference figures a notebook prints beside the learner's result: the course's class run of
the same recipe, recorded by a benchmark's ``--record`` in ``checkpoints/reference.json`` (with
its command, threads and date; the pages' ``<!--fig:KEY-->`` markers read it too, through
``python -m tools.figures``), and the paper's (EB-JEPA, Terver et al., 2026, arXiv 2602.03604).

    print(reference.compare("vicreg_probe_acc", 0.551))
    # linear probe accuracy: yours 55.1% | the course's class run 55.4% (2 CPU threads, ...)
    #     | the paper 90.1% (ResNet-18, 300 epochs on a GPU)
"""

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
_VIDEO = "python -m research.benchmarks.video_jepa"
_WORLD = "python -m research.benchmarks.two_rooms"
_PLANNING = "python -m research.benchmarks.planning"
_CIFAR = "ResNet-18, 300 epochs on a GPU"
_MPPI = "MPPI, a model trained on a GPU"
_SHIPPED = "the course's shipped model"
_PROBE, _SUCCESS = "linear probe accuracy", "planning success"
METRICS = {
    "video_map": Metric("detection mAP over horizons 1-7", "{:.3f}", 0.607,
                        "K = 4, trained on a GPU", _VIDEO),
    "video_ap3_lead": Metric("K = 4's lead over K = 1 in AP three steps ahead", "{:.2f}"),
    "world_probe_px": Metric("position probe error", "{:.2f} px", benchmark=_WORLD),
    "random_walk_success": Metric("random-walk success", "{:.1%}"),
    "planning_success_class": Metric(_SUCCESS, "{:.0%}", 0.97, _MPPI, _PLANNING),
    "planning_success_shipped": Metric(_SUCCESS, "{:.0%}", 0.97, _MPPI, _PLANNING, _SHIPPED),
    "planning_success_refit": Metric(_SUCCESS, "{:.0%}", 0.97, _MPPI, _PLANNING,
                                     "the course's refitted model"),
    "planning_success_live": Metric(_SUCCESS, "{:.0%}", 0.97, _MPPI,
                                    ours="chapter 05's class model"),
    "planning_success_shipped_fresh": Metric(_SUCCESS, "{:.1%}", 0.97, _MPPI, ours=_SHIPPED),
    "planning_cpu_s_shipped": Metric("CPU seconds per episode", "{:.1f} s", ours=_SHIPPED),
    "video_train_min": Metric("video JEPA class run (K = 4)", "{:.1f} min", benchmark=_VIDEO),
    "world_train_min": Metric("world model class run", "{:.1f} min", benchmark=_WORLD),
}
for loss, name, paper in (("vicreg", "VICReg", 0.901), ("sigreg", "SIGReg", 0.910)):
    METRICS |= {
        f"{loss}_probe_acc": Metric(_PROBE, "{:.1%}", paper, _CIFAR, _IMAGE),
        f"{loss}_random_init_probe_acc": Metric("random-init probe accuracy", "{:.1%}",
                                                benchmark=_IMAGE),
        f"{loss}_shipped_probe_acc": Metric(_PROBE, "{:.1%}", paper, _CIFAR, ours=_SHIPPED),
        f"{loss}_train_min": Metric(f"{name} class run", "{:.1f} min", benchmark=_IMAGE)}
del loss, name, paper
METRICS |= {  # the class runs pooled over seeds, and the longer shipped runs
    f"video_map_{run}_K{k}": Metric(f"detection mAP, K = {k}", "{:.3f}", paper,
                                    f"K = {k}, trained on a GPU", ours=ours)
    for k, paper in ((4, 0.607), (1, 0.383))
    for run, ours in (("class", "the course's class run"), ("long", _SHIPPED))}
METRICS |= {  # compute times of a whole notebook
    f"notebook_{nb:02d}_{scale}": Metric(f"notebook {nb:02d} at {scale}", "{:.0f} s",
                                         benchmark="python -m research.benchmarks.notebooks")
    for nb in range(8) for scale in ("ci", "class")}

TABLE_4 = {"no_variance": 0.47, "no_covariance": 0.46, "no_temporal": 0.61, "no_idm": 0.01}
METRICS |= {  # the paper's Table 4 at class length: chapter 05's class run without one term
    f"planning_success_{suffix}": Metric(_SUCCESS, "{:.0%}", paper, "MPPI, the paper's Table 4",
                                         _PLANNING)
    for suffix, paper in TABLE_4.items()}

BEYOND_PLANNERS = ("flat", "short", "learned_cost", "two_level")  # notebook 07's comparison
METRICS |= {f"beyond_{world}_{planner}": Metric(_SUCCESS, "{:.1%}",
                                                benchmark="python -m research.benchmarks.beyond")
            for world in ("two_rooms", "three_rooms") for planner in BEYOND_PLANNERS}


def load(path: Path = REFERENCE_FILE) -> dict:
    """The recorded figures, ``{key: {"value", "command", "threads", "date", "protocol"}}``."""
    return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {}


def references(key: str, path: Path = REFERENCE_FILE) -> list[str]:
    """The course's recorded class run (where a benchmark records it) and the paper's figure."""
    metric, parts, ours = METRICS[key], [], load(path).get(key)
    if ours is not None:  # with its range where one was measured (seeds, runs, hosts)
        low, high = ours.get("spread", (None, None))
        spread = "" if low is None else \
            f"range {metric.fmt.format(low)} to {metric.fmt.format(high)}, "
        parts.append(f"{metric.ours} {metric.fmt.format(ours['value'])} ({spread}"
                     f"{ours['threads']} CPU thread{'s' * (ours['threads'] != 1)}, "
                     f"{ours['date']})")
    elif metric.benchmark is not None:
        parts.append(f"{metric.ours}: not recorded (run {metric.benchmark} --record)")
    if metric.paper is not None:
        parts.append(f"the paper {metric.fmt.format(metric.paper)} ({metric.paper_setting})")
    return parts


def compare(key: str, yours: float, scale: str | None = None, path: Path = REFERENCE_FILE) -> str:
    """One line: your figure, the course's recorded class run and the paper's, each labelled."""
    metric = METRICS[key]
    line = " | ".join([f"{metric.label}: yours {metric.fmt.format(yours)}",
                       *references(key, path)])
    if (scale or current_scale()) == "ci":
        line += "\n(a ci run is a smoke test, far too short for its figure to mean anything)"
    return line


def show(key: str, path: Path = REFERENCE_FILE) -> str:
    """The references alone, for a figure the notebook does not compute itself."""
    return f"{METRICS[key].label}: " + " | ".join(references(key, path))
