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
    "step_violation": exercises.check_step_violation,
    "spread_loss": exercises.check_spread_loss,
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


def _variance_without_eps(z, gamma=1.0, eps=1e-4):
    return torch.relu(gamma - z.std(dim=0)).mean()


def _variance_summed(z, gamma=1.0, eps=1e-4):
    return torch.relu(gamma - torch.sqrt(z.var(dim=0) + eps)).sum()


def _covariance_biased(z):
    centred = z - z.mean(dim=0)
    cov = centred.T @ centred / len(z)
    return (cov - torch.diag(torch.diagonal(cov))).pow(2).sum() / (z.shape[1] * (z.shape[1] - 1))


def _covariance_not_centred(z):
    cov = z.T @ z / (len(z) - 1)
    return (cov - torch.diag(torch.diagonal(cov))).pow(2).sum() / (z.shape[1] * (z.shape[1] - 1))


def _vicreg_adding_views(z_a, z_b, inv_coeff, std_coeff, cov_coeff):
    from ebjepa_tutorial import losses

    return (inv_coeff * losses.invariance_term(z_a, z_b)
            + std_coeff * (losses.variance_term(z_a) + losses.variance_term(z_b))
            + cov_coeff * (losses.covariance_term(z_a) + losses.covariance_term(z_b)))


def _vicreg_swapped_weights(z_a, z_b, inv_coeff, std_coeff, cov_coeff):
    from ebjepa_tutorial import losses

    return losses.vicreg_loss(z_a, z_b, inv_coeff, cov_coeff, std_coeff)[0]


def _epps_pulley_parts(x, knots, t_max, scale_by_n):
    t = torch.linspace(0.0, t_max, knots)
    real, imag = torch.cos(x[:, None] * t).mean(0), torch.sin(x[:, None] * t).mean(0)
    return t, real, imag, torch.exp(-(t**2) / 2), (len(x) if scale_by_n else 1)


def _epps_pulley_unweighted(x, knots=17, t_max=3.0, scale_by_n=True):
    t, real, imag, gaussian, n = _epps_pulley_parts(x, knots, t_max, scale_by_n)
    return 2 * torch.trapezoid((real - gaussian) ** 2 + imag**2, t) * n


def _epps_pulley_real_part_only(x, knots=17, t_max=3.0, scale_by_n=True):
    t, real, imag, gaussian, n = _epps_pulley_parts(x, knots, t_max, scale_by_n)
    return 2 * torch.trapezoid(gaussian * (real - gaussian) ** 2, t) * n


def _rollout(predictor, z, context, steps, tbptt, *, early=0, teacher=False, reduce=torch.mean,
             target=lambda z: z):
    """A notebook-style rollout loss; the keywords make one mistake each."""
    errors = []
    for s in range(z.shape[1] - context - steps + 1):
        window = z[:, s:s + context]
        for k in range(steps):
            if tbptt is not None and k > 0 and k % tbptt == 0:
                window = window.detach()
            if teacher:
                window = z[:, s + k:s + k + context]
            z_hat = predictor(window)
            errors.append((z_hat - target(z)[:, s + context + k - early]).pow(2).mean())
            window = torch.cat([window[:, 1:], z_hat[:, None]], dim=1)
    return reduce(torch.stack(errors))


def _rollout_off_by_one(predictor, z, context=2, steps=4, tbptt=None):
    return _rollout(predictor, z, context, steps, tbptt, early=1)


def _rollout_teacher_forcing(predictor, z, context=2, steps=4, tbptt=None):
    return _rollout(predictor, z, context, steps, tbptt, teacher=True)


def _rollout_summed(predictor, z, context=2, steps=4, tbptt=None):
    return _rollout(predictor, z, context, steps, tbptt, reduce=torch.sum)


def _rollout_detached_targets(predictor, z, context=2, steps=4, tbptt=None):
    return _rollout(predictor, z, context, steps, tbptt, target=torch.Tensor.detach)


def _temporal_similarity_detached(z):
    z = z.detach()
    return (z[:, 1:] - z[:, :-1]).pow(2).mean()


def _temporal_similarity_unsquared(z):
    return (z[:, 1:] - z[:, :-1]).norm(dim=-1).mean()


def _inverse_dynamics_detached(predict_actions, z, actions):
    z = z.detach()
    return (predict_actions(z[:, :-1], z[:, 1:]) - actions).pow(2).mean()


def _inverse_dynamics_detached_next(predict_actions, z, actions):
    return (predict_actions(z[:, :-1], z[:, 1:].detach()) - actions).pow(2).mean()


def _inverse_dynamics_summed_over_actions(predict_actions, z, actions):
    return (predict_actions(z[:, :-1], z[:, 1:]) - actions).pow(2).sum(-1).mean()


def _mppi(actions, costs, elites, temperature, *, scale=None, std=None):
    """The notebook's MPPI update; ``scale`` replaces ``/ tau`` and ``std`` the spread."""
    elite_costs, index = costs.topk(elites, dim=1, largest=False)
    elite = actions.gather(1, index[:, :, None, None].expand(-1, -1, *actions.shape[2:]))
    shifted = elite_costs - elite_costs.min(dim=1, keepdim=True).values
    logits = -shifted * temperature if scale == "times" else -shifted / temperature
    w = torch.softmax(logits, dim=1)[:, :, None, None]
    mean = (w * elite).sum(dim=1)
    var = (w * (elite - mean[:, None]).pow(2)).sum(dim=1)
    return mean, var if std == "variance" else var.sqrt()


def _mppi_variance_as_std(actions, costs, elites, temperature):
    return _mppi(actions, costs, elites, temperature, std="variance")


def _mppi_times_tau(actions, costs, elites, temperature):
    return _mppi(actions, costs, elites, temperature, scale="times")


def _wall_stay_put(pos, moves, layouts):
    from ebjepa_tutorial.envs.two_rooms import HIGH, LOW, wall_collision

    target = (pos + moves).clamp(LOW, HIGH)
    new = wall_collision(pos, moves, layouts)
    return torch.where((new != target).any(-1, keepdim=True), pos, target)


def _wall_without_door_sides(pos, moves, layouts):
    from ebjepa_tutorial.envs.two_rooms import HIGH, LOW, wall_bounds

    x_lo, x_hi, y_lo, y_hi = wall_bounds(layouts)
    x0, y0 = pos.unbind(-1)
    x1, y1 = (pos + moves).clamp(LOW, HIGH).unbind(-1)
    dx = torch.where(x1 == x0, torch.ones_like(x0), x1 - x0)
    t_in = torch.where(x1 == x0, 0.0, torch.minimum((x_lo - x0) / dx, (x_hi - x0) / dx).clamp(0, 1))
    t_out = torch.where(x1 == x0, ((x0 > x_lo) & (x0 < x_hi)).float(),
                        torch.maximum((x_lo - x0) / dx, (x_hi - x0) / dx).clamp(0, 1))
    y_in = y0 + t_in * (y1 - y0)
    hits_face = (t_out > t_in) & ((y_in < y_lo) | (y_in > y_hi))
    return torch.stack([torch.where(hits_face, torch.where(x0 <= x_lo, x_lo, x_hi), x1), y1], -1)


@pytest.mark.parametrize("checker, wrong, message", [
    (exercises.check_epps_pulley, _epps_pulley_without_n, "N times too small"),
    (exercises.check_epps_pulley, _epps_pulley_unweighted,
     r"weight w\(t\) = exp\(-t\^2/2\) is missing"),
    (exercises.check_epps_pulley, _epps_pulley_real_part_only, "imaginary part is missing"),
    (exercises.check_vicreg, _vicreg_regularising_one_view, "but the answer is .*one view only"),
    (exercises.check_vicreg, _vicreg_adding_views, "added the two views' .* average them"),
    (exercises.check_vicreg, _vicreg_swapped_weights, "swapped the weights"),
    (exercises.check_vicreg_paper_to_ebjepa, lambda inv, std, cov, dim: (inv, std, cov * dim),
     "but the answer is"),
    (exercises.check_vicreg_paper_to_ebjepa, lambda inv, std, cov, dim: cov * dim,
     "expected a tuple of three"),
    (exercises.check_vicreg_paper_to_ebjepa, lambda inv, std, cov, dim: (1.0, std / inv, cov / inv),
     r"but the answer is .*forgot the factor \(D - 1\)"),
    (exercises.check_vicreg_paper_to_ebjepa, lambda inv, std, cov, dim: (inv, std, cov * (dim - 1)),
     "did not divide by the invariance weight"),
    (exercises.check_vicreg_paper_to_ebjepa,
     lambda inv, std, cov, dim: (1.0, std / inv, cov / (dim - 1) / inv),
     r"divided the covariance weight by \(D - 1\)"),
    (exercises.check_temporal_similarity, _temporal_similarity_summed,
     "but the answer is .*summed the squared change over the D dimensions"),
    (exercises.check_temporal_similarity, _temporal_similarity_swapped_axes,
     "but the answer is .*differences along the batch axis"),
    (exercises.check_temporal_similarity, _temporal_similarity_unsquared, "unsquared distance"),
    (exercises.check_temporal_similarity, _temporal_similarity_detached,
     "right value .* but not the right gradient .* no gradient reaches the latents z"),
    (exercises.check_inverse_dynamics, _inverse_dynamics_swapped_frames,
     "but the answer is .*pair in the wrong order"),
    (exercises.check_inverse_dynamics, _inverse_dynamics_detached,
     r"right value, but no gradient reaches the latents z: did you \.detach\(\) them\?"),
    (exercises.check_inverse_dynamics, _inverse_dynamics_detached_next,
     r"gradient reaches z_t but not z_t\+1: you detached z\[:, 1:\]"),
    (exercises.check_inverse_dynamics, _inverse_dynamics_summed_over_actions,
     "summed the squared error over the A action dimensions"),
    (exercises.check_variance_term, _biased_variance, "but the answer is .*biased variance"),
    (exercises.check_variance_term, _variance_without_eps, "eps is missing from the square root"),
    (exercises.check_variance_term, _variance_summed, "summed the hinge over the D dimensions"),
    (exercises.check_variance_term, _per_dimension_variance, "a single number.*one hinge per"),
    (exercises.check_variance_term, lambda z, gamma=1.0, eps=1e-4: 0.0, "expected a torch tensor"),
    (exercises.check_covariance_term, _covariance_with_diagonal,
     "but the answer is .*forgot to zero the diagonal"),
    (exercises.check_covariance_term, _covariance_divided_by_d,
     r"but the answer is .*divided the sum by D, as the VICReg paper does"),
    (exercises.check_covariance_term, _covariance_biased, "divides by B - 1"),
    (exercises.check_covariance_term, _covariance_not_centred, "did not centre z"),
    (exercises.check_rollout_loss, _rollout_off_by_one, "off-by-one target"),
    (exercises.check_rollout_loss, _rollout_teacher_forcing, "teacher forcing"),
    (exercises.check_rollout_loss, _rollout_summed, "summed the errors instead of averaging"),
    (exercises.check_rollout_loss, _rollout_detached_targets,
     "no gradient reaches the target latents"),
    (exercises.check_wall_collision, _wall_stay_put, "cancel the whole move"),
    (exercises.check_wall_collision, _wall_without_door_sides, "not the door's sides"),
    (exercises.check_mppi_update, _mppi_without_shift, "underflow.*subtract the minimum cost"),
    (exercises.check_mppi_update, _mppi_weighting_every_sample,
     "but the answer is .*weighted all N sampled plans"),
    (exercises.check_mppi_update, _mppi_plain_mean, "but the answer is .*same weight"),
    (exercises.check_mppi_update, _mppi_variance_as_std,
     r"a wrong std: std\[\d+, \d+, \d+\] is .* \(your mean is right\).* weighted variance"),
    (exercises.check_mppi_update, _mppi_times_tau, "multiplied by the temperature"),
    (exercises.check_mppi_update, lambda actions, costs, elites, temperature: actions.mean(1),
     "must return a pair"),
])
def test_checker_rejects_wrong_answers(checker, wrong, message):
    with pytest.raises(exercises.ExerciseError, match=message):
        checker(wrong)


@pytest.mark.slow  # every known mistake of every checker: seconds
@pytest.mark.parametrize("checker", list(CHECKERS.values()), ids=list(CHECKERS))
def test_checker_names_each_mistake_it_knows(checker):
    assert len(checker.mistakes) >= 2
    for words, wrong in checker.mistakes:  # each known slip is caught, and named as itself
        with pytest.raises(exercises.ExerciseError, match="Likely cause: " + re.escape(words)):
            checker(wrong)


def test_chapter_07_checkers_accept_a_learner_s_own_right_answers(capsys):
    def step_violation(step_distance, step_length):
        over = (step_distance - step_length).clamp(min=0)
        return (over * over).sum() / over.numel()

    def spread_loss(distance, cap):
        return torch.log1p(torch.exp(cap - distance)).mean()

    assert exercises.check_step_violation(step_violation) is step_violation
    assert exercises.check_spread_loss(spread_loss) is spread_loss
    assert capsys.readouterr().out.count("Correct") == 2


def test_an_unknown_mistake_is_not_given_a_cause():
    def variance_term(z, gamma=1.0, eps=1e-4):
        return torch.relu(gamma - torch.sqrt(z.var(dim=0) + eps)).mean() + 0.1

    with pytest.raises(exercises.ExerciseError, match="but the answer is") as caught:
        exercises.check_variance_term(variance_term)
    assert "Likely cause" not in str(caught.value)


def test_checkers_accept_other_valid_conventions(capsys):
    import torch.nn.functional as F

    def temporal_similarity(z):
        return F.mse_loss(z[:, 1:], z[:, :-1])

    def inverse_dynamics(predict_actions, z, actions):
        return F.mse_loss(predict_actions(z[:, :-1], z[:, 1:]), actions)

    def covariance_term(z):
        cov = torch.cov(z.T)
        return (cov.pow(2).sum() - cov.diagonal().pow(2).sum()) / (z.shape[1] * (z.shape[1] - 1))

    def mppi_update(actions, costs, elites, temperature):  # E[a^2] - mean^2, other indexing
        elite_costs, index = costs.topk(elites, dim=1, largest=False)  # cheapest first
        elite = actions[torch.arange(len(costs))[:, None], index]
        w = torch.softmax(-(elite_costs - elite_costs[:, :1]) / temperature, 1)[:, :, None, None]
        mean = (w * elite).sum(1)
        return mean, ((w * elite.pow(2)).sum(1) - mean.pow(2)).clamp_min(0).sqrt()

    for checker, fn in [(exercises.check_temporal_similarity, temporal_similarity),
                        (exercises.check_inverse_dynamics, inverse_dynamics),
                        (exercises.check_covariance_term, covariance_term),
                        (exercises.check_mppi_update, mppi_update)]:
        assert checker(fn) is fn
    assert capsys.readouterr().out.count("Correct") == 4


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
