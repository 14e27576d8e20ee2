"""Notebook 00's claims hold: invariance alone collapses, VICReg does not."""

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
