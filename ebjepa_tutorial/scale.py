"""The one switch that sizes every notebook: ``EBJEPA_SCALE``.

- ``ci``: each notebook finishes in well under a minute on 2 CPU cores; it
  checks that everything runs, not that it learns.
- ``class`` (default): each notebook finishes in about 10 minutes or less on a
  2-core laptop CPU and shows a real result.
- ``full``: the paper's configuration, for a GPU.

Each notebook asks for its own preset: ``cfg = preset("00")``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

SCALES = ("ci", "class", "full")
DEFAULT_SCALE = "class"


def current_scale(environ: dict[str, str] | None = None) -> str:
    """Return the scale named by ``EBJEPA_SCALE`` (``class`` when unset)."""
    environ = os.environ if environ is None else environ
    scale = environ.get("EBJEPA_SCALE", DEFAULT_SCALE).strip().lower() or DEFAULT_SCALE
    if scale not in SCALES:
        raise ValueError(
            f"EBJEPA_SCALE={scale!r} is not a scale; choose one of {', '.join(SCALES)} "
            f"(for example `EBJEPA_SCALE=ci make lab`)."
        )
    return scale


@dataclass(frozen=True)
class CollapsePreset:
    """Notebook 00: toy data and the tiny joint-embedding network trained on it."""

    n_points: int = 1024  # 2-D points in the toy data set
    embed_dim: int = 8  # D, the embedding size
    hidden: int = 64  # width of the MLP encoder
    steps: int = 600  # full-batch Adam steps per training run
    lr: float = 3e-3


PRESETS: dict[str, dict[str, object]] = {
    "00": {
        "ci": CollapsePreset(n_points=256, steps=60),
        "class": CollapsePreset(),
        "full": CollapsePreset(n_points=4096, steps=2000),
    },
}


def preset(notebook: str, scale: str | None = None):
    """Return the sizes for ``notebook`` (e.g. ``"00"``) at ``scale`` (default: current)."""
    scale = current_scale() if scale is None else scale
    if scale not in SCALES:
        raise ValueError(f"unknown scale {scale!r}; choose one of {', '.join(SCALES)}")
    if notebook not in PRESETS:
        raise KeyError(f"no presets for notebook {notebook!r}; known: {', '.join(PRESETS)}")
    return PRESETS[notebook][scale]
