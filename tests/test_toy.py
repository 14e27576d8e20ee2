"""Notebook 00's claims hold: invariance alone collapses, VICReg does not."""

import itertools

import pytest
import torch
from test_one_source import chapter_00_loop

from ebjepa_tutorial.training import toy
from ebjepa_tutorial.training.image import VICReg


@pytest.fixture(scope="module")
def data():
    return toy.make_blobs(256, k=4, seed=0)


def _train(data, inv=1.0, var=0.0, cov=0.0):
    x, _ = data
    encoder, history = chapter_00_loop()(x, VICReg(inv, var, cov), steps=150, seed=0)
    with torch.no_grad():
        return encoder(x), history


def test_blobs_are_reproducible():
    a, la = toy.make_blobs(50, seed=1)
    b, lb = toy.make_blobs(50, seed=1)
    assert torch.equal(a, b) and torch.equal(la, lb) and a.shape == (50, 2)


def test_invariance_alone_collapses(data):
    z, history = _train(data, inv=1.0)
    assert history.last("invariance") < 1e-4
    assert toy.spectrum(z).sum() < 1e-3  # no spread left in any direction


def test_vicreg_keeps_a_full_rank_cluster_code(data):
    z, _ = _train(data, inv=1.0, var=1.0, cov=1.0)
    eigenvalues = toy.spectrum(z)
    # 4 clusters -> a simplex spanning 3 dimensions with comparable eigenvalues
    assert eigenvalues[2] > 0.3 * eigenvalues[0]
    centres = torch.stack([z[data[1] == c].mean(dim=0) for c in range(4)])
    between = torch.cdist(centres, centres).pow(2)  # energies between cluster centres
    off_diagonal = between[~torch.eye(4, dtype=torch.bool)]
    assert off_diagonal.min() > 0.5 * off_diagonal.max()


def test_training_is_deterministic(data):
    z1, _ = _train(data, inv=1.0, var=1.0)
    z2, _ = _train(data, inv=1.0, var=1.0)
    assert torch.equal(z1, z2)


def test_energy_map_is_zero_at_the_anchor(data):
    x, _ = data
    encoder = toy.mlp_encoder()
    coords, energy = toy.energy_map(encoder, torch.zeros(2), extent=1.0, resolution=3)
    assert coords.tolist() == [-1.0, 0.0, 1.0]
    assert energy.shape == (3, 3) and energy[1, 1].item() == pytest.approx(0.0, abs=1e-10)
    # with the identity for an encoder, E is the squared distance: rows y, columns x
    coords, energy = toy.energy_map(torch.nn.Identity(), torch.tensor([0.5, 0.0]), 1.0, 3)
    x, y = coords[None, :], coords[:, None]
    assert torch.allclose(energy, (x - 0.5) ** 2 + y**2)


def test_blobs_sit_around_k_centres_evenly_spaced_on_the_circle():
    """Label ``l`` of ``k`` is centred at angle ``2 pi l / k`` on the circle of ``radius``; the
    points scatter around it with standard deviation ``spread`` on each axis."""
    centres = torch.tensor([[2.0, 0.0], [0.0, 2.0], [-2.0, 0.0], [0.0, -2.0]])
    x, labels = toy.make_blobs(40, k=4, radius=2.0, spread=0.0, seed=0)
    assert set(labels.tolist()) == {0, 1, 2, 3}
    assert torch.allclose(x, centres[labels], atol=1e-6)
    x, labels = toy.make_blobs(4000, k=4, radius=2.0, spread=0.3, seed=0)
    assert (x - centres[labels]).std().item() == pytest.approx(0.3, rel=0.05)


def test_spectrum_is_the_covariance_eigenvalues_largest_first():
    """On centred, uncorrelated columns scaled by 1, 3 and 2 the eigenvalues are the columns'
    variances, ``(8/7) s^2`` for 8 sign patterns, and they come sorted largest first."""
    signs = torch.tensor(list(itertools.product([-1.0, 1.0], repeat=3)))  # (8, 3)
    z = signs * torch.tensor([1.0, 3.0, 2.0])
    assert torch.allclose(toy.spectrum(z), torch.tensor([9.0, 4.0, 1.0]) * 8 / 7)
