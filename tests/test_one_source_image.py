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


def _notebook_01(vicreg_source: str):
    """Notebook 01's step and the learner's ``vicreg`` from ``vicreg_source``, both defined
    as a kernel defines a cell's functions (in ``__main__``)."""
    space = {**vars(image), "__name__": "__main__"}
    for source in (vicreg_source, notebook_function("01_vicreg.ipynb", "vicreg_step")):
        filename = f"<cell {abs(hash(source))}>"
        linecache.cache[filename] = (len(source), None, source.splitlines(True), filename)
        exec(compile(source, filename, "exec"), space)
    return space


RIGHT = """def vicreg(z_a, z_b, inv_coeff, std_coeff, cov_coeff):
    return vicreg_loss(z_a, z_b, inv_coeff, std_coeff, cov_coeff)[0]
"""


def test_a_learners_loss_trains_the_courses_run_only_once_it_passed_its_check():
    from ebjepa_tutorial.course import exercises

    config = preset("01", "ci").config
    course = image.identity(config)
    space = _notebook_01(RIGHT)
    # written but not checked yet: it may be anything, so its runs are its own
    unchecked = image.identity(config, step=space["vicreg_step"])
    assert unchecked != course and set(unchecked["calls"]) == {"vicreg"}
    space["vicreg"] = exercises.check_vicreg(space["vicreg"])
    assert image.identity(config, step=space["vicreg_step"]) == course
    # an edit after the check is a new function, unchecked again
    space = _notebook_01(RIGHT.replace("inv_coeff, std_coeff, cov_coeff)[0]",
                                       "inv_coeff, std_coeff, 0.0)[0]"))
    assert image.identity(config, step=space["vicreg_step"]) not in (course, unchecked)
    # the student's stub: the check hands over the course's function, whose run is the course's
    space = _notebook_01(RIGHT.replace("return vicreg_loss(", "raise NotImplementedError(")
                         .replace(")[0]", ")"))
    space["vicreg"] = exercises.check_vicreg(space["vicreg"])
    assert image.identity(config, step=space["vicreg_step"]) == course


def test_a_loss_that_failed_its_check_trains_no_run():
    from ebjepa_tutorial.course import exercises

    # a failed check leaves the learner's function bound (the assignment never happens)
    space = _notebook_01(RIGHT.replace("std_coeff, cov_coeff)[0]", "std_coeff, cov_coeff)[0] * 2"))
    with pytest.raises(exercises.ExerciseError):
        space["vicreg"] = exercises.check_vicreg(space["vicreg"])
    with pytest.raises(ValueError, match=r"vicreg failed its exercise's check, so no run trains "
                                         r"with it: correct it and rerun its check cell"):
        image.identity(preset("01", "ci").config, step=space["vicreg_step"])


def test_a_step_that_is_no_plain_function_still_has_an_identity():
    import functools

    config = preset("01", "ci").config
    step = functools.partial(image.vicreg_step)  # no __code__ to read its calls from
    assert image.identity(config, step=step) != image.identity(config)  # a run of its own
