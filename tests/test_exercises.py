"""Exercise checkers accept the solutions and other valid answers, reject wrong ones in
words (each exercise's own typical mistakes and the general ones), and offer graded hints;
student versions hold no line of a solution and hand over the course's implementations."""

import functools
import json
import re
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from ebjepa_tutorial import losses, planning
from ebjepa_tutorial.course import exercises
from ebjepa_tutorial.course.exercises import check_wall_collision, common
from ebjepa_tutorial.envs.two_rooms import HIGH, LOW
from tools.student import MARKDOWN_SOLUTION, strip_solutions

NOTEBOOKS = sorted(Path(__file__).resolve().parents[1].glob("notebooks/*.ipynb"))
CHECKERS = {
    "variance_term": exercises.check_variance_term,
    "covariance_term": exercises.check_covariance_term,
    "slab_crossing": exercises.check_slab_crossing,
    "wall_collision": check_wall_collision,
    "temporal_similarity": exercises.check_temporal_similarity,
    "inverse_dynamics": exercises.check_inverse_dynamics,
    "vicreg": exercises.check_vicreg,
    "vicreg_paper_to_ebjepa": exercises.check_vicreg_paper_to_ebjepa,
    "epps_pulley_1d": exercises.check_epps_pulley,
    "parallel_rollout_loss": exercises.check_parallel_rollout_loss,
    "mppi_update": exercises.check_mppi_update,
    "step_violation": exercises.check_step_violation,
    "spread_loss": exercises.check_spread_loss,
}
# the exercises whose output trains something, and the argument it trains
TRAINED = {"variance_term": 0, "covariance_term": 0, "vicreg": 0, "epps_pulley_1d": 0,
           "parallel_rollout_loss": 1, "temporal_similarity": 0, "inverse_dynamics": 1,
           "step_violation": 0, "spread_loss": 0}
BEGIN, END = "### BEGIN SOLUTION", "### END SOLUTION"


def _cells(path):
    return json.loads(path.read_text())["cells"]  # nbformat's import is slow


def _source(cell):
    return "".join(cell["source"])


def _solution_cells():
    """(notebook, index, source) of every code cell that holds a solution region."""
    for path in NOTEBOOKS:
        for index, cell in enumerate(_cells(path)):
            if cell["cell_type"] == "code" and BEGIN in _source(cell):
                yield path, index, _source(cell)


def _solution_functions():
    """Every function defined in a notebook cell that holds a solution region."""
    for path, _, source in _solution_cells():
        namespace = {"torch": torch}
        exec(source, namespace)
        for name in re.findall(r"^def (\w+)\(", source, flags=re.M):
            yield path.name, name, namespace[name]


SOLUTIONS = {name: fn for _, name, fn in _solution_functions()}


@pytest.fixture(autouse=True)
def _fresh_hints():
    common._shown.clear()  # which hint levels a failed check has offered: per test
    yield
    common._shown.clear()


def test_notebooks_have_exercises():
    assert NOTEBOOKS, "no notebooks found"
    assert set(SOLUTIONS) == set(CHECKERS)


@pytest.mark.parametrize("notebook, name, fn", list(_solution_functions()),
                         ids=lambda v: v if isinstance(v, str) else "")
def test_checker_accepts_the_notebook_solution(notebook, name, fn, capsys):
    assert name in CHECKERS, f"{notebook}: exercise {name} has no checker in CHECKERS"
    assert CHECKERS[name](fn) is fn  # the notebook goes on with the learner's own function
    out = capsys.readouterr().out
    assert "Correct" in out and "Note" not in out


# ------------------------------------------------------- each exercise's own mistakes

def _biased_variance(z, gamma=1.0, eps=1e-4):
    return torch.relu(gamma - torch.sqrt(z.var(dim=0, unbiased=False) + eps)).mean()


def _per_dimension_variance(z, gamma=1.0, eps=1e-4):
    return torch.relu(gamma - torch.sqrt(z.var(dim=0) + eps))


def _variance_without_eps(z, gamma=1.0, eps=1e-4):
    return torch.relu(gamma - z.std(dim=0)).mean()


def _covariance_with_diagonal(z):
    centred = z - z.mean(dim=0)
    cov = centred.T @ centred / (len(z) - 1)
    return cov.pow(2).sum() / (z.shape[1] * (z.shape[1] - 1))


def _covariance_not_centred(z):
    cov = z.T @ z / (len(z) - 1)
    return (cov - torch.diag(torch.diagonal(cov))).pow(2).sum() / (z.shape[1] * (z.shape[1] - 1))


def _temporal_similarity_unsquared(z):
    return (z[:, 1:] - z[:, :-1]).norm(dim=-1).mean()


def _inverse_dynamics_swapped_frames(predict_actions, z, actions):
    return (predict_actions(z[:, 1:], z[:, :-1]) - actions).pow(2).mean()


def _inverse_dynamics_detached_next(predict_actions, z, actions):
    return (predict_actions(z[:, :-1], z[:, 1:].detach()) - actions).pow(2).mean()


def _vicreg_regularising_one_view(z_a, z_b, inv_coeff, std_coeff, cov_coeff):
    return (inv_coeff * losses.invariance_term(z_a, z_b)
            + std_coeff * losses.variance_term(z_a) + cov_coeff * losses.covariance_term(z_a))


def _vicreg_adding_views(z_a, z_b, inv_coeff, std_coeff, cov_coeff):
    return (inv_coeff * losses.invariance_term(z_a, z_b)
            + std_coeff * (losses.variance_term(z_a) + losses.variance_term(z_b))
            + cov_coeff * (losses.covariance_term(z_a) + losses.covariance_term(z_b)))


def _vicreg_swapped_weights(z_a, z_b, inv_coeff, std_coeff, cov_coeff):
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


def _parallel(predictor, z, context=2, steps=4, detach_later=False, *, per_frame=False,
              axis=1, reduce=torch.mean, error=F.mse_loss, go_on=False):
    """A learner's parallel unroll, written another way than the course's: one predictor call
    per frame (``per_frame``) or windows by ``unfold``; ``axis``, ``reduce``, ``error`` (a
    step's error) and ``go_on`` (steps 2..K go on from step 1's sequence, detached) make a
    mistake."""
    z = z.transpose(0, 1) if axis == 0 else z
    errors, sequence = [], z
    for k in range(steps):
        source = z.detach() if detach_later and k > 0 else z
        if detach_later and k == 1 and go_on:
            sequence = sequence.detach()
        elif detach_later and k == 1:  # unroll again from the detached latents
            sequence = torch.cat([source[:, :context], _step(predictor, source, context,
                                                             per_frame)], dim=1)
        predictions = _step(predictor, sequence, context, per_frame)
        errors.append(error(predictions, source[:, context:]))
        sequence = torch.cat([source[:, :context], predictions], dim=1)
    return reduce(torch.stack(errors))


def _step(predictor, sequence, context, per_frame):
    """Every frame's prediction from the ``context`` frames before it: (B, T - context, ...)."""
    if per_frame:
        return torch.stack([predictor(sequence[:, t - context:t])
                            for t in range(context, sequence.shape[1])], dim=1)
    windows = sequence.unfold(1, context, 1)[:, :-1]  # (B, T - context, C, H, W, context)
    windows = windows.permute(0, 1, 5, 2, 3, 4)
    return predictor(windows.flatten(0, 1)).unflatten(0, windows.shape[:2])


def _parallel_summed_over_steps(predictor, z, context=2, steps=4, detach_later=False):
    return _parallel(predictor, z, context, steps, detach_later, reduce=torch.sum)


def _parallel_along_the_batch(predictor, z, context=2, steps=4, detach_later=False):
    return _parallel(predictor, z, context, steps, detach_later, axis=0)


def _parallel_unflattened(predictor, z, context=2, steps=4, detach_later=False):
    """Windows stacked as (B, context, T - context, C, H, W) and never flattened: the toy
    'last latent' predictors would pick the right frames, the course's network would crash."""
    errors, sequence, n = [], z, z.shape[1] - context
    for _ in range(steps):
        predictions = predictor(torch.stack([sequence[:, j:j + n] for j in range(context)], 1))
        errors.append(F.mse_loss(predictions, z[:, context:]))
        sequence = torch.cat([z[:, :context], predictions], dim=1)
    return torch.stack(errors).mean()


def _parallel_going_on_detached(predictor, z, context=2, steps=4, detach_later=False):
    return _parallel(predictor, z, context, steps, detach_later, go_on=True)


def _mppi_shifted_by_the_batch(actions, costs, elites, temperature):
    elite_costs, index = costs.topk(elites, dim=1, largest=False)
    elite = actions.gather(1, index[:, :, None, None].expand(-1, -1, *actions.shape[2:]))
    weights = torch.exp(-(elite_costs - elite_costs.min()) / temperature)  # one min for all
    w = (weights / weights.sum(1, keepdim=True))[:, :, None, None]
    mean = (w * elite).sum(1)
    return mean, (w * (elite - mean[:, None]).pow(2)).sum(1).sqrt()


def _autoregressive_given(predictor, z, context=2, steps=4, detach_later=False):
    return losses.rollout.rollout_loss(predictor, z, context, steps, detach_later)


def _parallel_every_step_to_the_encoder(predictor, z, context=2, steps=4, detach_later=False):
    return _parallel(predictor, z, context, steps, False)


def _mppi(actions, costs, elites, temperature, *, scale=None, std=None, shift=True,
          normalise=True):
    """The notebook's MPPI update; ``scale`` replaces ``/ tau``, ``std`` the spread
    (``"variance"`` or ``"uncentred"``), ``shift=False`` leaves out the minimum cost and
    ``normalise=False`` the division of the weights by their sum."""
    elite_costs, index = costs.topk(elites, dim=1, largest=False)
    elite = actions.gather(1, index[:, :, None, None].expand(-1, -1, *actions.shape[2:]))
    if shift:
        elite_costs = elite_costs - elite_costs.min(dim=1, keepdim=True).values
    logits = -elite_costs * temperature if scale == "times" else -elite_costs / temperature
    w = (torch.softmax(logits, dim=1) if normalise else torch.exp(logits))[:, :, None, None]
    mean = (w * elite).sum(dim=1)
    if std == "uncentred":
        return mean, (w * elite.pow(2)).sum(dim=1).sqrt()
    var = (w * (elite - mean[:, None]).pow(2)).sum(dim=1)
    return mean, var if std == "variance" else var.sqrt()


def _mppi_without_shift(actions, costs, elites, temperature):
    elite_costs, index = costs.topk(elites, dim=1, largest=False)
    elite = actions.gather(1, index[:, :, None, None].expand(-1, -1, *actions.shape[2:]))
    weights = torch.exp(-elite_costs / temperature)
    w = (weights / weights.sum(1, keepdim=True))[:, :, None, None]
    mean = (w * elite).sum(1)
    return mean, (w * (elite - mean[:, None]).pow(2)).sum(1).sqrt()


def _mppi_weighting_every_sample(actions, costs, elites, temperature):
    return _mppi(actions, costs, actions.shape[1], temperature)


def _mppi_plain_mean(actions, costs, elites, temperature):
    return _mppi(actions, costs, elites, 1e9)


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


def _slab_crossing_unordered(x0, x1, x_lo, x_hi):
    moving = x1 != x0
    dx = torch.where(moving, x1 - x0, torch.ones_like(x0))
    t_in = torch.where(moving, ((x_lo - x0) / dx).clamp(0, 1), 0.0)
    t_out = torch.where(moving, ((x_hi - x0) / dx).clamp(0, 1),
                        ((x0 > x_lo) & (x0 < x_hi)).float())
    return t_in, t_out


@pytest.mark.parametrize("checker, wrong, message", [
    (exercises.check_epps_pulley, _epps_pulley_unweighted,
     r"weight w\(t\) = exp\(-t\^2/2\) is missing"),
    (exercises.check_epps_pulley, _epps_pulley_real_part_only, "imaginary part is missing"),
    (exercises.check_vicreg, _vicreg_regularising_one_view, "but the answer is .*one view only"),
    (exercises.check_vicreg, _vicreg_adding_views, "added the two views' .* average them"),
    (exercises.check_vicreg, _vicreg_swapped_weights, "swapped the weights"),
    (exercises.check_vicreg_paper_to_ebjepa, lambda inv, std, cov, dim: (inv, std, cov * dim),
     "but the answer is"),
    (exercises.check_vicreg_paper_to_ebjepa, lambda inv, std, cov, dim: cov * dim,
     "must return a tuple of 3"),
    (exercises.check_vicreg_paper_to_ebjepa, lambda inv, std, cov, dim: (1.0, std / inv, cov / inv),
     r"but the answer is .*forgot the factor \(D - 1\)"),
    (exercises.check_vicreg_paper_to_ebjepa, lambda inv, std, cov, dim: (inv, std, cov * (dim - 1)),
     "did not divide by the invariance weight"),
    (exercises.check_vicreg_paper_to_ebjepa,
     lambda inv, std, cov, dim: (1.0, std / inv, cov / (dim - 1) / inv),
     r"divided the covariance weight by \(D - 1\)"),
    (exercises.check_temporal_similarity, _temporal_similarity_unsquared, "unsquared distance"),
    (exercises.check_inverse_dynamics, _inverse_dynamics_swapped_frames,
     "but the answer is .*pair in the wrong order"),
    (exercises.check_inverse_dynamics, _inverse_dynamics_detached_next,
     r"not the right gradient .* gradient reaches z_t but not z_t\+1: you detached the later"),
    (exercises.check_variance_term, _biased_variance, "but the answer is .*biased variance"),
    (exercises.check_variance_term, _variance_without_eps, "eps is missing from the square root"),
    (exercises.check_variance_term, _per_dimension_variance, "a single number.*one hinge per"),
    (exercises.check_covariance_term, _covariance_with_diagonal,
     "but the answer is .*kept the diagonal"),
    (exercises.check_covariance_term, _covariance_not_centred, "did not centre z"),
    (exercises.check_parallel_rollout_loss, _autoregressive_given,
     "this is the autoregressive rollout loss.*the paper's parallel unroll"),
    (exercises.check_parallel_rollout_loss, _parallel_summed_over_steps,
     r"too large by a factor of K = 3 on .*a sum over the K steps where their mean belongs"),
    (exercises.check_parallel_rollout_loss, _parallel_along_the_batch,
     "unrolled along the batch axis: time is axis 1"),
    (exercises.check_parallel_rollout_loss, _parallel_unflattened,
     r"takes windows \(N, context, C, S, S\), got \(4, 2, 7, 5, 4, 4\).*on one axis"),
    (exercises.check_parallel_rollout_loss, _parallel_every_step_to_the_encoder,
     r"not the right gradient with respect to the other latents.*steps 2\.\.K still reach "
     "the encoder"),
    (exercises.check_parallel_rollout_loss,
     lambda predictor, z, context=2, steps=4, detach_later=False: _parallel(
         predictor, z.detach(), context, steps, detach_later),
     r"does not flow to the other latents z\[:, :-1\].*look for a \.detach\(\)"),
    (exercises.check_slab_crossing, _slab_crossing_unordered,
     "your t_in .* but the answer is .*a move to the left reaches x_hi first"),
    (exercises.check_wall_collision, _wall_stay_put, "cancel the whole move"),
    (exercises.check_wall_collision, _wall_without_door_sides, "not the door's sides"),
    (exercises.check_mppi_update, _mppi_without_shift,
     "do not subtract the minimum cost: .* underflows"),
    (exercises.check_mppi_update, _mppi_weighting_every_sample,
     "but the answer is .*weighted all N sampled plans"),
    (exercises.check_mppi_update, _mppi_plain_mean, "but the answer is .*same weight"),
    (exercises.check_mppi_update, functools.partial(_mppi, std="variance"),
     r"your std .* but the answer is .*the weighted variance: take its square root"),
    (exercises.check_mppi_update, functools.partial(_mppi, scale="times"),
     "multiplied by the temperature"),
    (exercises.check_mppi_update, lambda actions, costs, elites, temperature: actions.mean(1),
     r"must return a tuple of 2 \(mean, std\)"),
])
def test_checker_rejects_wrong_answers(checker, wrong, message):
    with pytest.raises(exercises.ExerciseError, match=message):
        checker(wrong)


@pytest.mark.slow  # every known mistake of every checker: seconds
@pytest.mark.parametrize("checker", list(CHECKERS.values()), ids=list(CHECKERS))
def test_checker_names_each_mistake_it_knows(checker):
    assert len(checker.slips) >= 2
    for words, wrong in checker.slips:  # each known slip is caught, and named as itself
        with pytest.raises(exercises.ExerciseError, match="Likely cause: " + re.escape(words)):
            checker(wrong)


def _epps_pulley_rectangles(x, knots=17, t_max=3.0, scale_by_n=True):
    t, real, imag, gaussian, n = _epps_pulley_parts(x, knots, t_max, scale_by_n)
    return 2 * (gaussian * ((real - gaussian) ** 2 + imag**2)).sum() * (t[1] - t[0]) * n


def _epps_pulley_over_both_signs(x, knots=17, t_max=3.0, scale_by_n=True):
    t = torch.linspace(-t_max, t_max, knots)  # the whole line at once, so no doubling
    real, imag = torch.cos(x[:, None] * t).mean(0), torch.sin(x[:, None] * t).mean(0)
    gaussian = torch.exp(-(t**2) / 2)
    area = torch.trapezoid(gaussian * ((real - gaussian) ** 2 + imag**2), t)
    return area * len(x) if scale_by_n else area


def _slab_crossing_unclamped(x0, x1, x_lo, x_hi):
    moving = x1 != x0
    dx = torch.where(moving, x1 - x0, torch.ones_like(x0))
    t_a, t_b = (x_lo - x0) / dx, (x_hi - x0) / dx
    inside = ((x0 > x_lo) & (x0 < x_hi)).to(x0.dtype)
    return (torch.where(moving, torch.minimum(t_a, t_b), 0.0),
            torch.where(moving, torch.maximum(t_a, t_b), inside))


def _slab_crossing_dividing_by_zero(x0, x1, x_lo, x_hi):
    t_a, t_b = (x_lo - x0) / (x1 - x0), (x_hi - x0) / (x1 - x0)
    return torch.minimum(t_a, t_b).clamp(0, 1), torch.maximum(t_a, t_b).clamp(0, 1)


def _epps_pulley_without_its_knots(x, knots=17, t_max=3.0, scale_by_n=True):
    t = torch.linspace(0, t_max, knots)
    phi = torch.exp(1j * x[:, None] * t).mean(0)  # (K,) complex
    gaussian = torch.exp(-t**2 / 2)
    statistic = 2 * torch.trapezoid(gaussian * (phi - gaussian).abs() ** 2)  # dx left out
    return statistic * len(x) if scale_by_n else statistic


def _variance_deciding_with_if(z, gamma=1.0, eps=1e-4):
    std = (z.var(0) + eps).sqrt()  # (D,): an `if` cannot decide for each of them
    if std < gamma:
        return (gamma - std).mean()
    return std.sum() * 0


def _off_diagonal(z, f):
    cov = torch.cov(z.T)
    return (f(cov).sum() - f(cov.diagonal()).sum()) / (z.shape[1] * (z.shape[1] - 1))


def _wall_side_by_target(positions, moves, layouts):
    """The notebook's wall rules with rule 3 read off the target's y1, not y_out."""
    wall_x, door_y = layouts.float().unbind(-1)
    x_lo, x_hi, y_lo, y_hi = wall_x - 2.5, wall_x + 2.5, door_y - 3.5, door_y + 3.5
    (x0, y0), (x1, y1) = positions.unbind(-1), (positions + moves).clamp(LOW, HIGH).unbind(-1)
    t_in, t_out = SOLUTIONS["slab_crossing"](x0, x1, x_lo, x_hi)
    y_in = y0 + t_in * (y1 - y0)
    hits_face = (t_out > t_in) & ((y_in < y_lo) | (y_in > y_hi))
    hits_side = (t_out > t_in) & ~hits_face & ((y1 < y_lo) | (y1 > y_hi))  # y1, not y_out
    x = torch.where(hits_face, torch.where(x0 <= x_lo, x_lo, x_hi), x1)
    return torch.stack([x, torch.where(hits_side, y1.clamp(y_lo, y_hi), y1)], -1)


def _covariance_batch_by_batch(z):
    centred = z - z.mean(dim=0)
    cov = centred @ centred.T / (len(z) - 1)  # (B, B): the transpose on the wrong side
    return (cov - torch.diag(torch.diagonal(cov))).pow(2).sum() / (z.shape[1] * (z.shape[1] - 1))


def _covariance_centred_by_one_mean(z):
    centred = z - z.mean()  # every entry's mean, not each dimension's
    cov = centred.T @ centred / (len(z) - 1)
    return (cov - torch.diag(torch.diagonal(cov))).pow(2).sum() / (z.shape[1] * (z.shape[1] - 1))


def _epps_pulley_knot_mean(x, knots=17, t_max=3.0, scale_by_n=True):
    t, real, imag, gaussian, n = _epps_pulley_parts(x, knots, t_max, scale_by_n)
    return 2 * t_max * (gaussian * ((real - gaussian) ** 2 + imag**2)).mean() * n


@pytest.mark.parametrize("checker, wrong, words", [
    (exercises.check_variance_term,
     lambda z, gamma=1.0, eps=1e-4: torch.relu(gamma - z.std(dim=0) - eps).mean(),
     "you added eps after the square root"),
    (exercises.check_variance_term,
     lambda z, gamma=1.0, eps=1e-4: torch.relu(gamma - torch.sqrt(z.var(0) + 1e-4)).mean(),
     "you ignored the eps argument"),
    (exercises.check_epps_pulley, _epps_pulley_without_its_knots,
     r"torch.trapezoid\(y\) without the knots takes a spacing of 1"),
    (exercises.check_temporal_similarity, lambda z: torch.diff(z).pow(2).mean(),
     r"you took differences along the last axis, D \(torch.diff's default"),
    (exercises.check_temporal_similarity, lambda z: (torch.roll(z, -1, 1) - z).square().mean(),
     "your pairs include the last frame with the first"),
    (exercises.check_mppi_update, _mppi_shifted_by_the_batch,
     "you subtracted the cheapest cost of the whole batch"),
    (exercises.check_parallel_rollout_loss, _parallel_going_on_detached,
     "you detached the predictions between steps"),
    (exercises.check_variance_term,
     lambda z, gamma=1.0, eps=1e-4: torch.relu(gamma - (z.var(dim=0) + eps)).mean(),
     "you used the variance where the standard deviation belongs"),
    (exercises.check_covariance_term, lambda z: _off_diagonal(z, lambda c: c),
     "you summed the covariances themselves; square them first"),
    (exercises.check_covariance_term, lambda z: _off_diagonal(z, torch.abs),
     "you took absolute values; the term squares"),
    (exercises.check_epps_pulley, _epps_pulley_rectangles,
     r"you used a plain sum times the knot spacing \(a rectangle rule\)"),
    (exercises.check_epps_pulley, _epps_pulley_over_both_signs,
     r"you spread the knots over \[-t_max, t_max\]"),
    (exercises.check_parallel_rollout_loss, lambda predictor, z, context=2, steps=4,
     detach_later=False: _parallel(predictor, z, context, steps, detach_later,
                                   error=lambda p, t: F.mse_loss(p, t).sqrt()),
     r"an unsquared distance: the loss is the mean \*squared\* error"),
    (exercises.check_parallel_rollout_loss, lambda predictor, z, context=2, steps=4,
     detach_later=False: _parallel(predictor, z, context, steps, detach_later, error=F.l1_loss),
     "you used the absolute error; the loss is the mean squared error"),
    (exercises.check_slab_crossing, _slab_crossing_unclamped,
     r"you did not clamp the fractions to \[0, 1\]"),
    (exercises.check_slab_crossing, _slab_crossing_dividing_by_zero,
     "a move with no change in x divides by zero"),
    (exercises.check_temporal_similarity, lambda z: F.mse_loss(z[:, 1:], z[:, :-1].detach()),
     r"the gradient reaches z_t\+1 but not z_t: you detached the earlier latent"),
    (exercises.check_temporal_similarity, lambda z: F.mse_loss(z[:, 1:].detach(), z[:, :-1]),
     r"the gradient reaches z_t but not z_t\+1: you detached the later latent"),
    (exercises.check_inverse_dynamics, lambda g, z, a: (g(z[:, :-1], z[:, 1:]) - a).pow(2).sum(),
     "you summed instead of averaging"),
    (exercises.check_inverse_dynamics, lambda g, z, a: F.l1_loss(g(z[:, :-1], z[:, 1:]), a),
     "you used the absolute error; the loss is the mean squared error"),
    (exercises.check_mppi_update, functools.partial(_mppi, normalise=False),
     "your weights do not sum to 1"),
    (exercises.check_mppi_update, functools.partial(_mppi, std="uncentred"),
     "your std does not subtract the mean"),
    (exercises.check_step_violation, lambda d, length: (d - length).pow(2).mean(),
     "a step SHORTER than its action breaks nothing"),
    (exercises.check_step_violation, lambda d, length: (length - d).clamp(min=0).pow(2).mean(),
     "the excess is step_distance - step_length"),
    (exercises.check_spread_loss, lambda d, cap: torch.log1p(torch.exp(d - cap)).mean(),
     "the sign is flipped"),
    (exercises.check_spread_loss, lambda d, cap: (cap - d).clamp(min=0).mean(),
     "use the smooth hinge softplus, not relu"),
    (exercises.check_spread_loss, lambda d, cap: torch.log1p(torch.exp(-d)).mean(),
     "the cap is missing"),
    (exercises.check_spread_loss, lambda d, cap: F.softplus(cap - d).sum(),
     "average over the pairs, do not sum"),
    (exercises.check_covariance_term, _covariance_batch_by_batch,
     "you multiplied centred by its transpose on the right, which gives a B x B matrix"),
    (exercises.check_covariance_term, lambda z: (torch.corrcoef(z.T).fill_diagonal_(0) ** 2).sum()
     / (z.shape[1] * (z.shape[1] - 1)), "you squared correlations"),
    (exercises.check_covariance_term, _covariance_centred_by_one_mean,
     "you subtracted one mean of all the entries of z"),
    (exercises.check_epps_pulley, _epps_pulley_knot_mean,
     "you averaged the integrand over the knots and multiplied by the range"),
    (check_wall_collision, _wall_side_by_target, "you decided rule 3 by the target's y1"),
])
def test_a_learner_s_own_slip_is_named_in_its_words(checker, wrong, words):
    """A slip the checker knows, written as a learner would (not the checker's own slip
    function), is named in that slip's words: the test above pairs each slip function with
    the words it is filed under, so it cannot notice two slips' words swapped."""
    with pytest.raises(exercises.ExerciseError, match="Likely cause: " + words):
        checker(wrong)


# ------------------------------------------- an output that trains must keep its gradient

def _detached(right, index):
    @functools.wraps(right)
    def wrong(*args, **kwargs):
        args = list(args)
        args[index] = args[index].detach()
        return right(*args, **kwargs)
    return wrong


def _through_numpy(right, index):
    @functools.wraps(right)
    def wrong(*args, **kwargs):
        args = list(args)
        args[index] = torch.from_numpy(np.array(args[index].detach().numpy()))
        return right(*args, **kwargs)
    return wrong


def _under_no_grad(right):
    @functools.wraps(right)
    def wrong(*args, **kwargs):
        with torch.no_grad():
            return right(*args, **kwargs)
    return wrong


def _sign_flipped(right):
    @functools.wraps(right)
    def wrong(*args, **kwargs):
        return -right(*args, **kwargs)
    return wrong


LABELS = {  # how a message names the input that stops receiving a gradient
    "vicreg": "the first view z_a", "epps_pulley_1d": "the sample x",
    "parallel_rollout_loss":
        r"the (predictor's weights|other latents z\[:, :-1\])",
    "temporal_similarity": "the latents z", "inverse_dynamics": "the latents z",
    "step_violation": "the step distances", "spread_loss": "the distances"}


@pytest.mark.parametrize("name", list(TRAINED))
@pytest.mark.parametrize("cut", [
    lambda fn, index: _detached(fn, index), lambda fn, index: _through_numpy(fn, index),
    lambda fn, index: _under_no_grad(fn),
], ids=["detach", "numpy", "no_grad"])
def test_an_answer_that_cuts_the_gradient_is_named(name, cut):
    label = LABELS.get(name, "z")
    wrong = cut(SOLUTIONS[name], TRAINED[name])
    with pytest.raises(exercises.ExerciseError,
                       match=rf"right value on .*, but the gradient does not flow to {label}, so "
                             r"training could not change it .*\.detach\(\), \.item\(\), a "
                             r"detour through numpy, or torch\.no_grad\(\)"):
        CHECKERS[name](wrong)


@pytest.mark.parametrize("name", list(TRAINED))
def test_a_sign_flipped_answer_is_named(name):
    with pytest.raises(exercises.ExerciseError,
                       match=r"has the wrong sign on .*: it is minus the answer\. Look "
                             r".*difference taken the wrong way round.*Yours: -?[\d.]"):
        CHECKERS[name](_sign_flipped(SOLUTIONS[name]))


def test_the_general_causes_use_the_cases_own_tolerance():
    # a case whose answer float32 can only give to 1e-2: a sign flip off by 5e-3 is still a
    # sign flip, and the checker must say so rather than print only the numbers
    from ebjepa_tutorial.course.exercises.common import Case, Exercise

    def course(x):
        return 100 * x.sum()

    check = Exercise("variance_term", course, mistakes={},
                     cases=lambda: [Case("a loose case", (torch.full((4,), 0.025),), atol=1e-2)])
    with pytest.raises(exercises.ExerciseError, match=r"has the wrong sign on a loose case"):
        check(lambda x: -course(x) + 5e-3)


def test_a_numpy_implementation_is_named():
    def variance_term(z, gamma=1.0, eps=1e-4):
        std = np.sqrt(np.var(z.detach().numpy(), axis=0, ddof=1) + eps)
        return torch.tensor(np.maximum(0.0, gamma - std).mean())

    def epps_pulley_1d(x, knots=17, t_max=3.0, scale_by_n=True):
        t = np.linspace(0.0, t_max, knots)
        xt = np.asarray(x)[:, None] * t  # np.asarray reads a tensor through numpy
        gap = (np.cos(xt).mean(0) - np.exp(-t**2 / 2)) ** 2 + np.sin(xt).mean(0) ** 2
        statistic = 2 * np.trapezoid(np.exp(-t**2 / 2) * gap, t)
        return torch.tensor(statistic * len(x) if scale_by_n else statistic)

    for checker, fn, label in [(exercises.check_variance_term, variance_term, "z"),
                               (exercises.check_epps_pulley, epps_pulley_1d, "the sample x")]:
        with pytest.raises(exercises.ExerciseError,
                           match=rf"does not flow to {label}, so .*numpy"):
            checker(fn)


# ------------------------------------------------- general mistakes, each on two exercises

def _temporal_over_t(z):
    return (z[:, 1:] - z[:, :-1]).pow(2).sum() / z.numel()


def _epps_pulley_undoubled(x, knots=17, t_max=3.0, scale_by_n=True):
    t, real, imag, gaussian, n = _epps_pulley_parts(x, knots, t_max, scale_by_n)
    return torch.trapezoid(gaussian * ((real - gaussian) ** 2 + imag**2), t) * n


@pytest.mark.parametrize("checker, wrong, message", [
    # a factor off
    (exercises.check_covariance_term,
     lambda z: losses.covariance_term(z) * (z.shape[1] - 1),
     r"is too large by a factor of D - 1 = 7 on .*the VICReg paper divides the sum by D"),
    (exercises.check_covariance_term,
     lambda z: losses.covariance_term(z) * ((len(z) - 1) / len(z)) ** 2,
     r"is too small by a factor of \(B/\(B - 1\)\)² = 1.066.*divides by B - 1, not B"),
    (exercises.check_variance_term,
     lambda z, gamma=1.0, eps=1e-4: torch.relu(gamma - (z.var(0) + eps).sqrt()).sum(),
     r"is too large by a factor of D = 8 on .*averaged over the D dimensions, not summed"),
    (exercises.check_temporal_similarity,
     lambda z: (z[:, 1:] - z[:, :-1]).pow(2).sum(-1).mean(),
     r"is too large by a factor of D = 8 on .*averaged over the D dimensions too"),
    (exercises.check_temporal_similarity, _temporal_over_t,
     r"is too small by a factor of T/\(T - 1\) = 1.062.*T latents make T - 1 changes"),
    (exercises.check_inverse_dynamics,
     lambda g, z, a: (g(z[:, :-1], z[:, 1:]) - a).pow(2).sum(-1).mean(),
     r"is too large by a factor of A = 4 on .*averaged over the A action dimensions"),
    (exercises.check_epps_pulley,
     lambda x, knots=17, t_max=3.0, scale_by_n=True: losses.sigreg.epps_pulley(
         x, knots=knots, t_max=t_max, scale_by_n=False),
     r"is too small by a factor of N = 256 on .*N times the integral"),
    (exercises.check_epps_pulley, _epps_pulley_undoubled,
     r"is too small by a factor of 2 on .*integrate over \[0, t_max\], then double once"),
    (exercises.check_covariance_term,  # `/ dim * (dim - 1)`: D(D - 1) without its parentheses
     lambda z: torch.cov(z.T).fill_diagonal_(0).pow(2).sum() / z.shape[1] * (z.shape[1] - 1),
     r"is too large by a factor of \(D - 1\)² = 49 on .*put D\(D - 1\) in parentheses"),
    (exercises.check_covariance_term,
     lambda z: torch.cov(z.T).fill_diagonal_(0).pow(2).sum() / z.shape[1] ** 2,
     r"is too small by a factor of D/\(D - 1\) = 1.143 on .*D\(D - 1\) off-diagonal entries, "
     r"not D\^2"),
    # an input changed in place
    (exercises.check_covariance_term,
     lambda z: (z.sub_(z.mean(0)).T @ z / (len(z) - 1)).fill_diagonal_(0).pow(2).sum()
     / (z.shape[1] * (z.shape[1] - 1)),
     r"changed its input z in place on a random batch.*-=, \+= or \*="),
    (exercises.check_variance_term,
     lambda z, gamma=1.0, eps=1e-4: torch.relu(gamma - (z.sub_(z.mean(0)).var(0) + eps).sqrt())
     .mean(), r"changed its input z in place"),
    (exercises.check_mppi_update,
     lambda actions, costs, elites, temperature: _mppi(
         actions, costs.sub_(costs.min(1, keepdim=True).values), elites, temperature),
     r"changed its input costs in place"),
    # the wrong axis
    (exercises.check_variance_term,
     lambda z, gamma=1.0, eps=1e-4: torch.relu(gamma - (z.var(1) + eps).sqrt()).mean(),
     r"worked along the wrong axis: .*the batch and the dimension axes of z exchanged"),
    (exercises.check_temporal_similarity, lambda z: (z[1:] - z[:-1]).pow(2).mean(),
     r"worked along the wrong axis: .*the batch and the time axes.*neighbours along axis 1"),
    (exercises.check_covariance_term,
     lambda z: (torch.cov(z) - torch.diag(torch.cov(z).diagonal())).pow(2).sum()
     / (len(z) * (len(z) - 1)),
     r"worked along the wrong axis: .*torch.cov, for one, treats each row as a variable"),
    # a Python float, a numpy number or a tuple where a tensor belongs
    (exercises.check_variance_term,
     lambda z, gamma=1.0, eps=1e-4: losses.variance_term(z, gamma, eps).item(),
     r"returned a Python float on .*carries no gradient.*\.item\(\)"),
    (exercises.check_temporal_similarity,
     lambda z: np.float64((z[:, 1:] - z[:, :-1]).pow(2).mean()),
     r"returned a numpy float64 on .*numpy carries no gradient"),
    (exercises.check_vicreg,
     lambda z_a, z_b, *coeffs: losses.vicreg_loss(z_a, z_b, *coeffs),
     r"returned a tuple of 2 on .*a loss and its parts"),
    (exercises.check_covariance_term, lambda z: float(losses.covariance_term(z)),
     r"returned a Python float"),
    # a plan the course feeds back must keep its dtype (a loss may compute in float64)
    (exercises.check_mppi_update,
     lambda a, c, q, tau: tuple(x.double() for x in planning.mppi_update(a, c, q, tau)),
     r"returned mean as torch.float64 on .*where the course returns torch.float32.*numpy"),
    # a crash names the learner's line; an `if` on a tensor gets its remedy
    (exercises.check_variance_term, _variance_deciding_with_if,
     r"raised RuntimeError: Boolean value .* \(line \d+ of your code: if std < gamma:\)"
     r"\. An `if` .* torch\.where"),
])
def test_general_mistakes_are_named_in_words(checker, wrong, message):
    with pytest.raises(exercises.ExerciseError, match=message):
        checker(wrong)


def test_a_move_that_never_enters_may_give_any_pair_of_equal_fractions(capsys):
    """The text asks only that t_in equal t_out when the move never enters the slab: (1, 1)
    for a move that stays outside is as right as the course's (0, 0) or clamped values."""
    def slab_crossing(x0, x1, x_lo, x_hi):
        moving = x1 != x0
        dx = torch.where(moving, x1 - x0, torch.ones_like(x0))
        t_a, t_b = (x_lo - x0) / dx, (x_hi - x0) / dx
        t_in, t_out = torch.minimum(t_a, t_b).clamp(0, 1), torch.maximum(t_a, t_b).clamp(0, 1)
        never = moving & (t_in == t_out) | ~moving & ((x0 <= x_lo) | (x0 >= x_hi))
        t_in = torch.where(never, 1.0, torch.where(moving, t_in, 0.0))
        return t_in, torch.where(never | ~moving, 1.0, t_out)

    assert exercises.check_slab_crossing(slab_crossing) is slab_crossing
    assert "Correct" in capsys.readouterr().out


def _wall_with_a_strict_doorway(positions, moves, layouts):
    """The three rules, with the doorway open only strictly between its edges."""
    from ebjepa_tutorial.envs.two_rooms import wall_bounds

    x_lo, x_hi, y_lo, y_hi = wall_bounds(layouts)
    (x0, y0), (x1, y1) = positions.unbind(-1), (positions + moves).clamp(LOW, HIGH).unbind(-1)
    t_in, t_out = exercises.two_rooms._crossing_slip()(x0, x1, x_lo, x_hi)
    y_in, y_out = y0 + t_in * (y1 - y0), y0 + t_out * (y1 - y0)
    enters, door = t_out > t_in, lambda y: (y > y_lo) & (y < y_hi)  # should be >= and <=
    x = torch.where(enters & ~door(y_in), torch.where(x0 <= x_lo, x_lo, x_hi), x1)
    y = torch.where(enters & door(y_in) & ~door(y_out), y1.clamp(y_lo, y_hi), y1)
    return torch.stack([x, y], -1)


def test_a_doorway_without_its_edges_is_refused_where_a_door_side_stop_leaves_the_dot():
    """A stop at the door's side leaves the dot exactly on the door's edge; a doorway open only
    strictly between its edges then throws the dot to the wall's face on its next move."""
    with pytest.raises(exercises.ExerciseError,
                       match=r"a move along the door's edge, from inside the wall"):
        check_wall_collision(_wall_with_a_strict_doorway)


def test_a_wrong_gradient_is_put_down_only_to_a_slip_with_the_right_value():
    """Detaching the sine's part leaves the value right; the slip "the imaginary part is
    missing" has the same gradient but another value, so it is not named."""
    def epps_pulley_1d(x, knots=17, t_max=3.0, scale_by_n=True):
        t = torch.linspace(0.0, t_max, knots)
        gaussian = torch.exp(-t**2 / 2)
        gap = ((torch.cos(x[:, None] * t).mean(0) - gaussian) ** 2
               + torch.sin(x[:, None] * t).mean(0).detach() ** 2)
        statistic = 2 * torch.trapezoid(gaussian * gap, t)
        return statistic * len(x) if scale_by_n else statistic

    with pytest.raises(exercises.ExerciseError, match="not the right gradient") as error:
        exercises.check_epps_pulley(epps_pulley_1d)
    assert "imaginary" not in str(error.value)


def test_a_slips_own_warnings_stay_inside_the_check():
    """A std clamped to 0.05 is wrong; finding its cause runs the Q = 1 slips, whose std of one
    elite warns (degrees of freedom <= 0): the learner must not see that warning."""
    def mppi_update(actions, costs, elites, temperature):
        mean, std = _mppi(actions, costs, elites, temperature)
        return mean, std.clamp_min(0.05)

    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        with pytest.raises(exercises.ExerciseError, match="your std"):
            exercises.check_mppi_update(mppi_update)
    assert [str(w.message) for w in shown] == []


def _rollout_overwriting_z(predictor, z, context=2, steps=4, detach_later=False):
    """The course's unroll, but each step's sequence is z itself, overwritten in place."""
    errors, sequence = [], z
    for _ in range(steps):
        predictions = _step(predictor, sequence, context, per_frame=False)
        errors.append(F.mse_loss(predictions, z[:, context:]))
        sequence = z  # the slip: the caller's z, not a new tensor
        sequence[:, context:] = predictions
    return torch.stack(errors).mean()


def _wall_without_enters(positions, moves, layouts):
    """The notebook's wall rules with ``enters &`` left out of the face rule."""
    wall_x, door_y = layouts.float().unbind(-1)
    x_lo, x_hi, y_lo, y_hi = wall_x - 2.5, wall_x + 2.5, door_y - 3.5, door_y + 3.5
    x0, y0 = positions.unbind(-1)
    x1, y1 = (positions + moves).clamp(LOW, HIGH).unbind(-1)
    t_in, t_out = SOLUTIONS["slab_crossing"](x0, x1, x_lo, x_hi)
    y_in = y0 + t_in * (y1 - y0)
    hits_face = (y_in < y_lo) | (y_in > y_hi)
    return torch.stack([torch.where(hits_face, torch.where(x0 <= x_lo, x_lo, x_hi), x1), y1], -1)


def _wall_stopping_on_its_centre(positions, moves, layouts):
    new = check_wall_collision.reference(positions, moves, layouts)
    stopped = new[:, 0] != (positions + moves).clamp(LOW, HIGH)[:, 0]
    return torch.stack([torch.where(stopped, layouts[:, 0].float(), new[:, 0]), new[:, 1]], -1)


@pytest.mark.parametrize("checker, wrong, says, not_says", [
    # a wrong shape in a tuple answer: its values, joined, cannot tell one slip from another
    (exercises.check_mppi_update, lambda *args: (_mppi(*args)[0][:, None], _mppi(*args)[1]),
     r"returned shape \(\d+, 1, \d+, 2\) .* for your mean", "Likely cause"),
    # an input overwritten in place inside the loss: the step would project the predictions
    (exercises.check_parallel_rollout_loss, _rollout_overwriting_z,
     r"changed its input z in place", "Correct"),
    # a move that never reaches the wall stopped at the face: no open door to speak of
    (check_wall_collision, _wall_without_enters, r"gave \(.*\) but the reference gives",
     "the door is open"),
    (check_wall_collision, _wall_stopping_on_its_centre, r"left the dot centre inside the wall",
     "pass through"),
    # a squared error summed over each latent's elements, averaged over frames and batch
    (exercises.check_parallel_rollout_loss, lambda predictor, z, context=2, steps=4,
     detach_later=False: _parallel(predictor, z, context, steps, detach_later) * z[0, 0].numel(),
     r"summed the squared error over each latent's elements", "Correct"),
    # half the mean squared error: a factor 2, not a sum over 2-d actions
    (exercises.check_inverse_dynamics, lambda g, z, a: F.mse_loss(g(z[:, :-1], z[:, 1:]), a) / 2,
     r"too small by a factor of 2 ", "A = 2"),
    # the label is named once, the numbers after it plainly
    (exercises.check_vicreg_paper_to_ebjepa,
     lambda inv, std, cov, dim: (1.0, std / inv, 2 * cov * (dim - 1) / inv),
     r"\(your covariance weight\)\. .* Yours: [\d.]+, but", "Yours: your"),
    (exercises.check_vicreg_paper_to_ebjepa, lambda inv, std, cov, dim: None,
     r"returned None on .*did you forget the return statement", "NoneType"),
])
def test_a_typical_mistake_is_described_as_it_is(checker, wrong, says, not_says):
    with pytest.raises(exercises.ExerciseError) as caught:
        checker(wrong)
    assert re.search(says, str(caught.value)), str(caught.value)
    assert not_says not in str(caught.value)


def _rules_on_the_raw_target(positions, moves, layouts, clamp_at_the_end):
    """The notebook's scaffold, its first step left out: the target is not clamped first."""
    from ebjepa_tutorial.envs.two_rooms import HIGH, LOW

    wall_x, door_y = layouts.float().unbind(-1)
    x_lo, x_hi, y_lo, y_hi = wall_x - 2.5, wall_x + 2.5, door_y - 3.5, door_y + 3.5
    x0, y0 = positions.unbind(-1)
    x1, y1 = (positions + moves).unbind(-1)
    t_in, t_out = SOLUTIONS["slab_crossing"](x0, x1, x_lo, x_hi)
    y_in, y_out = y0 + t_in * (y1 - y0), y0 + t_out * (y1 - y0)
    face = (t_out > t_in) & ((y_in < y_lo) | (y_in > y_hi))
    side = (t_out > t_in) & ~face & ((y_out < y_lo) | (y_out > y_hi))
    x = torch.where(face, torch.where(x0 <= x_lo, x_lo, x_hi), x1)
    new = torch.stack([x, torch.where(side, y1.clamp(y_lo, y_hi), y1)], dim=-1)
    return new.clamp(LOW, HIGH) if clamp_at_the_end else new


@pytest.mark.parametrize("clamp_at_the_end", [True, False], ids=["clamped last", "never"])
def test_an_unclamped_target_is_named_not_an_open_door(clamp_at_the_end):
    def wall_collision(positions, moves, layouts):
        return _rules_on_the_raw_target(positions, moves, layouts, clamp_at_the_end)

    with pytest.raises(exercises.ExerciseError) as caught:
        check_wall_collision(wall_collision)
    assert "the target was not clamped to the arena first. Rule 1" in str(caught.value)
    assert "the door is open there" not in str(caught.value)


# ------------------------- each case tries what the others cannot: a right answer on one is not

def test_a_covariance_term_that_types_in_the_notebook_s_sizes_is_refused():
    """Notebook 00 embeds in D = 8 dimensions: a term that divides by 8 * 7 = 56 (or by a batch
    of 32 less one) agrees on a (32, 8) batch, so the check must also try other sizes."""
    def typed_d(z):
        return torch.cov(z.T).fill_diagonal_(0).pow(2).sum() / 56

    def typed_b(z):
        centred = z - z.mean(0)
        cov = (centred.T @ centred / 31).fill_diagonal_(0)
        return cov.pow(2).sum() / (z.shape[1] * (z.shape[1] - 1))

    for wrong in (typed_d, typed_b):
        with pytest.raises(exercises.ExerciseError, match="but the answer is"):
            exercises.check_covariance_term(wrong)


def _epps_pulley_typed_knots(x, knots=17, t_max=3.0, scale_by_n=True):
    t, real, imag, gaussian, n = _epps_pulley_parts(x, 17, 3.0, scale_by_n)  # the defaults
    return 2 * torch.trapezoid(gaussian * ((real - gaussian) ** 2 + imag**2), t) * n


@pytest.mark.parametrize("wrong, message", [
    (_epps_pulley_typed_knots, r"on knots=5 and t_max=2.0"),
    (lambda x, knots=17, t_max=3.0, scale_by_n=True: losses.sigreg.epps_pulley(x, knots, t_max),
     r"too large by a factor of N = 100 on a Gaussian sample of 100 numbers with "
     r"scale_by_n=False"),
], ids=["knots and t_max typed in", "scale_by_n ignored"])
def test_the_epps_pulley_check_holds_the_statistic_to_its_arguments(wrong, message):
    """The statistic's knots, t_max and scale_by_n are the learner's to honour: one that always
    integrates over 17 knots of [0, 3], or always multiplies by N, is right at the defaults
    only, and the cases that set those arguments refuse it."""
    with pytest.raises(exercises.ExerciseError, match=message):
        exercises.check_epps_pulley(wrong)


def test_a_spread_loss_that_types_in_its_cap_is_refused():
    """The text's cap C = 150 px is 15 in the head's units; a spread that types 15 in and
    ignores its cap argument agrees on the cases of cap 15 only."""
    with pytest.raises(exercises.ExerciseError, match="but the answer is .* on the same, cap 5"):
        exercises.check_spread_loss(lambda distance, cap: F.softplus(15.0 - distance).mean())


def test_a_slab_crossing_that_never_counts_a_still_dot_inside_is_refused():
    """A move with no change in x spends all of it inside the slab when the dot stands inside
    (t_out = 1): answering 0 for every still move is right only for dots outside, and the
    check has still dots on both sides."""
    def slab_crossing(x0, x1, x_lo, x_hi):
        still = x1 == x0
        dx = torch.where(still, torch.ones_like(x0), x1 - x0)
        t_a, t_b = (x_lo - x0) / dx, (x_hi - x0) / dx
        return (torch.where(still, 0.0, torch.minimum(t_a, t_b).clamp(0, 1)),
                torch.where(still, 0.0, torch.maximum(t_a, t_b).clamp(0, 1)))

    with pytest.raises(exercises.ExerciseError,
                       match=r"your t_out .* but the answer is 1 .*on moves with no change in x"):
        exercises.check_slab_crossing(slab_crossing)


def test_a_wall_rule_that_stops_short_of_the_face_is_refused():
    """The dot stops on the wall's face, not a safety margin before it: 0.01 px short is a
    wrong position the check's tolerance (1e-4 px) must not absorb."""
    def wall_collision(positions, moves, layouts):
        new = check_wall_collision.reference(positions, moves, layouts)
        stopped = ~torch.isclose(new[:, 0], (positions + moves).clamp(LOW, HIGH)[:, 0])
        back = torch.where(new[:, 0] < layouts[:, 0].float(), -0.01, 0.01)
        return torch.stack([new[:, 0] + torch.where(stopped, back, 0.0), new[:, 1]], -1)

    with pytest.raises(exercises.ExerciseError, match=r"gave \(.*\) but the reference gives"):
        check_wall_collision(wall_collision)


def test_vicreg_with_a_stop_gradient_on_the_second_view_is_refused():
    """VICReg trains both branches: an invariance term that stops the gradient at z_b (as
    BYOL and SimSiam do) has the right value, and only the gradient with respect to the
    second view tells it apart."""
    def vicreg(z_a, z_b, inv_coeff, std_coeff, cov_coeff):
        variance = (losses.variance_term(z_a) + losses.variance_term(z_b)) / 2
        covariance = (losses.covariance_term(z_a) + losses.covariance_term(z_b)) / 2
        return (inv_coeff * F.mse_loss(z_a, z_b.detach()) + std_coeff * variance
                + cov_coeff * covariance)

    with pytest.raises(exercises.ExerciseError,
                       match="not the right gradient with respect to the second view z_b"):
        exercises.check_vicreg(vicreg)


def test_an_unroll_whose_later_steps_train_nothing_is_refused():
    """detach_later cuts the encoder off from steps 2..K, not the predictor: running those
    steps under torch.no_grad() gives the right value and the right gradient for the latents,
    and only the gradient with respect to the predictor's weights shows the mistake."""
    def parallel_rollout_loss(predictor, z, context=2, steps=4, detach_later=False):
        if not detach_later:
            return _parallel(predictor, z, context, steps)
        first = _parallel(predictor, z, context, 1)
        with torch.no_grad():  # steps 2..K: counted, but (wrongly) training nothing
            later = _parallel(predictor, z, context, steps, True) * steps - first
        return (first + later) / steps

    with pytest.raises(exercises.ExerciseError,
                       match="not the right gradient with respect to the predictor's weights"):
        exercises.check_parallel_rollout_loss(parallel_rollout_loss)


# ------------------------------------------------------------- valid answers are accepted

def test_checkers_accept_other_valid_conventions(capsys):
    def temporal_similarity(z):
        return F.mse_loss(z[:, 1:], z[:, :-1])

    def inverse_dynamics(predict_actions, z, actions):
        return F.mse_loss(predict_actions(z[:, :-1], z[:, 1:]), actions)

    def mppi_update(actions, costs, elites, temperature):  # E[a^2] - mean^2, other indexing
        elite_costs, index = costs.topk(elites, dim=1, largest=False)  # cheapest first
        elite = actions[torch.arange(len(costs))[:, None], index]
        w = torch.softmax(-(elite_costs - elite_costs[:, :1]) / temperature, 1)[:, :, None, None]
        mean = (w * elite).sum(1)
        return mean, ((w * elite.pow(2)).sum(1) - mean.pow(2)).clamp_min(0).sqrt()

    def slab_crossing(x0, x1, x_lo, x_hi):  # the times of the two faces, sorted
        dx = x1 - x0
        faces = torch.stack([(x_lo - x0) / dx, (x_hi - x0) / dx]).sort(dim=0).values.clamp(0, 1)
        inside = ((x0 > x_lo) & (x0 < x_hi)).to(x0.dtype)
        return (torch.where(dx == 0, 0.0, faces[0]).to(x0.dtype),
                torch.where(dx == 0, inside, faces[1]))

    for checker, fn in [(exercises.check_temporal_similarity, temporal_similarity),
                        (exercises.check_inverse_dynamics, inverse_dynamics),
                        (exercises.check_mppi_update, mppi_update),
                        (exercises.check_slab_crossing, slab_crossing)]:
        assert checker(fn) is fn
    assert capsys.readouterr().out.count("Correct") == 4


@pytest.mark.parametrize("per_frame", [False, True], ids=["unfold", "one call per frame"])
def test_the_video_checker_accepts_other_ways_to_unroll(per_frame, capsys):
    def parallel_rollout_loss(predictor, z, context=2, steps=4, detach_later=False):
        return _parallel(predictor, z, context, steps, detach_later, per_frame=per_frame)

    assert exercises.check_parallel_rollout_loss(parallel_rollout_loss) is parallel_rollout_loss
    out = capsys.readouterr().out
    assert "Correct" in out and "Note" not in out


@pytest.mark.parametrize("covariance_term", [
    lambda z: (torch.cov(z.T).pow(2).sum() - torch.cov(z.T).diagonal().pow(2).sum())
    / (z.shape[1] * (z.shape[1] - 1)),
    lambda z: torch.cov(z.T).fill_diagonal_(0).pow(2).sum() / (z.shape[1] * (z.shape[1] - 1)),
    lambda z: ((torch.einsum("bi,bj->ij", z, z) - len(z) * torch.outer(z.mean(0), z.mean(0)))
               / (len(z) - 1)).triu(1).pow(2).sum() * 2 / (z.shape[1] * (z.shape[1] - 1)),
], ids=["torch.cov", "fill_diagonal_", "einsum"])
def test_equivalent_covariance_formulas_are_accepted(covariance_term, capsys):
    assert exercises.check_covariance_term(covariance_term) is covariance_term
    assert "Correct" in capsys.readouterr().out


def test_answers_that_compute_in_float64_are_accepted(capsys):
    def variance_term(z, gamma=1.0, eps=1e-4):
        return torch.relu(gamma - torch.sqrt(z.double().var(dim=0) + eps)).mean()

    def epps_pulley_1d(x, knots=17, t_max=3.0, scale_by_n=True):
        x = x.double()
        t = torch.linspace(0.0, t_max, knots, dtype=torch.float64)
        gaussian = torch.exp(-t**2 / 2)
        gap = ((torch.cos(x[:, None] * t).mean(0) - gaussian) ** 2
               + torch.sin(x[:, None] * t).mean(0) ** 2)
        statistic = 2 * torch.trapezoid(gaussian * gap, t)
        return statistic * len(x) if scale_by_n else statistic

    assert exercises.check_variance_term(variance_term) is variance_term
    assert exercises.check_epps_pulley(epps_pulley_1d) is epps_pulley_1d
    assert capsys.readouterr().out.count("Correct") == 2


def test_softmax_without_the_minimum_is_accepted_and_told_about_float32(capsys):
    def mppi_update(actions, costs, elites, temperature):
        return _mppi(actions, costs, elites, temperature, shift=False)

    assert exercises.check_mppi_update(mppi_update) is mppi_update
    out = capsys.readouterr().out
    assert "Correct" in out
    assert re.search(r"costs near 10,000 your mean and std differ .* by up to \d\.\de-0\d, "
                     r"which float32 explains.*about three decimals", out, re.S), out


def test_the_float32_note_reports_the_largest_gap_over_the_parts(capsys):
    def mppi_update(actions, costs, elites, temperature):  # the mean off by more than the std
        mean, std = planning.mppi_update(actions, costs, elites, temperature)
        near = costs.min() > 1000  # only the case of costs near 10,000 takes a looser tolerance
        return (mean + 4e-5, std + 2e-5) if near else (mean, std)

    assert exercises.check_mppi_update(mppi_update) is mppi_update
    assert "by up to 4.0e-05" in capsys.readouterr().out  # the mean's gap, not the last part's


def test_chapter_07_checkers_accept_a_learner_s_own_right_answers(capsys):
    def step_violation(step_distance, step_length):
        over = (step_distance - step_length).clamp(min=0)
        return (over * over).sum() / over.numel()

    def spread_loss(distance, cap):
        return torch.log1p(torch.exp(cap - distance)).mean()

    assert exercises.check_step_violation(step_violation) is step_violation
    assert exercises.check_spread_loss(spread_loss) is spread_loss
    assert capsys.readouterr().out.count("Correct") == 2


def test_whose_tells_the_learner_s_function_from_the_course_s(capsys):
    def variance_term(z, gamma=1.0, eps=1e-4):
        return losses.variance_term(z, gamma, eps)

    assert exercises.check_variance_term(variance_term) is variance_term
    assert "Correct" in capsys.readouterr().out
    assert exercises.whose(variance_term) == "your"
    assert exercises.whose(exercises.check_variance_term.reference) == "the course's"


def test_an_unknown_mistake_is_not_given_a_cause():
    def variance_term(z, gamma=1.0, eps=1e-4):
        return torch.relu(gamma - torch.sqrt(z.var(dim=0) + eps)).mean() + 0.1

    with pytest.raises(exercises.ExerciseError, match="but the answer is") as caught:
        exercises.check_variance_term(variance_term)
    assert "Likely cause" not in str(caught.value)


@pytest.mark.parametrize("checker", list(CHECKERS.values()), ids=list(CHECKERS))
def test_an_unfinished_exercise_hands_over_the_course_implementation(checker, capsys):
    def stub(*args, **kwargs):
        raise NotImplementedError("Exercise: write it")

    assert checker(stub) is checker.reference  # so "Run All" reaches the end of the chapter
    out = capsys.readouterr().out
    assert "not implemented yet" in out and "gets the course's implementation" in out
    assert f"exercises.hint({checker.exercise!r})" in out


def test_a_wrong_answer_is_reported_without_the_checkers_insides():
    def covariance_term(z):
        return z.var(dim=0).sum()

    with pytest.raises(exercises.ExerciseError) as caught:
        exercises.check_covariance_term(covariance_term)
    frames = [frame.name for frame in caught.traceback]
    assert frames[1:] == ["__call__"]  # the learner's cell, then the check: none of its insides


def test_checker_reports_a_crash_in_plain_words():
    def covariance_term(z):
        return z @ z  # wrong shapes for a non-square batch

    with pytest.raises(exercises.ExerciseError, match="raised RuntimeError"):
        exercises.check_covariance_term(covariance_term)


# -------------------------------------------------------------------------------- hints

def test_hints_come_one_level_at_a_time(capsys):
    for level in (1, 2, 3, 3):
        exercises.hint("mppi_update")
        assert f"Hint {level} of 3 for mppi_update" in capsys.readouterr().out
    exercises.hint(SOLUTIONS["covariance_term"], level=2)  # the function itself will do
    assert "Hint 2 of 3 for covariance_term, the formula" in capsys.readouterr().out
    exercises.hint("mppi")
    assert "no exercise called 'mppi'" in capsys.readouterr().out
    for level in (4, 2.0, True):  # past the last hint, or a float or bool that looks like one
        with pytest.raises(ValueError, match=f"level is 1 .*not {level!r}"):
            exercises.hint("mppi_update", level=level)


def test_a_failed_check_offers_the_next_hint_without_code():
    def covariance_term(z):
        return z.var(dim=0).sum()

    offered = []
    for _ in range(3):
        with pytest.raises(exercises.ExerciseError) as caught:
            exercises.check_covariance_term(covariance_term)
        offered.append(str(caught.value))
    assert "Hint 1 of 3 for covariance_term, the idea" in offered[0]
    assert "Hint 2 of 3 for covariance_term, the formula" in offered[1]
    assert "exercises.hint('covariance_term', level=3) shows an outline" in offered[2]
    assert common.HINTS["covariance_term"][2] not in "".join(offered)


def test_a_hint_asked_for_by_level_never_lowers_the_next_one(capsys):
    """hint(name, level=k) shows level k; the next plain hint() goes on from the highest level
    shown so far, not from the one just asked for again."""
    exercises.hint("mppi_update", level=3)
    exercises.hint("mppi_update", level=1)
    capsys.readouterr()
    exercises.hint("mppi_update")
    assert "Hint 3 of 3 for mppi_update" in capsys.readouterr().out


def test_each_hint_but_the_last_says_what_the_next_one_gives(capsys):
    """The idea says the formula comes next, the formula that an outline of the code does; the
    outline, the last, promises nothing more."""
    for level, following in ((1, "the formula"), (2, "an outline of the code")):
        exercises.hint("covariance_term", level=level)
        assert (f"(exercises.hint('covariance_term') again gives {following}.)"
                in capsys.readouterr().out)
    exercises.hint("covariance_term", level=3)
    assert "again gives" not in capsys.readouterr().out


def test_a_hint_on_the_course_function_a_check_handed_over_finds_its_exercise(capsys):
    """After an unfinished exercise the notebook's name holds the course's function, whose own
    name may differ from the exercise's (epps_pulley for epps_pulley_1d): hint() on it still
    gives that exercise's hint."""
    course = exercises.check_epps_pulley.reference
    assert course.__name__ != "epps_pulley_1d"
    exercises.hint(course)
    assert "Hint 1 of 3 for epps_pulley_1d, the idea" in capsys.readouterr().out


def test_a_known_slip_is_named_only_when_it_explains_the_answer_to_float_precision():
    """A slip is named when the answer matches it within a tenth of the tolerance: an answer a
    few tolerances away from the biased variance (that slip and something else besides) is
    shown by its numbers, not blamed on the one slip."""
    def variance_term(z, gamma=1.0, eps=1e-4):
        return _biased_variance(z, gamma, eps) + 3e-5

    with pytest.raises(exercises.ExerciseError, match="but the answer is") as caught:
        exercises.check_variance_term(variance_term)
    assert "Likely cause" not in str(caught.value)


def test_of_two_slips_that_give_the_same_numbers_the_first_listed_is_named():
    """Where two known slips give one answer on a case, the checker names the one the exercise
    lists first (the likelier slip), the same on every run."""
    from ebjepa_tutorial.course.exercises.common import Case, Exercise

    slips = common.TEXTS["variance_term"]["slips"]
    first, second = list(slips)[:2]

    def doubled(x):
        return 2 * x.sum()

    check = Exercise("variance_term", lambda x: x.sum(), mistakes={first: doubled, second: doubled},
                     cases=lambda: [Case("a case", (torch.ones(3),))])
    with pytest.raises(exercises.ExerciseError) as caught:
        check(lambda x: 2 * x.sum())
    assert f"Likely cause: {slips[first]}" in str(caught.value)


def test_a_gradient_a_little_off_is_refused_with_the_values_tolerance():
    """Gradients are held to the tolerance the values are (atol 1e-5, rtol 1e-4): an answer
    right in value whose gradient is off by 0.005 (a loss that would train a little wrongly)
    is refused, though the gap is under 0.25% of every gradient element."""
    from ebjepa_tutorial.course.exercises.common import Case, Exercise

    check = Exercise("variance_term", lambda z: z.pow(2).sum(), mistakes={},
                     cases=lambda: [Case("a batch", (torch.linspace(1, 2, 6),))], grad=((0, "z"),))

    def skewed(z):
        return z.pow(2).sum() + 0.005 * (z.sum() - z.sum().detach())

    with pytest.raises(exercises.ExerciseError, match="not the right gradient with respect to z"):
        check(skewed)


def test_every_exercise_has_three_hints_and_its_checker_names_each_mistake_in_hints_yaml():
    assert set(common.TEXTS) == set(CHECKERS)
    for name, checker in CHECKERS.items():
        assert checker.exercise == name
        idea, formula, outline = common.HINTS[name]
        assert len(idea) > 80 and len(formula) > 80 and outline
        assert {words for words, _ in checker.slips} == set(common.TEXTS[name]["slips"].values())


# --------------------------------------------------- the student version shows no solution

def _code(line):
    """A solution line without its comment and indentation ('' for a comment line)."""
    return "" if line.strip().startswith("#") else line.split("  #")[0].strip()


def _solution_lines(source):
    inside, lines = False, []
    for line in source.splitlines():
        if BEGIN in line or END in line:
            inside = BEGIN in line
        elif inside and _code(line):
            lines.append(_code(line))
    return lines


def _right_hand_side(line):
    """What a solution line computes, when that is long enough to be telling."""
    rhs = line.split(" = ", 1)[1] if " = " in line else line.removeprefix("return ")
    computes = any(c in rhs for c in ".+-*/[")  # not a bare call such as predictor(window)
    return rhs if len(rhs) >= 12 and computes else None


def _student_cells(path):
    out = []
    for cell in _cells(path):
        source = _source(cell)
        out.append(strip_solutions(source) if cell["cell_type"] == "code"
                   else MARKDOWN_SOLUTION.sub("", source))
    return out


def _exercise_cells(cells, index):
    """A stub cell's exercise cells: the markdown above that states it, the stub, its check."""
    check = next(i for i in range(index + 1, len(cells)) if "exercises.check_" in cells[i])
    return [cells[index - 1], cells[index], cells[check]]


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_the_student_version_holds_no_line_of_a_solution(path):
    cells, text = _cells(path), "\n".join(_student_cells(path))
    student = _student_cells(path)
    for index, cell in enumerate(cells):
        if cell["cell_type"] != "code" or BEGIN not in _source(cell):
            continue
        lines = _solution_lines(_source(cell))
        names = re.findall(r"^def (\w+)\(", _source(cell), flags=re.M)
        hints = "\n".join(common.HINTS[name][level] for name in names for level in (0, 1))
        # every cell a learner has read by the exercise, its statement and its check
        near = "\n".join(student[:index] + _exercise_cells(student, index)) + hints
        for line in lines:
            assert line not in text + hints, f"{path.name} cell {index}: {line!r} is shown"
            rhs = _right_hand_side(line)
            assert rhs is None or rhs not in near, f"{path.name} cell {index}: {rhs!r} is shown"
        assert all(f'exercises.hint("{name}")' in student[index] for name in names)


ANSWERS = {"variance_term": ["losses.variance_term", "variance_and_covariance", "vicreg_loss"],
           "covariance_term": ["losses.covariance_term", "covariance_matrix", "vicreg_loss"],
           "vicreg": ["vicreg_loss"], "vicreg_paper_to_ebjepa": [],
           "epps_pulley_1d": ["sigreg.epps_pulley", "import epps_pulley", "sigreg_loss"],
           "parallel_rollout_loss": ["rollout.parallel_rollout_loss", "parallel_unroll",
                                     "losses.rollout"],
           "slab_crossing": ["stop_at_wall"],
           "wall_collision": ["envs.wall_collision", "two_rooms.wall_collision", "stop_at_wall"],
           "temporal_similarity": ["temporal_similarity_loss"],
           "inverse_dynamics": ["inverse_dynamics_loss"],
           "mppi_update": ["planning.mppi_update", "mppi_weights", "weighted_mean_std"],
           "step_violation": ["cost.step_violation"], "spread_loss": ["cost.spread_loss"]}


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_the_exercise_cells_do_not_name_the_answer(path):
    student = _student_cells(path)
    for index, cell in enumerate(_cells(path)):
        if cell["cell_type"] == "code" and BEGIN in _source(cell):
            shown = "\n".join(_exercise_cells(student, index))
            for name in re.findall(r"^def (\w+)\(", _source(cell), flags=re.M):
                for answer in ANSWERS[name]:
                    assert answer not in shown, f"{path.name} cell {index} names {answer}"


def test_a_markdown_solution_goes_and_the_list_after_it_stays_a_list():
    source = ("Exercises 1 and 2 are above. <!-- BEGIN SOLUTION -->Solutions are here."
              "<!-- END SOLUTION --> Each takes minutes.\n\n3. **Next.** Do it.")
    assert MARKDOWN_SOLUTION.sub("", source) == (
        "Exercises 1 and 2 are above. Each takes minutes.\n\n3. **Next.** Do it.")
    ended = source.replace(" Each takes minutes.", "")  # the marker closes the paragraph
    # no stray space where the marker was
    assert MARKDOWN_SOLUTION.sub("", ended).endswith("above.\n\n3. **Next.** Do it.")


def test_strip_solutions_leaves_a_stub_that_asks_for_a_hint():
    source = (
        "def f(x):\n"
        "    y = 1\n"
        "    ### BEGIN SOLUTION\n"
        "    return x + y\n"
        "    ### END SOLUTION\n"
    )
    assert strip_solutions(source) == (
        "def f(x):\n"
        "    y = 1\n"
        '    # Your code here. Stuck? exercises.hint("f") gives a hint, one level at a time.\n'
        "    raise NotImplementedError('Exercise: write f; exercises.hint(\"f\") gives a hint.')\n"
    )  # the source's final newline stays


@pytest.mark.parametrize("source", [
    "### BEGIN SOLUTION\nx = 1\n",
    "x = 1\n### END SOLUTION\n",
    "def f():\n    ### BEGIN SOLUTION\n    # HINT: the answer\n    return 1\n"
    "    ### END SOLUTION\n",
])
def test_unbalanced_markers_and_hint_lines_are_errors(source):
    with pytest.raises(ValueError, match="SOLUTION|HINT"):
        strip_solutions(source)


@pytest.mark.slow  # nbformat's validator takes seconds to import
def test_student_versions_are_valid_and_solution_free(tmp_path, capsys):
    import nbformat

    from tools import student

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
        for source in stubs:  # every stub still defines its functions, which then say "todo"
            namespace = {"torch": torch}
            exec(source, namespace)
            for name in re.findall(r"^def (\w+)\(", source, flags=re.M):
                assert CHECKERS[name](namespace[name]) is CHECKERS[name].reference


@pytest.mark.slow
def test_make_student_keeps_a_learners_work(tmp_path):
    from tools import student

    student.write_student_versions(NOTEBOOKS[0].parent, tmp_path)
    mine = tmp_path / NOTEBOOKS[0].name
    mine.write_text(mine.read_text().replace("raise NotImplementedError", "return 0  # mine"))
    assert student.write_student_versions(NOTEBOOKS[0].parent, tmp_path) == []
    assert "# mine" in mine.read_text()
    assert mine in student.write_student_versions(NOTEBOOKS[0].parent, tmp_path, overwrite=True)
    assert "# mine" not in mine.read_text()


@pytest.mark.slow  # nbformat's validator takes seconds to import
def test_a_student_notebook_cut_off_while_written_is_not_kept_as_work(tmp_path, monkeypatch):
    import nbformat

    from tools import student

    source = tmp_path / "src"
    source.mkdir()
    shutil.copy(NOTEBOOKS[0], source)
    monkeypatch.setattr(nbformat, "writes", lambda notebook: 1 / 0)  # the write dies
    with pytest.raises(ZeroDivisionError):
        student.write_student_versions(source, tmp_path / "student")
    assert list((tmp_path / "student").iterdir()) == []  # nothing half-written to keep
    monkeypatch.undo()
    assert student.write_student_versions(source, tmp_path / "student")  # written, not kept


def test_a_run_takes_a_learners_function_only_once_it_passed_its_check():
    def variance_term(z, gamma=1.0, eps=1e-4):  # right
        return torch.relu(gamma - torch.sqrt(z.var(dim=0) + eps)).mean()

    def wrong(z, gamma=1.0, eps=1e-4):
        return 2 * variance_term(z, gamma, eps)

    course = losses.variance_term
    assert exercises.checked(variance_term, course) is course  # written, not checked yet
    assert exercises.checked(None, course) is course  # not written
    assert exercises.checked(exercises.check_variance_term(variance_term), course) is variance_term
    with pytest.raises(exercises.ExerciseError):
        exercises.check_variance_term(wrong)
    assert exercises.checked(wrong, course) is course
