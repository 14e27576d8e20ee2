"""Chapter 03's training step is written in the notebook and is the package's code.

The notebook defines ``video_jepa_loss`` (one step's loss: encode, the multistep loss,
projector, variance and covariance, weighted total) in a cell the learner edits, and its
training cells pass it to the package's loop. The package's
``training.video.video_jepa_loss`` trained the shipped checkpoints. These tests fail
when the two differ in code, show that an edit to the cell changes what trains at ``ci``
while the unedited cell reproduces the package's history, and that an edited step never
reads or writes a checkpoint.
"""

import inspect

import torch
from test_one_source import code_of, notebook_function

from ebjepa_tutorial.training import video

NOTEBOOK = "03_video_jepa.ipynb"
CONFIG = video.VideoJEPAConfig(model=video.VIDEO_MODEL_CONFIGS["ci"], n_clips=16, batch_size=4,
                               steps=4, channels_last=False)  # 2 steps of K = 1, 2 of K = 4


def _define(code: str):
    space = dict(vars(video))  # the names the notebook imports before the cell
    exec(code, space)
    return space["video_jepa_loss"]


def _clips() -> torch.Tensor:
    digits = torch.randint(0, 256, (20, 1, 28, 28), generator=torch.Generator().manual_seed(0),
                           dtype=torch.uint8)
    return video.make_clips(CONFIG, digits)


def test_the_notebook_shows_the_step_the_package_trains_with():
    shown = notebook_function(NOTEBOOK, "video_jepa_loss")
    assert code_of(shown) == code_of(inspect.getsource(video.video_jepa_loss)), (
        f"video_jepa_loss in {NOTEBOOK} and training.video.video_jepa_loss differ: change both")


def test_an_edit_to_the_step_changes_what_trains_and_the_cell_as_shown_does_not():
    source = notebook_function(NOTEBOOK, "video_jepa_loss")
    edited = source.replace("config.cov_coeff * covariance", "0.0 * covariance")
    assert edited != source
    clips = _clips()
    _, package = video.train_video_jepa(CONFIG, clips, progress=False)
    _, as_shown = video.train_video_jepa(CONFIG, clips, progress=False, step=_define(source))
    _, changed = video.train_video_jepa(CONFIG, clips, progress=False, step=_define(edited))
    for term in ("loss", "prediction", "variance", "covariance"):
        assert as_shown[term] == package[term], term  # bit for bit
    assert changed["loss"][0] != package["loss"][0]  # the total no longer counts covariance
    assert changed["covariance"][-1] != package["covariance"][-1]  # and training followed


def test_an_edited_step_neither_loads_nor_writes_a_checkpoint(monkeypatch, capsys):
    source = notebook_function(NOTEBOOK, "video_jepa_loss")
    edited = _define(source.replace("total = prediction +", "total = 2 * prediction +"))
    assert not video.is_the_course_step(edited)
    assert video.is_the_course_step(None) and video.is_the_course_step(video.video_jepa_loss)
    digits = torch.randint(0, 256, (20, 1, 28, 28), dtype=torch.uint8,
                           generator=torch.Generator().manual_seed(1))
    calls = []
    monkeypatch.setattr(video, "load_or_train", lambda *a, **k: calls.append(a))
    model, history = video.train_or_load(CONFIG, "edited_step_run", digits, progress=False,
                                         step=edited)
    assert not calls and len(history["loss"]) > 0  # trained here, the cache never consulted
    cache, shipped = video.checkpoint_paths("edited_step_run")
    assert not any(p.exists() for p in (cache, shipped, cache.with_suffix(".partial")))
    assert "edited training step" in capsys.readouterr().out
