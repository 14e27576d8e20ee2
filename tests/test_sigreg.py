"""SIGReg: the Epps-Pulley statistic against hand and numerical integrals, and its behaviour."""

import math

import numpy as np
import pytest
import torch

from ebjepa_tutorial.losses.sigreg import (
    EmpiricalCF,
    epps_pulley,
    random_directions,
    sigreg,
    sigreg_loss,
)
from ebjepa_tutorial.training.image import SIGReg
from ebjepa_tutorial.utils import as_generator


def test_two_symmetric_points_match_the_closed_form():
    # For x = {a, -a}: phi_N(t) = cos(a t). Over the whole real line, with w(t) = exp(-t^2/2),
    #   int w (cos(a t) - e^{-t^2/2})^2 dt
    #   = sqrt(2 pi) (1 + e^{-2 a^2}) / 2 - 2 sqrt(pi) e^{-a^2 / 4} + sqrt(2 pi / 3)
    # (each piece is a Gaussian integral  int e^{-c t^2} cos(b t) dt = sqrt(pi / c) e^{-b^2 / 4c}).
    a = 0.7
    exact = (
        math.sqrt(2 * math.pi) * (1 + math.exp(-2 * a**2)) / 2
        - 2 * math.sqrt(math.pi) * math.exp(-(a**2) / 4)
        + math.sqrt(2 * math.pi / 3)
    )
    x = torch.tensor([a, -a], dtype=torch.float64)
    ours = epps_pulley(x, knots=4001, t_max=12.0, scale_by_n=False).item()
    assert ours == pytest.approx(exact, rel=1e-5)
    assert epps_pulley(x, knots=4001, t_max=12.0).item() == pytest.approx(2 * exact, rel=1e-5)


def _numpy_epps_pulley(x, t_max, sigma, points):
    t = np.linspace(-t_max, t_max, points)
    ecf = np.exp(1j * np.outer(t, x)).mean(axis=1)  # complex arithmetic, the textbook formula
    integrand = np.exp(-(t**2) / (2 * sigma**2)) * np.abs(ecf - np.exp(-(t**2) / 2)) ** 2
    return len(x) * np.trapezoid(integrand, t)


@pytest.mark.parametrize("sigma", [1.0, 0.5])
def test_default_quadrature_against_a_fine_numpy_integral(sigma):
    x = np.array([0.3, -1.2, 2.0, 0.1, 0.8])
    reference = _numpy_epps_pulley(x, 3.0, sigma, 200_001)
    fine = epps_pulley(torch.tensor(x), knots=10_001, sigma=sigma).item()
    assert fine == pytest.approx(reference, rel=1e-6)
    coarse = epps_pulley(torch.tensor(x), sigma=sigma).item()  # 17 knots on [0, 3]
    assert coarse == pytest.approx(reference, rel=1e-2)


def test_hand_written_gradient_matches_finite_differences():
    # epps_pulley's ECF has its own backward pass (the closed-form derivative of cos and sin)
    x = torch.randn(7, 3, dtype=torch.float64, generator=as_generator(0), requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: epps_pulley(x, knots=21, t_max=4.0), (x,))


def test_angle_addition_keeps_the_ecf_exact_over_many_knots():
    # cos and sin at each knot are built from the previous knot's: check they do not drift
    x = 3 * torch.randn(64, 4, generator=as_generator(1))  # float32, arguments up to ~100 rad
    knots, t_max = 201, 12.0
    real, imag = EmpiricalCF.apply(x, t_max / (knots - 1), knots)  # (4, 201) each
    t = torch.linspace(0.0, t_max, knots, dtype=torch.float64)
    angles = x.double()[..., None] * t  # (64, 4, 201)
    assert torch.allclose(real.double(), angles.cos().mean(0), atol=2e-5)
    assert torch.allclose(imag.double(), angles.sin().mean(0), atol=2e-5)


def test_columns_are_independent_slices():
    x = torch.randn(50, 3, generator=as_generator(0))
    per_column = torch.stack([epps_pulley(x[:, j]) for j in range(3)])
    assert torch.allclose(epps_pulley(x), per_column)


def test_small_on_gaussian_large_on_collapsed_or_uniform():
    gen = as_generator(0)
    n, d = 1024, 16
    gaussian = sigreg(torch.randn(n, d, generator=gen), 64, gen).item()
    collapsed = sigreg(torch.full((n, d), 0.3), 64, gen).item()
    uniform = sigreg(torch.rand(n, d, generator=gen), 64, gen).item()
    # N * EP is about 1 under the null (its mean is int w (1 - e^{-t^2}) dt ~ 1.05).
    assert 0.3 < gaussian < 3
    assert collapsed > 100 * gaussian and uniform > 100 * gaussian
    unscaled = sigreg(torch.randn(n, d, generator=gen), 64, gen, scale_by_n=False).item()
    assert unscaled < 3 / n  # without the factor N it is near zero, O(1/N)


def test_unit_variance_uniform_is_detected_with_enough_samples():
    gen = as_generator(1)
    x = (torch.rand(4096, generator=gen) - 0.5) * math.sqrt(12)  # mean 0, variance 1
    assert epps_pulley(x).item() > 20 * epps_pulley(torch.randn(4096, generator=gen)).item()


def test_directions_are_unit_and_seeded():
    d1 = random_directions(8, 5, as_generator(3))
    assert d1.shape == (8, 5) and torch.allclose(d1.norm(dim=0), torch.ones(5))
    assert torch.equal(d1, random_directions(8, 5, as_generator(3)))
    # uniform on the sphere: no favoured direction, so the second moment is I / D (uniform
    # numbers in [0, 1), or directions left unnormalised, would fail this)
    d = random_directions(8, 20_000, as_generator(4))
    assert torch.allclose(d @ d.T / 20_000, torch.eye(8) / 8, atol=0.005)
    assert d.mean(dim=1).abs().max() < 0.01


def test_same_generator_same_value_fresh_slices_each_call():
    z = torch.randn(64, 10, generator=as_generator(0))
    assert sigreg(z, 16, as_generator(5)) == sigreg(z, 16, as_generator(5))
    gen = as_generator(5)
    assert sigreg(z, 16, gen) != sigreg(z, 16, gen)  # the generator moved on: new directions


def test_sigreg_loss_terms_and_gradient():
    gen = as_generator(0)
    z_a = torch.randn(32, 8, generator=gen, requires_grad=True)
    z_b = (z_a.detach() + 0.1 * torch.randn(32, 8, generator=gen)).requires_grad_()
    total, terms = sigreg_loss(z_a, z_b, lam=0.5, num_slices=32, generator=as_generator(1))
    assert set(terms) == {"invariance", "sigreg"}
    assert total.item() == pytest.approx(float(terms["invariance"] + 0.5 * terms["sigreg"]),
                                        rel=1e-5)
    assert float(terms["invariance"]) == pytest.approx(((z_a - z_b) ** 2).mean().item(), rel=1e-6)
    directions = random_directions(8, 32, as_generator(1))  # the draw sigreg_loss made
    both = (sigreg(z_a, directions=directions) + sigreg(z_b, directions=directions)) / 2
    assert float(terms["sigreg"]) == pytest.approx(both.item(), rel=1e-6)  # both views, alike
    # detached tensors: logging them keeps no graph alive and costs no wait for a GPU
    assert all(v.ndim == 0 and not v.requires_grad for v in terms.values())
    total.backward()
    for z in (z_a, z_b):  # each view is pushed by its own regulariser and the invariance
        assert torch.isfinite(z.grad).all() and z.grad.abs().sum() > 0


def test_batch_of_one_is_a_clear_error():
    with pytest.raises(ValueError, match="at least 2"):
        sigreg(torch.randn(1, 8))
    with pytest.raises(ValueError, match="at least 2"):
        epps_pulley(torch.randn(1))
    with pytest.raises(ValueError, match="at least 2"):
        sigreg_loss(torch.randn(1, 8), torch.randn(1, 8))


def test_half_precision_inputs_are_computed_in_float32():
    z = torch.randn(64, 8, generator=as_generator(0))
    full = sigreg(z, 16, as_generator(2))
    half = sigreg(z.bfloat16(), 16, as_generator(2))
    assert half.dtype == torch.float32 and half.item() == pytest.approx(full.item(), rel=0.05)


def test_angle_addition_does_not_drift_over_thousands_of_knots():
    """cos and sin are recomputed exactly every 8 knots, so float32's error stays at a few ulp
    however many knots there are; angle addition alone drifts (some 7e-6 by 2,000 knots)."""
    x = 3 * torch.randn(64, 4, generator=as_generator(1))  # float32, arguments up to ~100 rad
    knots, t_max = 2001, 12.0
    real, imag = EmpiricalCF.apply(x, t_max / (knots - 1), knots)
    angles = x.double()[..., None] * torch.linspace(0.0, t_max, knots, dtype=torch.float64)
    assert (real.double() - angles.cos().mean(0)).abs().max() < 2e-6
    assert (imag.double() - angles.sin().mean(0)).abs().max() < 2e-6


def test_without_the_factor_n_both_views_lose_it():
    """``scale_by_n=False`` drops the factor N from both views' statistics alike: the
    regulariser is then the scaled one divided by N (here 32), the invariance unchanged."""
    gen = as_generator(0)
    z_a, z_b = torch.randn(32, 8, generator=gen), 2 * torch.randn(32, 8, generator=gen)
    _, scaled = sigreg_loss(z_a, z_b, num_slices=16, generator=as_generator(1))
    total, unscaled = sigreg_loss(z_a, z_b, lam=0.5, num_slices=16, generator=as_generator(1),
                                  scale_by_n=False)
    assert float(unscaled["sigreg"]) == pytest.approx(float(scaled["sigreg"]) / 32, rel=1e-5)
    assert torch.equal(unscaled["invariance"], scaled["invariance"])
    assert total.item() == pytest.approx(float(unscaled["invariance"] + 0.5 * unscaled["sigreg"]),
                                        rel=1e-6)


def test_sigreg_loss_defaults_are_the_course_recipe():
    """Called with its defaults, ``sigreg_loss`` is the course's ``SIGReg()`` (lambda, slices,
    the factor N): a cell that calls it bare trains with the weights the course trains with."""
    gen = as_generator(0)
    z_a, z_b = torch.randn(32, 8, generator=gen), 2 * torch.randn(32, 8, generator=gen)
    recipe = SIGReg()
    bare, _ = sigreg_loss(z_a, z_b, generator=as_generator(1))
    explicit, _ = sigreg_loss(z_a, z_b, recipe.lam, recipe.slices, as_generator(1),
                              recipe.scale_by_n)
    assert torch.equal(bare, explicit)
