"""Chapters 01 and 02 write their training step in the notebook, and the package runs the same.

Notebook 01 defines ``vicreg_step`` and notebook 02 ``sigreg_step`` in a cell the learner
edits; ``training.image`` holds the same functions, which ``train_image_jepa`` (and so the
commands that made the shipped checkpoints) calls. These tests fail when a notebook's step
and the package's differ in code, show that an edit to the cell changes what trains at
``ci`` scale while the cell as shown trains exactly the package's run, and that an edited
step never loads, or replaces, the checkpoint of the unedited run.
"""

import inspect
import linecache
from dataclasses import replace

import pytest
import torch
from test_one_source import code_of, notebook_function

from ebjepa_tutorial.course.presets import preset
from ebjepa_tutorial.training import image

# (notebook, its preset, the step it defines, the package's copy, an edit that changes a run)
STEPS = [
    ("01_vicreg.ipynb", "01", "vicreg_step", image.vicreg_step,
     ("weights.inv_coeff", "2 * weights.inv_coeff")),  # twice the invariance weight
    ("02_sigreg.ipynb", "02", "sigreg_step", image.sigreg_step,
     ("weights.lam", "10 * weights.lam")),  # ten times SIGReg's weight
]


def define(source: str, name: str):
    """``name`` defined by ``source`` with the names the notebook imports, its source kept
    where ``inspect`` finds it (as IPython keeps a cell's)."""
    filename = f"<cell {name} {abs(hash(source))}>"
    linecache.cache[filename] = (len(source), None, source.splitlines(True), filename)
    space = dict(vars(image))  # embed, vicreg, vicreg_loss, sigreg_loss
    exec(compile(source, filename, "exec"), space)
    return space[name]


def _images(n=64, seed=0):
    generator = torch.Generator().manual_seed(seed)
    return torch.randint(0, 256, (n, 3, 32, 32), dtype=torch.uint8, generator=generator)


@pytest.mark.parametrize("notebook, scale, name, package, edit", STEPS, ids=[s[2] for s in STEPS])
def test_the_notebook_shows_the_step_the_package_runs(notebook, scale, name, package, edit):
    assert code_of(notebook_function(notebook, name)) == code_of(
        inspect.getsource(package)), (
        f"{name} in {notebook} and training.image.{name} differ: change both together")
    config = preset(scale, "ci").config
    assert image.package_step(config) is package  # the step that trains the chapter's runs


@pytest.mark.parametrize("notebook, scale, name, package, edit", STEPS, ids=[s[2] for s in STEPS])
def test_an_edit_to_the_step_changes_what_trains(notebook, scale, name, package, edit):
    source = notebook_function(notebook, name)
    edited = source.replace(*edit)
    assert edited != source
    # the ci config cut to 4 steps (history rows at steps 0 and 3): enough to see an edit
    config, images = replace(preset(scale, "ci").config, steps=4, warmup_steps=1), _images()
    trained, history = image.train_image_jepa(config, images, progress=False)
    shown, history_shown = image.train_image_jepa(config, images, progress=False,
                                                  step=define(source, name))
    _, history_edited = image.train_image_jepa(config, images, progress=False,
                                               step=define(edited, name))
    assert history_shown == history  # the cell as shown is the package's run, bit for bit
    assert all(torch.equal(p, q) for p, q in zip(shown.parameters(), trained.parameters()))
    assert history_edited["loss"] != history["loss"]
    assert history_edited["invariance"][1:] != history["invariance"][1:]  # it trained otherwise


def test_an_edited_step_is_a_run_of_its_own(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path))
    source = notebook_function("01_vicreg.ipynb", "vicreg_step")
    shown, edited = (define(s, "vicreg_step") for s in (source, source.replace(*STEPS[0][-1])))
    config = image.ImageJEPAConfig(widths=(4, 4, 8, 8), projector=(16, 16), batch_size=8,
                                   steps=3, warmup_steps=1)
    # the cell as shown (comments and docstring aside) is the package's run; an edit is not
    assert image.identity(config, step=shown) == image.identity(config)
    assert image.identity(config, step=edited) != image.identity(config)
    images = _images(32)
    _, unedited = image.train_or_load(config, "a_run", images, step=shown)
    assert "Trained and saved" in capsys.readouterr().out
    _, history = image.train_or_load(config, "a_run", images, step=edited)
    assert "Trained and saved" in capsys.readouterr().out  # not loaded from the unedited run
    assert history != unedited
    _, again = image.train_or_load(config, "a_run", images)  # the package's step: unedited
    assert "Loaded" in capsys.readouterr().out and again == unedited  # kept, not replaced
