"""Run notebook 02's sensitivity and projector sweeps at a scale; store the results as JSON.

    python -m research.sweep --scale class --out checkpoints/sweeps_class.json [--record]

Two families of short training runs of the CIFAR-10 recipe (``sweep_steps`` steps each,
from the same initial weights), each scored with the frozen protocol
(:func:`ebjepa_tutorial.evaluation.classify.probe_encoder`, at the config's
``eval_image_size``): **sensitivity** (the EB-JEPA paper's Figure 3) multiplies SIGReg's
``sigreg_lambda`` and VICReg's ``std_coeff`` and ``cov_coeff`` (each with the others at
their defaults) by the same factors; **projector** trains both methods without a
projector and with outputs of several widths after a hidden layer of the default width.

The file is rewritten after every run, so an interrupted sweep resumes where it stopped;
a stored row is reused only for the same run identity, probe size and data sizes. At the
end the file holds one row per run of the plan, in order (a run shared by two sweeps,
such as a default, trained once and stored under each of its labels), which is what
:func:`ebjepa_tutorial.evaluation.sweeps.load_sweeps` reads for the notebook.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from ebjepa_tutorial.course.presets import SCALES, preset
from ebjepa_tutorial.data import data_dir, load_cifar10, random_subset
from ebjepa_tutorial.data.cifar10 import find_cifar10
from ebjepa_tutorial.data.paths import atomic_file
from ebjepa_tutorial.evaluation.classify import probe_encoder
from ebjepa_tutorial.evaluation.sweeps import load_sweeps, shorten, tenfold_costs
from ebjepa_tutorial.training.image import ImageJEPAConfig, identity, train_image_jepa
from ebjepa_tutorial.utils import get_device
from tools import figures

from .train_image import protocol

FACTORS = {"ci": (0.1, 1.0, 10.0), "class": (0.01, 0.1, 1.0, 10.0, 100.0),
           "full": (0.01, 0.1, 1.0, 10.0, 100.0)}  # multiples of each default coefficient


@dataclass(frozen=True)
class Run:
    """One training run of a sweep: the sweep's name, the value it sets, and the full config.

    ``factor`` is ``value`` as a multiple of the default (sensitivity sweeps; None otherwise).
    """

    sweep: str
    value: float | int | None
    config: ImageJEPAConfig
    factor: float | None = None


def sensitivity_runs(sigreg_config: ImageJEPAConfig, vicreg_config: ImageJEPAConfig,
                     factors) -> list[Run]:
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


def projector_runs(sigreg_config: ImageJEPAConfig, vicreg_config: ImageJEPAConfig, hidden: int,
                   outputs) -> list[Run]:
    """Both methods with no projector (``None``) and with each output width in ``outputs``."""
    runs = []
    for name, base in [("projector_sigreg", sigreg_config), ("projector_vicreg", vicreg_config)]:
        for out in outputs:
            projector = None if out is None else (hidden, out)
            runs.append(Run(name, out, replace(base, projector=projector)))
    return runs


def sweep_plan(scale: str) -> dict[str, list[Run]]:
    """Notebook 02's runs of both sweeps at ``scale``: ``{"sensitivity": [...],
    "projector": [...]}``."""
    sizes = preset("02", scale)
    sigreg_config = shorten(sizes.config, sizes.sweep_steps)
    vicreg_config = shorten(preset("01", scale).config, sizes.sweep_steps)
    hidden = (sigreg_config.projector or (1024, 1024))[0]
    outputs = (None, hidden // 16, hidden // 4, hidden)  # class: none, 64, 256, 1024
    outputs = (None, hidden // 4) if scale == "ci" else outputs  # ci: fewer runs, it only checks
    return {"sensitivity": sensitivity_runs(sigreg_config, vicreg_config, FACTORS[scale]),
            "projector": projector_runs(sigreg_config, vicreg_config, hidden, outputs)}


def run_identity(config: ImageJEPAConfig) -> dict:
    """What a result row stores of its run: the run's identity (``training.image.identity``:
    the fields that define the training) and the size its probe saw."""
    return {**identity(config), "eval_image_size": config.eval_image_size}


def key(config: ImageJEPAConfig | dict, n_train: int, n_test: int) -> str:
    """What identifies a result: :func:`run_identity` as JSON (tuples become lists) and the
    data sizes. An option added to the config with a default leaves stored rows valid."""
    config = run_identity(config) if isinstance(config, ImageJEPAConfig) else config
    return json.dumps([config, n_train, n_test], sort_keys=True)


def load_results(path: str | Path | None) -> list[dict]:
    """The result rows stored in a sweep file, or ``[]`` when there is none."""
    if path is None or not Path(path).is_file():
        return []
    return json.loads(Path(path).read_text())["runs"]


def stored_rows(path: str | Path | None) -> dict[str, dict]:
    """The result rows of the sweep file ``path``, by what identifies a run."""
    return {key(row["config"], row["n_train"], row["n_test"]): row for row in load_results(path)}


def save_results(path: str | Path, rows: list[dict], meta: dict) -> None:
    """Write ``{**meta, "runs": rows}`` as JSON, whole or not at all."""
    with atomic_file(Path(path)) as f:
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


def run_sweep(runs: list[Run], train, test, path: str | Path | None = None, device="cpu",
              progress: bool = True, meta: dict | None = None) -> list[dict]:
    """One result row per run, in order: found in ``path``, else trained now (once per
    identity) and added to ``path`` as soon as it finishes.

    ``train``, ``test``: ``(uint8 images (N, 3, 32, 32), labels (N,))``.
    """
    sizes = (len(train[0]), len(test[0]))
    stored = stored_rows(path)
    todo = list({key(run.config, *sizes): run for run in runs
                 if key(run.config, *sizes) not in stored}.values())
    # counted over the file, not as runs - todo: todo trains a run two sweeps share only once
    found = sum(key(run.config, *sizes) in stored for run in runs)
    print(f"{found} of {len(runs)} runs found in {path or 'no file'}; "
          f"training {len(todo)} now.")
    own = load_results(path)
    for i, run in enumerate(todo, start=1):
        row = train_and_probe(run, train, test, device, progress)
        stored[key(run.config, *sizes)] = row
        print(f"[{i}/{len(todo)}] {run.sweep} = {run.value}: probe {row['probe_acc']:.1%}, "
              f"kNN {row['knn_acc']:.1%} ({row['seconds']:.0f} s)")
        if path is not None:
            own.append(row)
            save_results(path, own, meta or {"protocol": protocol(run.config)})
    return [{**stored[key(run.config, *sizes)], "sweep": run.sweep, "value": run.value,
             "factor": run.factor} for run in runs]


def describe_data() -> str:
    """Which copy of CIFAR-10 the loaders read: every accuracy depends on it."""
    source = find_cifar10(data_dir())
    if source is None:
        return "CIFAR-10 (not found)"
    jpeg = source.is_file()  # the packed archive, not the official release's folder
    return f"CIFAR-10{' (JPEG copy)' if jpeg else ''}, read from {source}"


def main(argv: list[str] | None = None) -> None:
    """Run both sweeps at a scale and store their rows in plan order: the documented command."""
    parser = argparse.ArgumentParser(description="Notebook 02's sensitivity and projector sweeps.")
    parser.add_argument("--scale", choices=SCALES, default="class")
    parser.add_argument("--out", required=True, help="the JSON file to write (and resume)")
    parser.add_argument("--record", action="store_true", help="store the tenfold costs in "
                        "checkpoints/reference.json, which the pages quote (class scale only)")
    args = parser.parse_args(argv)
    if args.record and args.scale != "class":
        parser.error("--record stores the class sweep's figures: drop --scale or --record")
    sizes = preset("02", args.scale)
    train = random_subset(*load_cifar10("train"), sizes.train_images)
    test = random_subset(*load_cifar10("test"), sizes.test_images)
    runs = [run for group in sweep_plan(args.scale).values() for run in group]
    meta = {"scale": args.scale, "data": describe_data(), "protocol": protocol(sizes.config),
            "command": f"python -m research.sweep --scale {args.scale} --out {args.out}",
            "torch_threads": torch.get_num_threads()}
    start = time.perf_counter()
    rows = run_sweep(runs, train, test, path=args.out, device=get_device(), meta=meta)
    written = json.loads(Path(args.out).read_text())  # the description of the runs' training
    save_results(args.out, rows, {name: value for name, value in written.items() if name != "runs"})
    print(f"done in {(time.perf_counter() - start) / 60:.1f} min; results in {args.out}")
    if args.record:
        record_tenfold_costs(args.out, meta["command"] + " --record")


def record_tenfold_costs(path: str | Path, command: str) -> None:
    """Record the points of probe accuracy a tenth or ten times each default costs, per method
    (``tenfold_costs``: the fewest and most over its coefficients), from the sweep at ``path``."""
    meta, rows = load_sweeps(path)
    for method, (low, high) in tenfold_costs(rows["sensitivity"]).items():
        figures.record(f"sweep_{method.lower()}_tenfold_points", high, command,
                       "points of linear-probe accuracy lost at a tenth or ten times each "
                       f"default coefficient, {rows['sensitivity'][0]['config']['steps']} steps "
                       "per run, seed 0; value: the largest loss; spread: the fewest and most "
                       "over the method's coefficients (SIGReg: lambda; VICReg: std_coeff and "
                       "cov_coeff) and both factors", meta["torch_threads"], spread=(low, high))


if __name__ == "__main__":
    main()
