"""VICReg's loss terms, one function per term of the paper (notebooks 00, 01, 03 and 05). Each
term takes embeddings ``z`` of shape ``(B, D)`` (batch, dimensions) and returns a 0-d tensor."""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F

Term = Callable[[torch.Tensor], torch.Tensor]  # embeddings (B, D) -> 0-d tensor


def _check_embeddings(z: torch.Tensor) -> None:
    if z.ndim != 2 or z.shape[0] < 2:
        raise ValueError(f"embeddings must be a (batch, dim) tensor with at least 2 samples (a "
                         f"standard deviation over one is undefined), got {tuple(z.shape)}")


def invariance_term(z_a: torch.Tensor, z_b: torch.Tensor) -> torch.Tensor:
    """Mean squared distance between two views ``(B, D)``: ``mean_{b,d} (z_a - z_b)^2``, the
    energy ``E(x, y)`` of a joint-embedding architecture averaged over pairs, divided by D."""
    if z_a.ndim != 2 or z_a.shape != z_b.shape:
        raise ValueError(f"the views must be (batch, dim) tensors and not differ in shape, got "
                         f"{tuple(z_a.shape)} and {tuple(z_b.shape)}")
    return F.mse_loss(z_a, z_b)


def variance_term(z: torch.Tensor, gamma: float = 1.0, eps: float = 1e-4) -> torch.Tensor:
    """Hinge on each dimension's standard deviation over the batch ``(B, D)``, ``B >= 2``:

        v(Z) = (1/D) sum_d max(0, gamma - sqrt(Var(z_d) + eps))"""
    _check_embeddings(z)
    std = torch.sqrt(z.var(dim=0) + eps)
    return F.relu(gamma - std).mean()


def covariance_matrix(z: torch.Tensor) -> torch.Tensor:
    """Sample covariance ``C = (Z - mean)^T (Z - mean) / (B - 1)``: ``(B, D) -> (D, D)``."""
    _check_embeddings(z)
    centred = z - z.mean(dim=0)
    return centred.T @ centred / (z.shape[0] - 1)


def covariance_term(z: torch.Tensor) -> torch.Tensor:
    """Mean squared off-diagonal covariance of ``(B, D)``, ``D >= 2`` (VICReg divides by ``D``;
    EB-JEPA's mean keeps the coefficient independent of ``D``):

        c(Z) = sum_{i != j} C_ij^2 / (D (D - 1))"""
    return off_diagonal_term(covariance_matrix(z))


def off_diagonal_term(cov: torch.Tensor) -> torch.Tensor:
    """``c`` of a covariance matrix ``(D, D)``, a 0-d tensor."""
    dim = cov.shape[0]
    if dim < 2:
        raise ValueError("the covariance term needs at least 2 embedding dimensions")
    off_diagonal = cov - torch.diag(torch.diagonal(cov))
    return off_diagonal.pow(2).sum() / (dim * (dim - 1))


def vicreg_loss(z_a: torch.Tensor, z_b: torch.Tensor, inv_coeff: float = 1.0,
                std_coeff: float = 1.0, cov_coeff: float = 1.0, variance: Term = variance_term,
                covariance: Term = covariance_term) -> tuple[torch.Tensor, dict]:
    """``(L, terms)`` of two views ``(B, D)``: ``L = inv_coeff s + std_coeff v + cov_coeff c``,
    ``v`` and ``c`` computed on each view and averaged; ``terms``: the three, detached, 0-d."""
    inv = invariance_term(z_a, z_b)
    var = (variance(z_a) + variance(z_b)) / 2
    cov = (covariance(z_a) + covariance(z_b)) / 2
    total = inv_coeff * inv + std_coeff * var + cov_coeff * cov
    return total, {"invariance": inv.detach(), "variance": var.detach(),
                   "covariance": cov.detach()}


def vicreg(z_a: torch.Tensor, z_b: torch.Tensor, inv_coeff: float = 1.0, std_coeff: float = 1.0,
           cov_coeff: float = 1.0) -> torch.Tensor:
    """The total of :func:`vicreg_loss`, a 0-d tensor: what notebook 01's exercise 1 writes."""
    return vicreg_loss(z_a, z_b, inv_coeff, std_coeff, cov_coeff)[0]
