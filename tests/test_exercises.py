"""Exercise checkers accept the solutions, reject wrong answers; student versions are valid."""

import json
import re
from pathlib import Path

import pytest
import torch

from ebjepa_tutorial.course import exercises
from ebjepa_tutorial.course.exercises import check_wall_collision

NOTEBOOKS = sorted(Path(__file__).resolve().parents[1].glob("notebooks/*.ipynb"))
CHECKERS = {
    "variance_term": exercises.check_variance_term,
    "covariance_term": exercises.check_covariance_term,
    "wall_collision": check_wall_collision,
    "temporal_similarity": exercises.check_temporal_similarity,
    "inverse_dynamics": exercises.check_inverse_dynamics,
    "vicreg": exercises.check_vicreg,
    "vicreg_paper_to_ebjepa": exercises.check_vicreg_paper_to_ebjepa,
    "epps_pulley_1d": exercises.check_epps_pulley,
    "rollout_loss": exercises.check_rollout_loss,
    "mppi_update": exercises.check_mppi_update,
}


def _solution_functions():
    """Every function defined in a notebook cell that holds a solution region."""
    for path in NOTEBOOKS:
        for cell in json.loads(path.read_text())["cells"]:  # nbformat's import is slow
            source = "".join(cell["source"])
            if cell["cell_type"] == "code" and "### BEGIN SOLUTION" in source:
                namespace = {"torch": torch}
                exec(source, namespace)
                for name in re.findall(r"^def (\w+)\(", source, flags=re.M):
                    yield path.name, name, namespace[name]


def test_notebooks_have_exercises():
    assert NOTEBOOKS, "no notebooks found"
    assert any(True for _ in _solution_functions())


@pytest.mark.parametrize("notebook, name, fn", list(_solution_functions()),
                         ids=lambda v: v if isinstance(v, str) else "")
def test_checker_accepts_the_notebook_solution(notebook, name, fn, capsys):
    assert name in CHECKERS, f"{notebook}: exercise {name} has no checker in CHECKERS"
    assert CHECKERS[name](fn) is fn  # the notebook goes on with the learner's own function
    assert "Correct" in capsys.readouterr().out


def _biased_variance(z, gamma=1.0, eps=1e-4):
    return torch.relu(gamma - torch.sqrt(z.var(dim=0, unbiased=False) + eps)).mean()


def _per_dimension_variance(z, gamma=1.0, eps=1e-4):
    return torch.relu(gamma - torch.sqrt(z.var(dim=0) + eps))


def _covariance_with_diagonal(z):
    centred = z - z.mean(dim=0)
    cov = centred.T @ centred / (len(z) - 1)
    return cov.pow(2).sum() / (z.shape[1] * (z.shape[1] - 1))


def _covariance_divided_by_d(z):
    centred = z - z.mean(dim=0)
    cov = centred.T @ centred / (len(z) - 1)
    return (cov - torch.diag(torch.diagonal(cov))).pow(2).sum() / z.shape[1]


def _temporal_similarity_summed(z):
    return (z[:, 1:] - z[:, :-1]).pow(2).sum(dim=-1).mean()


def _temporal_similarity_swapped_axes(z):
    return (z[1:] - z[:-1]).pow(2).mean()


def _inverse_dynamics_swapped_frames(predict_actions, z, actions):
    return (predict_actions(z[:, 1:], z[:, :-1]) - actions).pow(2).mean()


def _vicreg_regularising_one_view(z_a, z_b, inv_coeff, std_coeff, cov_coeff):
    from ebjepa_tutorial import losses

    return (inv_coeff * losses.invariance_term(z_a, z_b)
            + std_coeff * losses.variance_term(z_a) + cov_coeff * losses.covariance_term(z_a))


def _epps_pulley_without_n(x, knots=17, t_max=3.0, scale_by_n=True):
    from ebjepa_tutorial.losses import sigreg

    return sigreg.epps_pulley(x, knots=knots, t_max=t_max, scale_by_n=False)


def _mppi_without_shift(actions, costs, elites, temperature):
    from ebjepa_tutorial import planning

    elite_actions, elite_costs = planning.select_elites(actions, costs, elites)
    weights = torch.exp(-elite_costs / temperature)
    return planning.weighted_mean_std(elite_actions, weights / weights.sum(1, keepdim=True))


def _mppi_weighting_every_sample(actions, costs, elites, temperature):
    from ebjepa_tutorial import planning

    return planning.mppi_update(actions, costs, actions.shape[1], temperature)


def _mppi_plain_mean(actions, costs, elites, temperature):
    from ebjepa_tutorial import planning

    return planning.cem_update(actions, costs, elites)


@pytest.mark.parametrize("checker, wrong, message", [
    (exercises.check_epps_pulley, _epps_pulley_without_n, "N times too small"),
    (exercises.check_vicreg, _vicreg_regularising_one_view, "but the answer is"),
    (exercises.check_vicreg_paper_to_ebjepa, lambda inv, std, cov, dim: (inv, std, cov * dim),
     "but the answer is"),
    (exercises.check_vicreg_paper_to_ebjepa, lambda inv, std, cov, dim: cov * dim,
     "expected a tuple of three"),
    (exercises.check_temporal_similarity, _temporal_similarity_summed, "but the answer is"),
    (exercises.check_temporal_similarity, _temporal_similarity_swapped_axes, "but the answer is"),
    (exercises.check_inverse_dynamics, _inverse_dynamics_swapped_frames, "but the answer is"),
    (exercises.check_variance_term, _biased_variance, "but the answer is"),
    (exercises.check_variance_term, _per_dimension_variance, "a single number"),
    (exercises.check_variance_term, lambda z, gamma=1.0, eps=1e-4: 0.0, "expected a torch tensor"),
    (exercises.check_covariance_term, _covariance_with_diagonal, "but the answer is"),
    (exercises.check_covariance_term, _covariance_divided_by_d, "but the answer is"),
    (exercises.check_mppi_update, _mppi_without_shift, "underflow"),
    (exercises.check_mppi_update, _mppi_weighting_every_sample, "but the answer is"),
    (exercises.check_mppi_update, _mppi_plain_mean, "but the answer is"),
    (exercises.check_mppi_update, lambda actions, costs, elites, temperature: actions.mean(1),
     "must return a pair"),
])
def test_checker_rejects_wrong_answers(checker, wrong, message):
    with pytest.raises(exercises.ExerciseError, match=message):
        checker(wrong)


@pytest.mark.parametrize("checker", list(CHECKERS.values()), ids=list(CHECKERS))
def test_an_unfinished_exercise_hands_over_the_course_implementation(checker, capsys):
    def stub(*args, **kwargs):
        raise NotImplementedError("Exercise: see the text above this cell")

    assert checker(stub) is checker.reference  # so "Run All" reaches the end of the chapter
    out = capsys.readouterr().out
    assert "not implemented yet" in out and "uses the course's implementation" in out


def test_a_wrong_answer_is_reported_without_the_checkers_insides():
    def covariance_term(z):
        return z.var(dim=0).sum()

    with pytest.raises(exercises.ExerciseError) as caught:
        exercises.check_covariance_term(covariance_term)
    frames = [frame.name for frame in caught.traceback]
    assert "compare" not in frames and "_call" not in frames  # nor the reference's name


def test_checker_reports_a_crash_in_plain_words():
    def covariance_term(z):
        return z @ z  # wrong shapes for a non-square batch

    with pytest.raises(exercises.ExerciseError, match="raised RuntimeError"):
        exercises.check_covariance_term(covariance_term)


def test_strip_solutions_keeps_hints_and_indentation():
    from ebjepa_tutorial.course import student  # imports nbformat: only where needed

    source = (
        "def f(x):\n"
        "    y = 1\n"
        "    ### BEGIN SOLUTION\n"
        "    # HINT: add y\n"
        "    return x + y\n"
        "    ### END SOLUTION\n"
    )
    assert student.strip_solutions(source) == (
        "def f(x):\n"
        "    y = 1\n"
        "    # HINT: add y\n"
        "    raise NotImplementedError('Exercise: add y')"
    )


@pytest.mark.parametrize("source", [
    "### BEGIN SOLUTION\nx = 1\n",
    "x = 1\n### END SOLUTION\n",
])
def test_unbalanced_markers_are_errors(source):
    from ebjepa_tutorial.course import student

    with pytest.raises(ValueError, match="SOLUTION"):
        student.strip_solutions(source)


@pytest.mark.slow  # nbformat's validator takes seconds to import
def test_student_versions_are_valid_and_solution_free(tmp_path, capsys):
    import nbformat

    from ebjepa_tutorial.course import student

    written = student.write_student_versions(NOTEBOOKS[0].parent, tmp_path)
    assert [p.name for p in written] == [p.name for p in NOTEBOOKS]
    for original_path, path in zip(NOTEBOOKS, written):
        original = nbformat.read(original_path, as_version=4)
        notebook = nbformat.read(path, as_version=4)
        nbformat.validate(notebook)
        assert len(notebook.cells) == len(original.cells)
        code = [c.source for c in notebook.cells if c.cell_type == "code"]
        text = [c.source for c in notebook.cells if c.cell_type == "markdown"]
        assert not any("SOLUTION" in s for s in code + text)
        assert not any("Solutions are in this notebook" in s for s in text)
        assert not any(c.get("outputs") for c in notebook.cells if c.cell_type == "code")
        stubs = [s for s in code if "raise NotImplementedError" in s]
        for source in stubs:  # every stub still defines its function, which then says "todo"
            namespace = {"torch": torch}
            exec(source, namespace)
            name = re.search(r"^def (\w+)\(", source, flags=re.M).group(1)
            assert CHECKERS[name](namespace[name]) is CHECKERS[name].reference


@pytest.mark.slow
def test_make_student_keeps_a_learners_work(tmp_path):
    from ebjepa_tutorial.course import student

    student.write_student_versions(NOTEBOOKS[0].parent, tmp_path)
    mine = tmp_path / NOTEBOOKS[0].name
    mine.write_text(mine.read_text().replace("raise NotImplementedError", "return 0  # mine"))
    assert student.write_student_versions(NOTEBOOKS[0].parent, tmp_path) == []
    assert "# mine" in mine.read_text()
    assert mine in student.write_student_versions(NOTEBOOKS[0].parent, tmp_path, overwrite=True)
    assert "# mine" not in mine.read_text()
