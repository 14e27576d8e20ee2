"""VICReg terms against values worked out by hand on tiny inputs."""

import math

import pytest
import torch

from ebjepa_tutorial import losses


def test_invariance_is_mean_squared_distance():
    z_a = torch.tensor([[0.0, 0.0], [1.0, 1.0]])
    z_b = torch.tensor([[1.0, 0.0], [1.0, 3.0]])
    # squared differences 1, 0, 0, 4 -> mean 5/4
    assert losses.invariance_term(z_a, z_b).item() == pytest.approx(1.25)


def test_variance_hinge_by_hand():
    z = torch.tensor([[0.0, 0.0], [2.0, 0.0]])
    # dim 0: unbiased var 2 -> std 1.414 > 1, no penalty; dim 1: var 0 -> std sqrt(eps)
    expected = (0.0 + (1.0 - math.sqrt(1e-4))) / 2
    assert losses.variance_term(z).item() == pytest.approx(expected, abs=1e-6)
    # a spread under gamma: dim 0 has unbiased var 0.5 (biased 0.25), so the hinge reads
    # 1 - sqrt(0.5 + eps); a biased variance or an eps outside the root gives another number
    z = torch.tensor([[0.0, 0.0], [1.0, 0.0]])
    expected = ((1.0 - math.sqrt(0.5 + 1e-4)) + (1.0 - math.sqrt(1e-4))) / 2
    assert losses.variance_term(z).item() == pytest.approx(expected, abs=1e-6)


def test_variance_is_zero_when_every_std_exceeds_gamma():
    z = 5 * torch.randn(256, 4, generator=torch.Generator().manual_seed(0))
    assert losses.variance_term(z).item() == 0.0
    assert losses.variance_term(z, gamma=100.0).item() > 90


def test_covariance_two_dims_by_hand():
    z = torch.tensor([[1.0, 2.0], [-1.0, -2.0]])
    # C = [[2, 4], [4, 8]]; off-diagonal squares 16 + 16, divided by D(D-1) = 2
    assert losses.covariance_matrix(z).tolist() == [[2.0, 4.0], [4.0, 8.0]]
    assert losses.covariance_term(z).item() == pytest.approx(16.0)
    # the same rows moved by (1, 1): the covariance is of the centred rows, so it is unchanged
    # (without centring it would read [[4, 6], [6, 10]] and a term of 36, not 16)
    assert losses.covariance_matrix(z + 1).tolist() == [[2.0, 4.0], [4.0, 8.0]]
    assert losses.covariance_term(z + 1).item() == pytest.approx(16.0)


def test_covariance_three_dims_by_hand():
    z = torch.tensor([[1.0, 0.0, 1.0], [-1.0, 0.0, -1.0], [0.0, 0.0, 0.0]])
    # C = [[1, 0, 1], [0, 0, 0], [1, 0, 1]]: two off-diagonal ones, divided by 3 * 2
    assert losses.covariance_term(z).item() == pytest.approx(1 / 3)


def test_covariance_vanishes_for_decorrelated_dimensions():
    z = torch.tensor([[1.0, 1.0], [1.0, -1.0], [-1.0, 1.0], [-1.0, -1.0]])
    assert losses.covariance_term(z).item() == pytest.approx(0.0)


def test_vicreg_loss_weights_the_terms():
    g = torch.Generator().manual_seed(0)
    z_a, z_b = torch.randn(16, 4, generator=g), torch.randn(16, 4, generator=g)
    total, terms = losses.vicreg_loss(z_a, z_b, inv_coeff=2.0, std_coeff=3.0, cov_coeff=5.0)
    expected = 2 * terms["invariance"] + 3 * terms["variance"] + 5 * terms["covariance"]
    assert total.item() == pytest.approx(float(expected), rel=1e-5)
    # each regulariser is the mean over the two views, the invariance between them
    by_term = {"invariance": losses.invariance_term(z_a, z_b),
               "variance": (losses.variance_term(z_a) + losses.variance_term(z_b)) / 2,
               "covariance": (losses.covariance_term(z_a) + losses.covariance_term(z_b)) / 2}
    assert {k: float(v) for k, v in terms.items()} == pytest.approx(
        {k: float(v) for k, v in by_term.items()}, rel=1e-6)
    assert set(terms) == {"invariance", "variance", "covariance"}
    # detached tensors: logging them keeps no graph alive and costs no wait for a GPU
    assert all(v.ndim == 0 and not v.requires_grad for v in terms.values())


def test_bad_inputs_give_clear_errors():
    with pytest.raises(ValueError, match="at least 2 samples"):
        losses.variance_term(torch.ones(1, 4))
    with pytest.raises(ValueError, match=r"\(batch, dim\)"):
        losses.covariance_term(torch.ones(4, 3, 2))
    with pytest.raises(ValueError, match="differ in shape"):
        losses.invariance_term(torch.ones(4, 3), torch.ones(4, 2))
    with pytest.raises(ValueError, match="at least 2 embedding dimensions"):
        losses.covariance_term(torch.ones(4, 1))


def test_still_steps_are_the_draws_below_the_stay_probability():
    """A step stands still where its uniform draw falls below ``stay_probability`` (so a
    probability of 0.1 stills about a tenth of the steps, not nine tenths). With the draws 0.1
    then 0.9 against 0.5, step 1 stands still and step 2 makes the first move: the sequence
    reads z0, z0, z1, so a predictor that never moves errs only on step 2."""
    from ebjepa_tutorial.losses import world

    z = torch.tensor([[[0.0], [1.0], [3.0]]])  # (1, K + 1 = 3, 1)
    actions = torch.tensor([[[1.0], [2.0]]])  # (1, K = 2, 1)
    draws = lambda rows, steps, generator=None: torch.tensor([[0.1, 0.9]])  # noqa: E731
    stands = lambda z, a: z  # noqa: E731  (predicts no change, whatever the action)
    loss = world.multistep_prediction_loss(stands, z, actions, steps=2, stay_probability=0.5,
                                           rand=draws)
    # targets z0 = 0, z1 = 1 against the prediction 0: errors 0 and 1 -> mean 1/2
    assert loss.item() == pytest.approx(0.5)
