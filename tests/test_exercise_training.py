"""Chapter 00 trains with the learner's own variance and covariance terms once they pass."""

import torch

from ebjepa_tutorial import losses
from ebjepa_tutorial.training import toy


def test_the_toy_run_trains_with_the_terms_it_is_given():
    x, _ = toy.make_blobs(64, k=3, seed=0)
    coeffs = toy.Coefficients(inv=1.0, var=1.0, cov=1.0)
    calls = {"variance": 0, "covariance": 0}

    def variance_term(z, gamma=1.0, eps=1e-4):  # a learner's own, written differently
        calls["variance"] += 1
        return torch.relu(gamma - (z.var(dim=0) + eps).sqrt()).mean()

    def covariance_term(z):
        calls["covariance"] += 1
        cov = torch.cov(z.T)
        return (cov.pow(2).sum() - cov.diagonal().pow(2).sum()) / (z.shape[1] * (z.shape[1] - 1))

    course, course_history = toy.train_toy(x, coeffs, steps=5, seed=0)
    mine, history = toy.train_toy(x, coeffs, steps=5, seed=0, variance=variance_term,
                                  covariance=covariance_term)
    assert calls == {"variance": 10, "covariance": 10}  # both views, every step
    assert torch.allclose(torch.tensor(history["loss"]), torch.tensor(course_history["loss"]),
                          atol=1e-5)

    def no_spread(z):  # a term that never pushes: the run must differ
        return z.sum() * 0.0

    _, other = toy.train_toy(x, coeffs, steps=5, seed=0, variance=no_spread, covariance=no_spread)
    assert other["variance"][-1] == 0.0 and course_history["variance"][-1] > 0.0


def test_the_course_s_terms_are_the_default():
    z_a, z_b = torch.randn(16, 4), torch.randn(16, 4)
    explicit = losses.vicreg_loss(z_a, z_b, 1.0, 2.0, 3.0, variance=losses.variance_term,
                                  covariance=losses.covariance_term)[0]
    assert torch.equal(explicit, losses.vicreg_loss(z_a, z_b, 1.0, 2.0, 3.0)[0])
