"""Re-save the shipped checkpoints with the identity their notebooks ask for today.

    python -m research.resave_checkpoints           # check, rewrite what differs
    python -m research.resave_checkpoints --check   # only say what differs (exit 1 if any)

A notebook uses ``checkpoints/<name>.pt`` only when the identity stored in the file equals
the one its preset computes (``training.checkpoints.run_identity``: the fields that
define the run). When the way identities are formed changes, or a default of a config
changes, run this once and commit the files. It never relabels another run: every field
that both the stored and today's identity record must agree, or the file is left alone
and named. A field only the stored identity records (an edited step's ``step``, say) also
leaves the file alone, unless ``--drop FIELD`` says that field left the identity on purpose;
fields only today's records are listed for the maintainer to read.

``shipped_runs`` is the one list of which preset each shipped file is the run of;
tests/test_shipped.py checks the files against it.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from ebjepa_tutorial.course.presets import preset
from ebjepa_tutorial.data import load_mnist
from ebjepa_tutorial.data.moving_mnist import split_digits
from ebjepa_tutorial.training import image, video, world
from ebjepa_tutorial.training.checkpoints import (
    SHIPPED_DIR,
    load_checkpoint,
    run_identity,
    save_checkpoint,
)

from . import fit_beyond, refit


def shipped_runs() -> dict[str, dict]:
    """``{file name: the identity its notebook computes at class scale}`` for every shipped
    model (the video runs need the MNIST test digits, EBJEPA_DATA)."""
    runs = {f"{loss}_class_long": image.identity(preset(nb, "class").long_config, True)
            for nb, loss in (("01", "vicreg"), ("02", "sigreg"))}
    runs.update(_world_runs())
    runs.update(_video_runs())
    for world_name in sorted(fit_beyond.WORLDS):
        _, config, name = fit_beyond.world_run(world_name)
        runs[name] = world.identity(config)
        for kind, fit in zip(("cost_head", "coarse"), fit_beyond.fit_configs(world_name)):
            runs[f"{kind}_{world_name}_class"] = run_identity(fit, base=world.identity(config))
    return runs


def _world_runs() -> dict[str, dict]:
    cfg = preset("06", "class")
    longer, (refit_base, refit_config) = cfg.longer, refit.shipped_pair()
    runs = {"world_model_class": world.identity(cfg.world),
            "world_model_class_long": world.identity(longer.paper),
            "world_model_class_course_long": world.identity(longer.course),
            "world_model_class_long20k": world.identity(refit_base),
            "world_model_class_long20k_mlp": refit.refit_identity(
                refit_config, world.identity(refit_base))}
    for term, suffix in world.ABLATION_SUFFIXES.items():
        runs[f"world_model_class_{suffix}"] = world.identity(world.ablation_config(cfg.world, term))
        if term in longer.ablations:
            runs[f"world_model_class_long_{suffix}"] = world.identity(
                world.ablation_config(longer.paper, term))
    return runs


def _video_runs() -> dict[str, dict]:
    cfg = preset("03", "class")
    train_digits, _ = split_digits(load_mnist("test", download=False)[0],
                                   n_train=cfg.n_train_digits)
    configs = [("class", c) for c in video.ablation_configs(cfg.train, cfg.rollout_steps,
                                                            cfg.seeds)]
    configs += [("class_long", c) for c in cfg.long_runs()]
    configs += [("class_autoregressive", replace(cfg.train, unroll="autoregressive"))]
    return {video.run_name(scale, c): video.identity(c, train_digits) for scale, c in configs}


def _flat(value, prefix: str = "") -> dict:
    """Nested dicts as one level of dotted keys; tuples as lists (how a file may store them)."""
    if isinstance(value, dict):
        return {k: v for key, item in value.items()
                for k, v in _flat(item, f"{prefix}{key}.").items()}
    return {prefix.rstrip("."): list(value) if isinstance(value, tuple) else value}


def compare(stored: dict, today: dict) -> tuple[list[str], list[str], list[str]]:
    """``(disagree, only stored, only today)``: dotted field names of the two identities."""
    old, new = _flat(stored), _flat(today)
    disagree = [k for k in new if k in old and old[k] != new[k]]
    return disagree, sorted(set(old) - set(new)), sorted(set(new) - set(old))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--check", action="store_true",
                        help="only report; write nothing; exit 1 if any file differs")
    parser.add_argument("--drop", action="append", default=[], metavar="FIELD",
                        help="a dotted field the identity no longer records (repeatable)")
    args = parser.parse_args(argv)
    refused, differ = 0, []
    for name, today in shipped_runs().items():
        path = SHIPPED_DIR / f"{name}.pt"
        state = load_checkpoint(path)
        if state.get("config") == today:
            continue
        differ.append(f"{name}.pt")
        disagree, only_stored, only_today = compare(state.get("config") or {}, today)
        print(f"{name}: only stored {only_stored}; only today {only_today}")
        unexplained = [field for field in only_stored if field not in args.drop]
        if disagree or unexplained:
            refused += 1
            print(f"  REFUSED, another run: {disagree}" if disagree else f"  REFUSED: the file "
                  f"records {unexplained}, which today's identity does not (--drop FIELD)")
        elif not args.check:
            save_checkpoint(path, **{**state, "config": today})
            print(f"  re-saved {Path(path).name}")
    if args.check and differ:  # a check fails on any file today's notebooks would not load
        print(f"{len(differ)} file(s) differ from today's identity: {', '.join(differ)}")
        return 1
    return 1 if refused else 0


if __name__ == "__main__":
    raise SystemExit(main())
