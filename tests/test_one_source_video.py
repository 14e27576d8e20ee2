"""Chapter 03's training step is written in the notebook and is the package's code.

The notebook defines ``video_jepa_step`` (one whole step: encode, the multistep loss,
projector, variance and covariance, weighted total, backward, the gradients' mean over
ranks, the optimiser's and the scheduler's steps) in a cell the learner edits, and its
training cells pass it to the notebook's loop. The package's
``training.video.video_jepa_step`` trained the shipped checkpoints. These tests fail when
the two differ in code, show that the unedited cell reproduces the package's run bit for bit
while an edit to it changes what trains at ``ci``, and that an edited step is a run of its
own, which never loads or replaces the unedited run's checkpoint.
"""

import inspect
import linecache

import torch
from test_one_source import code_of, notebook_function

from ebjepa_tutorial.training import video
from research.train_video import notebook

NOTEBOOK = "03_video_jepa.ipynb"
# 2 steps of K = 1, 2 of K = 4
CONFIG = video.VideoJEPAConfig(model=video.VIDEO_MODEL_CONFIGS["ci"], n_clips=16, batch_size=4,
                               steps=4, recipe=video.Recipe(channels_last=False))


def _define(code: str):
    """``video_jepa_step`` as a notebook cell defines it: its source readable, as Jupyter
    keeps a cell's (the run's identity compares the step's code)."""
    space = dict(vars(video))  # the names the notebook imports before the cell
    name = f"<cell {len(_CELLS)}>"
    _CELLS.append(name)
    linecache.cache[name] = (len(code), None, code.splitlines(keepends=True), name)
    exec(compile(code, name, "exec"), space)
    return space["video_jepa_step"]


_CELLS: list[str] = []


def _clips() -> torch.Tensor:
    digits = torch.randint(0, 256, (20, 1, 28, 28), generator=torch.Generator().manual_seed(0),
                           dtype=torch.uint8)
    return video.make_clips(CONFIG, digits)


def test_the_notebook_shows_the_step_the_package_trains_with():
    shown = notebook_function(NOTEBOOK, "video_jepa_step")
    assert code_of(shown) == code_of(inspect.getsource(video.video_jepa_step)), (
        f"video_jepa_step in {NOTEBOOK} and training.video.video_jepa_step differ: change both")


def test_an_edit_to_the_step_changes_what_trains_and_the_cell_as_shown_does_not():
    source = notebook_function(NOTEBOOK, "video_jepa_step")
    edited = source.replace("COV_COEFF * covariance", "0.0 * covariance")
    assert edited != source
    clips, loop = _clips(), notebook().train_video_jepa
    package, package_history = loop(CONFIG, clips, video.video_jepa_step)
    as_shown, history = loop(CONFIG, clips, _define(source))
    _, changed = loop(CONFIG, clips, _define(edited))
    assert history == package_history  # every logged term, bit for bit
    for name, value in package.state_dict().items():
        assert torch.equal(as_shown.state_dict()[name], value), name
    assert changed["loss"][0] != package_history["loss"][0]  # the total no longer counts it
    assert changed["covariance"][-1] != package_history["covariance"][-1]  # training followed


def test_an_edited_step_is_a_run_of_its_own(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("EBJEPA_CACHE", str(tmp_path))
    source = notebook_function(NOTEBOOK, "video_jepa_step")
    edited = _define(source.replace("total = prediction +", "total = 2 * prediction +"))
    digits = torch.randint(0, 256, (20, 1, 28, 28), dtype=torch.uint8,
                           generator=torch.Generator().manual_seed(1))
    course = video.identity(CONFIG, digits)
    assert "step" not in course  # the default step adds nothing: the shipped files still load
    assert video.identity(CONFIG, digits, _define(source)) == course  # the cell as shown
    assert video.identity(CONFIG, digits, edited) == {**course, "step": course_hash(edited)}
    train_or_load = notebook().train_or_load
    train_or_load(CONFIG, "run", digits, video.video_jepa_step)
    assert "Trained and saved" in capsys.readouterr().out
    train_or_load(CONFIG, "run", digits, edited)
    assert "Trained and saved" in capsys.readouterr().out  # never the unedited run's file
    train_or_load(CONFIG, "run", digits, edited)
    assert "Loaded a trained model" in capsys.readouterr().out  # cached as itself
    train_or_load(CONFIG, "run", digits, video.video_jepa_step)
    assert "moved it back" in capsys.readouterr().out  # the unedited run was kept aside


def course_hash(step) -> str:
    return video.step_identity(step, video.video_jepa_step)["step"]
