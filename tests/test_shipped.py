"""Every shipped checkpoint is the run its notebook asks for at class scale.

``load_or_train`` loads a file only if its stored run identity equals the
notebook's; a shipped file that drifted from the preset would be skipped
silently and the class would wait for a retrain. The list of which preset each
file is the run of is ``research.resave_checkpoints.shipped_runs`` (the command
that re-saves the files when identities change); these tests hold the files to
it, and the sweep file's runs to notebook 02's plan. No model is built.
"""

import re
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from ebjepa_tutorial.course import reference
from ebjepa_tutorial.course.presets import preset
from ebjepa_tutorial.data import DataNotFoundError, load_mnist
from ebjepa_tutorial.training.checkpoints import load_checkpoint, save_checkpoint
from research import refit, resave_checkpoints, sweep

SHIPPED = Path(__file__).resolve().parents[1] / "checkpoints"


@pytest.fixture(scope="module")
def runs():
    try:
        load_mnist("test", download=False)
    except DataNotFoundError:
        pytest.skip("MNIST is not on this machine (set EBJEPA_DATA): the video runs need it")
    return resave_checkpoints.shipped_runs()


def test_every_shipped_file_is_the_run_its_notebook_asks_for(runs):
    on_disk = {p.stem for p in SHIPPED.glob("*.pt")}
    assert on_disk == set(runs), f"unlisted {on_disk - set(runs)}, missing {set(runs) - on_disk}"
    wrong = [name for name, expected in runs.items()
             if load_checkpoint(SHIPPED / f"{name}.pt")["config"] != expected]
    assert not wrong, f"{wrong} would be retrained: python -m research.resave_checkpoints"


def test_shipped_video_weights_are_half_precision(runs):
    for name in (n for n in runs if n.startswith("video_jepa")):
        weights = load_checkpoint(SHIPPED / f"{name}.pt")["model"]
        assert {w.dtype for w in weights.values() if w.is_floating_point()} == {torch.float16}


def test_the_refit_and_course_long_runs_are_what_their_names_say():
    cfg = preset("06", "class")
    longer = cfg.longer
    base, refit_config = refit.shipped_pair()
    assert base == replace(longer.paper, steps=2 * longer.paper.steps)
    assert refit_config == refit.RefitConfig()  # the command's defaults
    assert longer.course.model.predictor == cfg.world.model.predictor == "mlp"
    assert longer.course.steps > cfg.world.steps and longer.course.recipe.grad_clip > 0
    assert longer.paper.n_trajectories == 100_000 and longer.paper.steps > cfg.world.steps


def test_resave_refuses_to_relabel_another_run():
    stored = {"steps": 2800, "model": {"predictor": "mlp"}, "lr": 0.001}
    disagree, only_stored, only_today = resave_checkpoints.compare(
        stored, {"steps": 5600, "model": {"predictor": "mlp"}, "seed": 0})
    assert disagree == ["steps"] and only_stored == ["lr"] and only_today == ["seed"]
    assert resave_checkpoints.compare({"widths": [1, 2]}, {"widths": (1, 2)})[0] == []


def test_resave_keeps_a_file_whose_identity_records_more_unless_told(tmp_path, monkeypatch,
                                                                     capsys):
    edited = {"steps": 2800, "step": "9f2c"}  # e.g. a run of an edited training step
    save_checkpoint(tmp_path / "run.pt", model={}, config=edited)
    monkeypatch.setattr(resave_checkpoints, "SHIPPED_DIR", tmp_path)
    monkeypatch.setattr(resave_checkpoints, "shipped_runs", lambda: {"run": {"steps": 2800}})
    assert resave_checkpoints.main([]) == 1
    assert "REFUSED: the file records ['step']" in capsys.readouterr().out
    assert load_checkpoint(tmp_path / "run.pt")["config"] == edited
    assert resave_checkpoints.main(["--drop", "step"]) == 0
    assert load_checkpoint(tmp_path / "run.pt")["config"] == {"steps": 2800}


def test_the_sweep_file_holds_every_run_of_notebook_02():
    cfg = preset("02", "class")
    path = SHIPPED / "sweeps_class.json"
    assert path.is_file(), f"{path} is documented in checkpoints/README.md but missing"
    stored = sweep.stored_rows(path)
    missing = [run for group in sweep.sweep_plan("class").values() for run in group
               if sweep.key(run.config, cfg.train_images, cfg.test_images) not in stored]
    assert not missing, f"{len(missing)} runs would be retrained: {missing[:2]}"


# a recorded figure's key, its notebook, what its protocol says of the run and its probe, and
# the sizes of the notebook's class preset that must say the same
RECORDED_SIZES = [
    ("world_probe_px", "05", r"^(\d+) steps; linear probe fitted on (\d+) trajectories, scored "
     r"on (\d+) held-out ones of (\d+) steps", lambda c: (c.train.steps, c.n_probe, c.n_test,
                                                      c.horizon)),
    ("video_map", "03", r"fitted on (\d+) clips of training digits, AP on (\d+) clips of "
     r"held-out digits, horizons 1\.\.(\d+)", lambda c: (c.n_probe, c.n_eval, c.horizons)),
    ("video_map_class_K4", "03", r"K = (\d+), ([\d,]+) steps",
     lambda c: (c.train.rollout_steps, c.train.steps)),
    ("video_map_long_K4", "03", r"K = 4, ([\d,]+) steps", lambda c: (c.long_config.steps,)),
    ("random_walk_success", "04", r"^(\d+) episodes of (\d+) steps",
     lambda c: (c.n_episodes, c.episode_steps)),
    ("planning_success_class", "06", r"seeds (\d+)-\d+; (\d+) steps; .*MPPI H(\d+) N(\d+) "
     r"J(\d+) \((\d+) warm\), first spread (\d+) px, re-plan every (\d+), stands still within "
     r"(\d+) px", lambda c: (c.first_seed, c.episode_steps, c.planner.horizon, c.planner.samples,
                             c.planner.iterations, c.planner.habits.warm_iterations,
                             c.planner.noise.std, c.planner.execute, c.planner.habits.stop_px)),
    ("sweep_vicreg_tenfold_points", "02", r"(\d+) steps per run", lambda c: (c.sweep_steps,)),
    ("vicreg_probe_acc", "01", r"^(\d+) steps", lambda c: (c.config.steps,)),
    ("sigreg_probe_acc", "02", r"^(\d+) steps", lambda c: (c.config.steps,)),
    ("vicreg_shipped_probe_acc", "01", r"for ([\d,]+) steps .*, ([\d,]+) train / ([\d,]+) test",
     lambda c: (c.long_config.steps, c.train_images, c.test_images)),
    ("sigreg_shipped_probe_acc", "02", r"for ([\d,]+) steps", lambda c: (c.long_config.steps,)),
]


@pytest.mark.parametrize("key, notebook, protocol, sizes", RECORDED_SIZES,
                         ids=[key for key, *_ in RECORDED_SIZES])
def test_a_recorded_figure_was_measured_at_its_notebook_s_class_sizes(key, notebook, protocol,
                                                                     sizes):
    """A notebook compares its class run's figure with the recorded one (reference.compare),
    which means something only while the class preset keeps the sizes the figure was
    measured with: a preset edited apart from its figure would compare unlike runs."""
    recorded = reference.load()[key]["protocol"]
    found = re.search(protocol, recorded)
    assert found, f"{key}: {protocol!r} not in its protocol {recorded!r}"
    numbers = tuple(float(group.replace(",", "")) for group in found.groups())
    assert numbers == sizes(preset(notebook, "class")), key
