"""Chapter 05's training step: the notebook's cell is the step that trains, and an edit to it
is a run of its own, which never loads or replaces the unedited run's checkpoint.

tests/test_one_source.py compares the cell's code with ``training.world.world_model_step``;
here the cell itself trains, in notebook 05's loop: unedited it gives the package step's history
bit for bit, edited it gives another, and it calls the learner's two exercise functions on every
step.
"""

import linecache
from dataclasses import replace

import pytest
import torch
from test_one_source import notebook_function

from ebjepa_tutorial.course.presets import preset
from ebjepa_tutorial.training import world
from research.train_world import notebook, train_world_model

NOTEBOOK = "05_world_model.ipynb"
# the ci preset: the class recipe's window, wall starts, still steps, replay and channels_last
CI = preset("05", "ci").train
SHORT = replace(CI, steps=3, n_trajectories=64, batch_size=8)  # logs steps 0 and 2


@pytest.fixture
def small_replay(monkeypatch):
    """SHORT's replayed updates on 64 windows, not 1,024: what they test is the same."""
    monkeypatch.setattr(world, "REPLAY_BATCH", 64)


def notebook_step(edit=lambda source: source, **names):
    """The notebook's ``world_model_step``, defined among the package's names (those the
    notebook imports before the cell) and ``names`` (e.g. the learner's functions)."""
    source = notebook_function(NOTEBOOK, "world_model_step")
    edited = edit(source)
    assert edited == source or edit(source) != source
    space = {**vars(world), **names}
    filename = f"<notebook 05 cell, {len(linecache.cache)}>"  # readable by inspect, as in IPython
    linecache.cache[filename] = (len(edited), None, edited.splitlines(True), filename)
    exec(compile(edited, filename, "exec"), space)
    return space["world_model_step"]


def train(step, config=SHORT):
    return train_world_model(config, progress=False, device="cpu", step=step)


def weights(model) -> list[torch.Tensor]:
    return [t for t in model.state_dict().values() if isinstance(t, torch.Tensor)]


def test_the_cell_as_shown_trains_the_packages_run_and_an_edit_changes_it(small_replay):
    package_model, package = train(world.world_model_step)
    shown_model, shown = train(notebook_step())
    assert shown == package  # every logged term, bit for bit
    assert all(torch.equal(a, b) for a, b in zip(weights(shown_model), weights(package_model)))
    # twice the prediction term's gradient (Adam ignores a scale of the whole gradient)
    edited = notebook_step(lambda s: s.replace(
        "total.backward()", "(total + terms['prediction']).backward()"))
    _, changed = train(edited)
    assert changed["loss"][0] == package["loss"][0]  # the same first batch and weights ...
    assert changed["loss"][-1] != package["loss"][-1]  # ... then another update


@pytest.mark.slow  # ten steps of the ci run: a pin of its numbers, for CI
def test_the_ci_run_keeps_the_terms_it_had_before_the_step_moved_into_the_notebook():
    # recorded from train_world_model before world_model_step existed (the ci preset, 10 steps,
    # on 1 thread); bit-identical on the machine that recorded it
    _, history = train(notebook_step(), CI)
    before = {"step": [0, 9], "loss": [8.430205345153809, 4.285619258880615],
              "prediction": [0.06543906778097153, 0.09975956380367279],
              "temporal": [0.017093710601329803, 0.022132975980639458],
              "inverse_dynamics": [0.6459769606590271, 0.5691583156585693],
              "variance": [0.4606993496417999, 0.1303287148475647],
              "covariance": [0.017809344455599785, 0.15823078155517578]}
    assert history.keys() == before.keys()
    for name, values in before.items():
        assert history[name] == pytest.approx(values, rel=1e-5), name


def test_the_step_calls_the_learners_functions_on_every_step(small_replay):
    calls = []

    def temporal_similarity(z):  # the learner's exercise 1, counted
        calls.append("temporal")
        return world.temporal_similarity_loss(z)

    def inverse_dynamics(predict_actions, z, actions):  # exercise 2
        calls.append("inverse")
        return world.inverse_dynamics_loss(predict_actions, z, actions)

    train(notebook_step(temporal_similarity=temporal_similarity,
                        inverse_dynamics=inverse_dynamics))
    assert calls == ["temporal", "inverse"] * SHORT.steps


def test_an_edited_step_is_a_run_of_its_own(tmp_path, monkeypatch, capsys, small_replay):
    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path))
    run, train_or_load = replace(SHORT, steps=2), notebook().train_or_load
    train_or_load(run, "world", notebook_step(), "cpu")
    assert "Trained and saved" in capsys.readouterr().out
    train_or_load(run, "world", notebook_step(), "cpu")  # the same code
    assert "Loaded a trained model" in capsys.readouterr().out
    # twice the prediction term's gradient (Adam ignores a scale of the whole gradient)
    edited = notebook_step(lambda s: s.replace(
        "total.backward()", "(total + terms['prediction']).backward()"))
    assert world.identity(run, edited)["step"] and "step" not in world.identity(run)
    _, history = train_or_load(run, "world", edited, "cpu")
    assert "Trained and saved" in capsys.readouterr().out and len(history["loss"]) == 2
    train_or_load(run, "world", edited, "cpu")
    assert "Loaded a trained model" in capsys.readouterr().out  # cached as a run of its own
    train_or_load(run, "world", notebook_step(), "cpu")
    assert "moved it back" in capsys.readouterr().out  # the unedited run was kept, not lost
