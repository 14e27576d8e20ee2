"""Notebook 02's sweeps: the course's class-scale results, read back to be drawn.

Two families of short runs of the class recipe (250 steps each, from the same initial
weights), each scored with :func:`~ebjepa_tutorial.evaluation.classify.probe_encoder`:
**sensitivity** (the EB-JEPA paper's Figure 3 at our scale: SIGReg's ``sigreg_lambda``
and VICReg's ``std_coeff`` and ``cov_coeff``, each times the same factors) and
**projector** (both methods without a projector and with outputs of several widths).
About twenty class-scale runs, too many for a class period: ``python -m research.sweep
--scale class --out checkpoints/sweeps_class.json`` made the file the notebook reads.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

from ..training.image import ImageJEPAConfig

SWEEP_LABELS = {
    "sigreg_lambda": "SIGReg: lambda",
    "std_coeff": "VICReg: variance weight",
    "cov_coeff": "VICReg: covariance weight",
    "projector_sigreg": "SIGReg",
    "projector_vicreg": "VICReg",
}


def shorten(config: ImageJEPAConfig, steps: int) -> ImageJEPAConfig:
    """``config`` cut to ``steps`` steps, its warm-up cut to at most a tenth of them."""
    return replace(config, steps=steps, warmup_steps=min(config.warmup_steps, steps // 10))


def load_sweeps(path: str | Path) -> tuple[dict, dict[str, list[dict]]]:
    """A sweep file's description (scale, data, protocol, command) and its result rows by
    family: ``{"sensitivity": the rows with a factor, "projector": the others}``."""
    meta = json.loads(Path(path).read_text())
    rows = meta.pop("runs")
    return meta, {"sensitivity": [row for row in rows if row["factor"] is not None],
                  "projector": [row for row in rows if row["factor"] is None]}
