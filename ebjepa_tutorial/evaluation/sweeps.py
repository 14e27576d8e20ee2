"""Notebook 02's sweeps (loss weights: the paper's Figure 3; projector widths), as written by
``python -m research.sweep --scale class``."""

import json
from dataclasses import replace
from pathlib import Path

from ..training.image import ImageJEPAConfig

SWEEP_LABELS = {"sigreg_lambda": "SIGReg: lambda", "std_coeff": "VICReg: variance weight",
                "cov_coeff": "VICReg: covariance weight", "projector_sigreg": "SIGReg",
                "projector_vicreg": "VICReg"}


def shorten(config: ImageJEPAConfig, steps: int) -> ImageJEPAConfig:
    """``config`` cut to ``steps`` steps, its warm-up to at most a tenth of them."""
    return replace(config, steps=steps, warmup_steps=min(config.warmup_steps, steps // 10))


def load_sweeps(path: str | Path) -> tuple[dict, dict[str, list[dict]]]:
    """A sweep file's description (scale, data, protocol, command) and its result rows by
    family: ``{"sensitivity": the rows with a factor, "projector": the others}``."""
    meta = json.loads(Path(path).read_text())
    rows = meta.pop("runs")
    return meta, {"sensitivity": [row for row in rows if row["factor"] is not None],
                  "projector": [row for row in rows if row["factor"] is None]}


def tenfold_costs(sensitivity: list[dict]) -> dict[str, tuple[float, float]]:
    """The fewest and most points of probe accuracy that a tenth or ten times a default costs,
    over each method's coefficients: ``{"SIGReg": (low, high), "VICReg": (low, high)}``."""
    default = {row["sweep"]: row["probe_acc"] for row in sensitivity if row["factor"] == 1.0}
    costs: dict[str, list[float]] = {}
    for row in sensitivity:
        if row["factor"] in (0.1, 10.0):
            method = SWEEP_LABELS[row["sweep"]].split(":")[0]
            costs.setdefault(method, []).append(100 * (default[row["sweep"]] - row["probe_acc"]))
    return {method: (min(points), max(points)) for method, points in costs.items()}
