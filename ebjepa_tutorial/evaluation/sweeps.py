"""Notebook 02's sweeps: how much does the probe depend on the coefficients and the projector?

Two families of short training runs of the CIFAR-10 recipe (``cfg.sweep_steps``
steps each, from the same initial weights), each scored with the usual frozen
protocol (:func:`ebjepa_tutorial.evaluation.classify.probe_encoder`, at the config's
``eval_image_size``; a stored result is reused only at the same size):

- **sensitivity** (the EB-JEPA paper's Figure 3, at our scale): SIGReg's one
  weight ``sigreg_lambda``, and VICReg's two, ``std_coeff`` and ``cov_coeff``
  (each with the other at its default), multiplied by the same factors;
- **projector**: SIGReg and VICReg without a projector, and with outputs of
  several widths (the bottleneck) after a hidden layer of the default width.

At ``class`` scale that is about twenty runs, too many for a class period, so
the results come from a command and are stored in a small JSON file::

    python -m research.sweep --scale class --out checkpoints/sweeps_class.json

The notebook reads that file if it holds its runs, and otherwise trains the
missing ones live (seconds at ``ci`` scale). The file is rewritten after every
run, so an interrupted sweep resumes where it stopped.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

from ..data.paths import atomic_file
from ..training.image import ImageJEPAConfig, identity, train_image_jepa
from .classify import probe_encoder, protocol

FACTORS = {"ci": (0.1, 1.0, 10.0), "class": (0.01, 0.1, 1.0, 10.0, 100.0),
           "full": (0.01, 0.1, 1.0, 10.0, 100.0)}  # multiples of each default coefficient


SWEEP_LABELS = {
    "sigreg_lambda": "SIGReg: lambda",
    "std_coeff": "VICReg: variance weight",
    "cov_coeff": "VICReg: covariance weight",
    "projector_sigreg": "SIGReg",
    "projector_vicreg": "VICReg",
}


@dataclass(frozen=True)
class Run:
    """One training run of a sweep: the sweep's name, the value it sets, and the full config.

    ``factor`` is ``value`` as a multiple of the default (sensitivity sweeps; None otherwise).
    """

    sweep: str
    value: float | int | None
    config: ImageJEPAConfig
    factor: float | None = None


def shorten(config: ImageJEPAConfig, steps: int) -> ImageJEPAConfig:
    """``config`` cut to ``steps`` steps, its warm-up cut to at most a tenth of them."""
    return replace(config, steps=steps, warmup_steps=min(config.warmup_steps, steps // 10))


def sensitivity_runs(sigreg_config: ImageJEPAConfig, vicreg_config: ImageJEPAConfig,
                     factors=FACTORS["class"]) -> list[Run]:
    """SIGReg's ``sigreg_lambda``, VICReg's ``std_coeff`` and ``cov_coeff``, times ``factors``."""
    runs = []
    for name, base, field in [("sigreg_lambda", sigreg_config, "lam"),
                              ("std_coeff", vicreg_config, "std_coeff"),
                              ("cov_coeff", vicreg_config, "cov_coeff")]:
        default = getattr(base.loss, field)
        for factor in factors:
            value = float(f"{default * factor:.6g}")  # 0.1 * 0.1 is 0.01, not 0.010000000000000002
            loss = replace(base.loss, **{field: value})
            runs.append(Run(name, value, replace(base, loss=loss), factor))
    return runs


def projector_runs(sigreg_config: ImageJEPAConfig, vicreg_config: ImageJEPAConfig,
                   outputs=(None, 64, 256, 1024)) -> list[Run]:
    """Both methods with no projector (``None``) and with each output width in ``outputs``.

    The hidden width is the SIGReg config's (1024 at ``class`` scale).
    """
    hidden = (sigreg_config.projector or vicreg_config.projector or (1024, 1024))[0]
    runs = []
    for name, base in [("projector_sigreg", sigreg_config), ("projector_vicreg", vicreg_config)]:
        for out in outputs:
            projector = None if out is None else (hidden, out)
            runs.append(Run(name, out, replace(base, projector=projector)))
    return runs


def run_identity(config: ImageJEPAConfig) -> dict:
    """What a result row stores of its run: the run's identity (``training.image.identity``:
    the fields that define the training) and the size its probe saw."""
    return {**identity(config), "eval_image_size": config.eval_image_size}


def key(config: ImageJEPAConfig | dict, n_train: int, n_test: int) -> str:
    """What identifies a result: :func:`run_identity` as JSON (tuples become lists) and the
    data sizes. An option added to the config with a default leaves stored rows valid."""
    config = run_identity(config) if isinstance(config, ImageJEPAConfig) else config
    return json.dumps([config, n_train, n_test], sort_keys=True)


def load_meta(path: str | Path | None) -> dict:
    """Everything a sweep file holds (scale, data, protocol, command, ``runs``), or ``{}``."""
    if path is None or not Path(path).is_file():
        return {}
    with open(path) as f:
        return json.load(f)


def load_results(path: str | Path | None) -> list[dict]:
    """The result rows stored in a sweep file, or ``[]`` when there is none."""
    return load_meta(path).get("runs", [])


def stored_rows(*paths: str | Path | None) -> dict[str, dict]:
    """The result rows of the sweep files ``paths``, by what identifies a run (later files win)."""
    return {key(row["config"], row["n_train"], row["n_test"]): row
            for path in paths for row in load_results(path)}


def missing_runs(runs: list[Run], n_train: int, n_test: int, stored: dict) -> list[Run]:
    """The runs in ``runs`` that ``stored`` (see :func:`stored_rows`) lacks at these sizes."""
    return [run for run in runs if key(run.config, n_train, n_test) not in stored]


def _save_results(path: Path, rows: list[dict], meta: dict) -> None:
    """Write ``{**meta, "runs": rows}`` as JSON, whole or not at all."""
    with atomic_file(path) as f:
        f.write(json.dumps({**meta, "runs": rows}, indent=1).encode())


def train_and_probe(run: Run, train, test, device="cpu", progress: bool = True) -> dict:
    """Train ``run.config`` on ``train`` images, probe its encoder: one result row."""
    start = time.perf_counter()
    model, history = train_image_jepa(run.config, train[0], device=device, progress=progress)
    scores = probe_encoder(model.encoder.cpu(), run.config, train, test)
    final = {name: values[-1] for name, values in history.items() if name != "step"}
    return {"sweep": run.sweep, "value": run.value, "factor": run.factor, **scores,
            "final_terms": final, "seconds": round(time.perf_counter() - start, 1),
            "n_train": len(train[0]), "n_test": len(test[0]), "config": run_identity(run.config)}


def run_sweep(runs: list[Run], train, test, path: str | Path | None = None,
              shipped: str | Path | None = None, device="cpu", progress: bool = True,
              meta: dict | None = None) -> list[dict]:
    """One result row per run, in order: found in ``shipped`` or ``path``, else trained now.

    ``train``, ``test``: ``(uint8 images (N, 3, 32, 32), labels (N,))``. A stored
    row is used only if it was made with the same config and data sizes. Newly
    trained rows are added to ``path`` (JSON) as soon as each run finishes.
    """
    sizes = (len(train[0]), len(test[0]))
    stored = stored_rows(shipped, path)
    todo = missing_runs(runs, *sizes, stored)
    where = " or ".join(str(p) for p in (shipped, path) if p is not None) or "no file"
    print(f"{len(runs) - len(todo)} of {len(runs)} runs found in {where}; "
          f"training {len(todo)} now.")
    own = load_results(path)
    for i, run in enumerate(todo, start=1):
        row = train_and_probe(run, train, test, device, progress)
        stored[key(run.config, *sizes)] = row
        print(f"[{i}/{len(todo)}] {run.sweep} = {run.value}: probe {row['probe_acc']:.1%}, "
              f"kNN {row['knn_acc']:.1%} ({row['seconds']:.0f} s)")
        if path is not None:
            own.append(row)
            _save_results(Path(path), own, meta or {"protocol": protocol(run.config)})
    return [{**stored[key(run.config, *sizes)], "sweep": run.sweep, "value": run.value,
             "factor": run.factor} for run in runs]
