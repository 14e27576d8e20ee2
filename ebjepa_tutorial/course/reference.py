"""Reference figures that a notebook prints beside the learner's own result.

Two references stand next to a number a cell computes: the course's own run of
the same recipe at class scale, which a benchmark measured and recorded with
``--record`` in ``checkpoints/reference.json`` (with its command, threads and
date), and the paper's figure (EB-JEPA, Terver et al., 2026, arXiv 2602.03604),
cited below with the setting it was measured in. Nothing here is typed by hand
from a run: re-run the benchmark with ``--record`` to refresh a figure.

    print(reference.compare("vicreg_probe_acc", 0.551))
    # linear probe accuracy: yours 55.1% | the course's class run 55.4% (2 CPU threads, ...)
    #     | the paper 90.1% (ResNet-18, 300 epochs on a GPU)

The same file is the one source of every measured figure in README.md,
RESULTS.md, TEACHING.md and the notebooks' text: there a figure is written as
``<!--fig:KEY-->62.6%<!--/fig-->`` (``<!--fig:KEY:spread-->`` for its range), the
comments invisible once rendered; ``python -m tools.figures render`` rewrites them
from the file and ``check`` lists those that disagree (a test runs it).
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
    """What a key measures, how to print it, the paper's figure (None: the paper has none) and
    the benchmark that records the course's run (None: none records it yet), and what that
    run is called where it is printed."""

    label: str
    fmt: str
    paper: float | None = None
    paper_setting: str = ""
    benchmark: str | None = None
    ours: str = "the course's class run"


_IMAGE = "python -m research.benchmarks.image_jepa"
_PLANNING = "python -m research.benchmarks.planning"
_CIFAR = "ResNet-18, 300 epochs on a GPU"
_MPPI = "MPPI, a model trained on a GPU"
METRICS = {
    "vicreg_probe_acc": Metric("linear probe accuracy", "{:.1%}", 0.901, _CIFAR, _IMAGE),
    "vicreg_random_init_probe_acc": Metric("random-init probe accuracy", "{:.1%}",
                                           benchmark=_IMAGE),
    "sigreg_probe_acc": Metric("linear probe accuracy", "{:.1%}", 0.910, _CIFAR, _IMAGE),
    "sigreg_random_init_probe_acc": Metric("random-init probe accuracy", "{:.1%}",
                                           benchmark=_IMAGE),
    "video_map": Metric("detection mAP over horizons 1-7", "{:.3f}", 0.607,
                        "K = 4, trained on a GPU", "python -m research.benchmarks.video_jepa"),
    "world_probe_px": Metric("position probe error", "{:.2f} px",
                             benchmark="python -m research.benchmarks.two_rooms"),
    "planning_success_class": Metric("planning success", "{:.0%}", 0.97, _MPPI,
                                     _PLANNING),
    "planning_success_shipped": Metric("planning success", "{:.0%}", 0.97, _MPPI,
                                       _PLANNING, "the course's shipped model"),
    "planning_success_refit": Metric("planning success", "{:.0%}", 0.97, _MPPI,
                                     _PLANNING, "the course's refitted model"),
}

_SHIPPED = "the course's shipped model"
METRICS |= {  # figures of the longer runs, and class runs pooled over seeds or seed ranges
    "vicreg_shipped_probe_acc": Metric("linear probe accuracy", "{:.1%}", 0.901, _CIFAR,
                                       ours=_SHIPPED),
    "sigreg_shipped_probe_acc": Metric("linear probe accuracy", "{:.1%}", 0.910, _CIFAR,
                                       ours=_SHIPPED),
    "video_map_class_K4": Metric("detection mAP, K = 4", "{:.3f}", 0.607,
                                 "K = 4, trained on a GPU"),
    "video_map_class_K1": Metric("detection mAP, K = 1", "{:.3f}", 0.383,
                                 "K = 1, trained on a GPU"),
    "video_ap3_lead": Metric("K = 4's lead over K = 1 in AP three steps ahead", "{:.2f}"),
    "video_map_long_K4": Metric("detection mAP, K = 4", "{:.3f}", 0.607,
                                "K = 4, trained on a GPU", ours=_SHIPPED),
    "video_map_long_K1": Metric("detection mAP, K = 1", "{:.3f}", 0.383,
                                "K = 1, trained on a GPU", ours=_SHIPPED),
    "random_walk_success": Metric("random-walk success", "{:.1%}"),
    "planning_success_live": Metric("planning success", "{:.0%}", 0.97, _MPPI,
                                    ours="chapter 05's class model"),
    "planning_success_shipped_fresh": Metric("planning success", "{:.1%}", 0.97, _MPPI,
                                             ours=_SHIPPED),
    "planning_cpu_s_shipped": Metric("CPU seconds per episode", "{:.1f} s", ours=_SHIPPED),
}

_NOTEBOOKS = "python -m research.benchmarks.notebooks"
METRICS |= {  # compute times: a whole notebook, and one live class run of a chapter's model
    **{f"notebook_{nb:02d}_{scale}": Metric(f"notebook {nb:02d} at {scale}", "{:.0f} s",
                                            benchmark=_NOTEBOOKS)
       for nb in range(8) for scale in ("ci", "class")},
    "vicreg_train_min": Metric("VICReg class run", "{:.1f} min", benchmark=_IMAGE),
    "sigreg_train_min": Metric("SIGReg class run", "{:.1f} min", benchmark=_IMAGE),
    "video_train_min": Metric("video JEPA class run (K = 4)", "{:.1f} min",
                              benchmark="python -m research.benchmarks.video_jepa"),
    "world_train_min": Metric("world model class run", "{:.1f} min",
                              benchmark="python -m research.benchmarks.two_rooms"),
}

TABLE_4 = {"no_variance": 0.47, "no_covariance": 0.46, "no_temporal": 0.61, "no_idm": 0.01}
METRICS |= {  # the paper's Table 4 at class length: chapter 05's class run without one term
    f"planning_success_{suffix}": Metric("planning success", "{:.0%}", paper, "MPPI, the paper's "
                                         "Table 4", _PLANNING, "the course's class run")
    for suffix, paper in TABLE_4.items()}

BEYOND_PLANNERS = ("flat", "short", "learned_cost", "two_level")  # notebook 07's comparison
METRICS |= {f"beyond_{world}_{planner}": Metric("planning success", "{:.1%}",
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
