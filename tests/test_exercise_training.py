"""Chapters 00 and 01 train with the learner's own functions once they pass their checks:
chapter 00 its variance and covariance terms, chapter 01 its VICReg loss."""

from dataclasses import replace

import pytest
import torch
from test_one_source import chapter_00_loop, notebook_function

from ebjepa_tutorial import losses
from ebjepa_tutorial.course import exercises
from ebjepa_tutorial.course.presets import preset
from ebjepa_tutorial.losses.vicreg import variance_term as course_term  # a notebook's import
from ebjepa_tutorial.training import image, toy

CONFIG = replace(preset("01", "ci").config, steps=4, warmup_steps=1)  # chapter 01's ci run, cut


def test_the_toy_run_trains_with_the_terms_it_is_given():
    x, _ = toy.make_blobs(64, k=3, seed=0)
    coeffs = image.VICReg(inv_coeff=1.0, std_coeff=1.0, cov_coeff=1.0)
    calls = {"variance": 0, "covariance": 0}

    def variance_term(z, gamma=1.0, eps=1e-4):  # a learner's own, written differently
        calls["variance"] += 1
        return torch.relu(gamma - (z.var(dim=0) + eps).sqrt()).mean()

    def covariance_term(z):
        calls["covariance"] += 1
        cov = torch.cov(z.T)
        return (cov.pow(2).sum() - cov.diagonal().pow(2).sum()) / (z.shape[1] * (z.shape[1] - 1))

    train_toy = chapter_00_loop()  # notebook 00's loop
    course, course_history = train_toy(x, coeffs, steps=5, seed=0)
    mine, history = train_toy(x, coeffs, steps=5, seed=0, variance=variance_term,
                              covariance=covariance_term)
    assert calls == {"variance": 10, "covariance": 10}  # both views, every step
    assert torch.allclose(torch.tensor(history["loss"]), torch.tensor(course_history["loss"]),
                          atol=1e-5)

    def no_spread(z):  # a term that never pushes: the run must differ
        return z.sum() * 0.0

    _, other = train_toy(x, coeffs, steps=5, seed=0, variance=no_spread, covariance=no_spread)
    assert other["variance"][-1] == 0.0 and course_history["variance"][-1] > 0.0


def test_the_course_s_terms_are_the_default():
    z_a, z_b = torch.randn(16, 4), torch.randn(16, 4)
    explicit = losses.vicreg_loss(z_a, z_b, 1.0, 2.0, 3.0, variance=losses.variance_term,
                                  covariance=losses.covariance_term)[0]
    assert torch.equal(explicit, losses.vicreg_loss(z_a, z_b, 1.0, 2.0, 3.0)[0])


def _chapter_01_step(vicreg):
    """Notebook 01's training step, defined as its cell does, after its exercise 1 cell."""
    space = {**vars(image), "vicreg": vicreg}
    exec(notebook_function("01_vicreg.ipynb", "vicreg_step"), space)
    return space["vicreg_step"]


def test_chapter_01_trains_with_the_learner_s_vicreg_once_it_passes(capsys):
    calls = []

    def vicreg(z_a, z_b, inv_coeff, std_coeff, cov_coeff):  # a learner's own, passing
        calls.append(1)
        centred = [z - z.mean(0) for z in (z_a, z_b)]
        var = sum(torch.relu(1 - (z.var(0) + 1e-4).sqrt()).mean() for z in (z_a, z_b)) / 2
        cov = sum(((c.T @ c / (len(c) - 1)) * (1 - torch.eye(c.shape[1]))).pow(2).sum()
                  / (c.shape[1] * (c.shape[1] - 1)) for c in centred) / 2
        return inv_coeff * (z_a - z_b).pow(2).mean() + std_coeff * var + cov_coeff * cov

    checked = exercises.check_vicreg(vicreg)
    assert checked is vicreg and exercises.whose(checked) == "your"
    calls.clear()
    config, images = CONFIG, torch.randint(0, 256, (64, 3, 32, 32), dtype=torch.uint8)
    _, history = image.train_image_jepa(config, images, progress=False,
                                        step=_chapter_01_step(checked))
    assert len(calls) == config.steps  # the learner's function, at every step
    _, course = image.train_image_jepa(config, images, progress=False)
    assert torch.allclose(torch.tensor(history["loss"]), torch.tensor(course["loss"]), rtol=1e-3)


def test_chapter_01_trains_with_the_course_s_vicreg_while_the_learner_s_is_unwritten(capsys):
    def vicreg(z_a, z_b, inv_coeff, std_coeff, cov_coeff):  # the student version's stub
        raise NotImplementedError("write the VICReg loss")

    checked = exercises.check_vicreg(vicreg)
    assert checked is losses.vicreg.vicreg and exercises.whose(checked) == "the course's"
    config = CONFIG
    images = torch.randint(0, 256, (64, 3, 32, 32), dtype=torch.uint8)
    _, history = image.train_image_jepa(config, images, progress=False,
                                        step=_chapter_01_step(checked))
    assert history == image.train_image_jepa(config, images, progress=False)[1]


def _in_notebook(fn):
    """``fn`` as if a notebook cell defined it (its module ``__main__``)."""
    fn.__module__ = "__main__"
    return fn


def test_a_notebook_answer_that_calls_the_course_s_own_function_is_refused_and_never_trains():
    wrappers = [  # through a module's attributes, an alias, a lambda inside, a slip on top
        lambda z, gamma=1.0, eps=1e-4: losses.vicreg.variance_term(z, gamma, eps),
        lambda z, gamma=1.0, eps=1e-4: course_term(z, gamma, eps),
        lambda z, gamma=1.0, eps=1e-4: (lambda y: losses.variance_term(y, gamma, eps))(z),
        lambda z, gamma=1.0, eps=1e-4: 2 * losses.variance_term(z, gamma, eps),
    ]
    for wrapper in map(_in_notebook, wrappers):
        try:
            exercises.check_variance_term(wrapper)
        except exercises.ExerciseError as error:
            assert "calls the course's own variance_term" in str(error)
            assert "hint" in str(error).lower()  # and offers the next hint
        else:
            raise AssertionError("a wrapper of the course's function passed")
        assert getattr(wrapper, exercises.common.CHECKED) == "failed"  # so no run takes it


def test_a_wrapper_hidden_in_a_notebook_helper_or_a_closure_is_refused_too():
    def helper(z, gamma, eps):  # the call two steps away from the answer
        return losses.variance_term(z, gamma, eps)

    def answer(z, gamma=1.0, eps=1e-4):
        return helper(z, gamma, eps)

    def made_with(term):  # the course's function captured in a closure
        return lambda z, gamma=1.0, eps=1e-4: term(z, gamma, eps)

    def recursive(z, gamma=1.0, eps=1e-4, depth=0):  # reads itself: the walk must end
        return recursive(z, gamma, eps, 1) if depth == 0 else course_term(z, gamma, eps)

    _in_notebook(helper)
    for wrapper in map(_in_notebook, (answer, made_with(losses.variance_term), recursive)):
        with pytest.raises(exercises.ExerciseError, match="calls the course's own variance_term"):
            exercises.check_variance_term(wrapper)


def test_a_notebook_answer_may_call_the_course_s_other_functions(capsys):
    def vicreg(z_a, z_b, inv_coeff=25.0, std_coeff=25.0, cov_coeff=1.0):  # the course's terms
        invariance = (z_a - z_b).pow(2).mean()
        variance = (losses.variance_term(z_a) + losses.variance_term(z_b)) / 2
        covariance = (losses.covariance_term(z_a) + losses.covariance_term(z_b)) / 2
        return inv_coeff * invariance + std_coeff * variance + cov_coeff * covariance

    assert exercises.check_vicreg(_in_notebook(vicreg)) is vicreg
    assert "Correct" in capsys.readouterr().out
