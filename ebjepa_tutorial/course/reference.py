"""Reference figures a notebook prints beside the learner's: the course's class run (recorded by a
benchmark's ``--record`` in ``checkpoints/reference.json``) and the paper's (arXiv 2602.03604)."""

import json
from dataclasses import dataclass
from pathlib import Path

from ..training.checkpoints import SHIPPED_DIR
from ..training.world import ABLATION_SUFFIXES
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
_CIFAR = "ResNet-18, 300 epochs on a GPU, its probe trained online on augmented views"
_PROBE = "linear probe accuracy"
_SEEDS = "the course's class runs, mean of 3 seeds"
_PLANNING = ("planning success", "{:.0%}", 0.97, "MPPI, a model trained on a GPU",
             "python -m research.benchmarks.planning")  # label, format, the paper, its setting
_TABLE_4 = {"variance": 0.47, "covariance": 0.46, "temporal": 0.61, "inverse_dynamics": 0.01}
BEYOND_PLANNERS = ("flat", "short", "learned_cost", "two_level")  # notebook 07's comparison
METRICS = {  # the figures the notebooks print (the pages' others: tools/figures.py)
    "vicreg_probe_acc": Metric(_PROBE, "{:.1%}", 0.901, _CIFAR, _IMAGE),
    "sigreg_probe_acc": Metric(_PROBE, "{:.1%}", 0.910, _CIFAR, _IMAGE),
    **dict.fromkeys(["vicreg_random_init_probe_acc", "sigreg_random_init_probe_acc"],
                    Metric("random-init probe accuracy", "{:.1%}", benchmark=_IMAGE)),
    **{f"video_map_{run}_K{k}": Metric(f"detection mAP, K = {k}", "{:.3f}", paper, setting,
                                       ours=ours)
       for run, ours in (("class", _SEEDS), ("long", "the course's shipped long run"))
       for k, paper, setting in ((1, None, ""), (4, 0.607, "K = 4, its code release, on a GPU"))},
    "video_ap3_lead": Metric("AP three steps ahead, K = 4 minus K = 1", "{:.2f}", ours=_SEEDS),
    "world_probe_px": Metric("position probe error", "{:.2f} px",
                             benchmark="python -m research.benchmarks.two_rooms"),
    "planning_success_class": Metric(*_PLANNING),
    "planning_success_shipped": Metric(*_PLANNING, "the course's shipped model"),
    "planning_success_refit": Metric(*_PLANNING, "the course's refitted model"),
    "random_walk_success": Metric("within 4.5 px at some step", "{:.1%}", ours="the course's run"),
} | {f"planning_success_{suffix}": Metric(  # the paper's Table 4: the loss less one term
    "planning success", "{:.0%}", _TABLE_4[term], f"Table 4, without {term.replace('_', ' ')}",
    _PLANNING[4], "the course's ablated class model (100 episodes)")
     for term, suffix in ABLATION_SUFFIXES.items()  # the shipped files' suffixes, as notebook 06
} | {f"beyond_{world}_{planner}": Metric("planning success", "{:.1%}",
                                         benchmark="python -m research.benchmarks.beyond")
     for world in ("two_rooms", "three_rooms") for planner in BEYOND_PLANNERS}


def load(path: Path = REFERENCE_FILE) -> dict:
    """The recorded figures, ``{key: {"value", "command", "threads", "date", "protocol"}}``."""
    return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {}


def compare(key: str, yours: float | None = None, scale: str | None = None,
            path: Path = REFERENCE_FILE) -> str:
    """One line: the notebook's figure ``yours`` (if given), the course's recorded class run
    (where a benchmark records it) and the paper's, each labelled; at ``ci``, a warning that the
    notebook's figure means nothing."""
    metric, ours = METRICS[key], load(path).get(key)
    fmt = metric.fmt.format
    parts = [] if yours is None else [f"this notebook {fmt(yours)}"]
    if ours is not None:  # with its range where one was measured (seeds, runs, hosts)
        low, high = ours.get("spread", (None, None))
        spread = "" if low is None else f"range {fmt(low)} to {fmt(high)}, "
        threads = f"{ours['threads']} CPU thread{'s' * (ours['threads'] != 1)}"
        parts.append(f"{metric.ours} {fmt(ours['value'])} ({spread}{threads}, {ours['date']})")
    elif metric.benchmark is not None:
        parts.append(f"{metric.ours}: not recorded (run {metric.benchmark} --record)")
    if metric.paper is not None:
        parts.append(f"the paper {fmt(metric.paper)} ({metric.paper_setting})")
    line = f"{metric.label}: " + " | ".join(parts)
    if yours is not None and (scale or current_scale()) == "ci":
        line += "\n(a ci run is a smoke test, far too short for its figure to mean anything)"
    return line
