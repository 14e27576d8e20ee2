"""Loss terms of energy-based JEPAs, one function per term of the paper.

All functions take embeddings ``z`` of shape ``(B, D)`` (batch, dimensions)
and return a 0-d tensor. Introduced in notebook 00 (variance, covariance) and
used again in notebooks 01, 03 and 05.

Across several processes (``torchrun``), :func:`vicreg_loss` with
``across_ranks=True`` computes the variance and covariance on the global batch
(see :mod:`ebjepa_tutorial.distributed`) by gathering its rows, and
:func:`variance_and_covariance` from per-rank sums; the terms themselves only
see a batch.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
import torch.nn.functional as F

from .. import distributed


def _check_embeddings(z: torch.Tensor, name: str = "z", min_batch: int = 1) -> None:
    if not isinstance(z, torch.Tensor) or z.ndim != 2:
        shape = tuple(z.shape) if isinstance(z, torch.Tensor) else type(z).__name__
        raise ValueError(f"{name} must be a (batch, dim) tensor, got {shape}")
    if z.shape[0] < min_batch:
        raise ValueError(
            f"{name} has a batch of {z.shape[0]}; this term needs at least {min_batch} "
            "samples (a standard deviation over one sample is undefined)"
        )


def invariance_term(z_a: torch.Tensor, z_b: torch.Tensor) -> torch.Tensor:
    """Mean squared distance between two views: ``mean_{b,d} (z_a - z_b)^2``.

    ``z_a``, ``z_b``: ``(B, D)``. This is the energy ``E(x, y)`` of a
    joint-embedding architecture with an identity predictor, averaged over pairs.
    """
    _check_embeddings(z_a, "z_a")
    _check_embeddings(z_b, "z_b")
    if z_a.shape != z_b.shape:
        raise ValueError(f"views differ in shape: {tuple(z_a.shape)} vs {tuple(z_b.shape)}")
    return F.mse_loss(z_a, z_b)


def multi_view_invariance(
    z_a: torch.Tensor, z_b: torch.Tensor, local: Sequence[torch.Tensor] = ()
) -> torch.Tensor:
    """:func:`invariance_term` averaged over every pair of a global view with another view.

    The pairs are ``(z_a, z_b)`` and, for each smaller local view ``l``, ``(z_a, l)`` and
    ``(z_b, l)``: local views are pulled towards the global ones, never towards each other (as
    in SwAV's and DINO's multi-crop). All views ``(B, D)``. Without local views it is
    ``invariance_term(z_a, z_b)``.
    """
    pairs = [(z_a, z_b)] + [(view, z) for z in local for view in (z_a, z_b)]
    return sum(invariance_term(x, y) for x, y in pairs) / len(pairs)


def variance_term(z: torch.Tensor, gamma: float = 1.0, eps: float = 1e-4) -> torch.Tensor:
    """Hinge on the standard deviation of each dimension over the batch.

    ``v(Z) = (1/D) sum_d max(0, gamma - sqrt(Var(z_d) + eps))``, with ``z``
    of shape ``(B, D)`` and ``B >= 2``. Zero once every dimension has std >= gamma.
    """
    _check_embeddings(z, min_batch=2)
    std = torch.sqrt(z.var(dim=0) + eps)
    return F.relu(gamma - std).mean()


def covariance_matrix(z: torch.Tensor) -> torch.Tensor:
    """Sample covariance ``C = (Z - mean)^T (Z - mean) / (B - 1)``: ``(B, D) -> (D, D)``."""
    _check_embeddings(z, min_batch=2)
    centred = z - z.mean(dim=0)
    return centred.T @ centred / (z.shape[0] - 1)


def covariance_term(z: torch.Tensor) -> torch.Tensor:
    """Mean squared off-diagonal covariance: ``c(Z) = sum_{i != j} C_ij^2 / (D (D - 1))``.

    ``z``: ``(B, D)`` with ``D >= 2``. The VICReg paper divides the same sum by
    ``D`` instead; the EB-JEPA paper's ``D (D - 1)`` makes the term an average,
    so its coefficient does not have to grow with the embedding size.
    """
    cov = covariance_matrix(z)
    dim = cov.shape[0]
    if dim < 2:
        raise ValueError("the covariance term needs at least 2 embedding dimensions")
    off_diagonal = cov - torch.diag(torch.diagonal(cov))
    return off_diagonal.pow(2).sum() / (dim * (dim - 1))


def variance_and_covariance(
    z: torch.Tensor, gamma: float = 1.0, eps: float = 1e-4, across_ranks: bool = False
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(variance_term(z, gamma, eps), covariance_term(z))`` of embeddings ``(B, D)``.

    With ``across_ranks`` (a no-op in a single process), those of the global batch, every
    rank holding ``b`` rows of ``(W b, D)``, computed from per-rank sums rather than from
    gathered rows: two all-reduces of ``D`` and ``D x D`` numbers, however many rows. That
    matters when the rows are every location of every frame (chapter 03: millions at full
    scale). The rows are centred on the global mean first, as in :func:`covariance_matrix`.
    """
    if not across_ranks or distributed.world_size() == 1:
        return variance_term(z, gamma, eps), covariance_term(z)
    _check_embeddings(z)
    cov = _covariance_across_ranks(z)  # (D, D); then the two terms' formulas, as above
    dim, variances = cov.shape[0], torch.diagonal(cov)
    if dim < 2:
        raise ValueError("the covariance term needs at least 2 embedding dimensions")
    variance = F.relu(gamma - torch.sqrt(variances + eps)).mean()
    return variance, (cov - torch.diag(variances)).pow(2).sum() / (dim * (dim - 1))


def _covariance_across_ranks(z: torch.Tensor) -> torch.Tensor:
    # this rank's rows (b, D) of a global batch (W b, D) -> its sample covariance (D, D)
    world = distributed.world_size()
    (mean,) = distributed.mean_across_ranks(z.mean(dim=0))  # (D,): the global mean
    centred = z - mean
    (scatter,) = distributed.mean_across_ranks(centred.T @ centred)  # (D, D): 1/W of the sum
    return scatter * (world / (world * z.shape[0] - 1))


def vicreg_loss(
    z_a: torch.Tensor,
    z_b: torch.Tensor,
    inv_coeff: float = 1.0,
    std_coeff: float = 1.0,
    cov_coeff: float = 1.0,
    across_ranks: bool = False,
    local: Sequence[torch.Tensor] = (),
    variance: Callable[[torch.Tensor], torch.Tensor] = variance_term,
    covariance: Callable[[torch.Tensor], torch.Tensor] = covariance_term,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """VICReg on two views ``(B, D)``: weighted invariance + variance + covariance.

    The variance and covariance terms are applied to each view and averaged. ``local``:
    more views of the same images (multi-crop), each ``(B, D)``; the invariance becomes
    :func:`multi_view_invariance` and the two regularisers average over every view.
    Returns the total and a dict of the unweighted terms, detached 0-d tensors for logging
    (``float()`` reads one; reading waits for the GPU, so training loops read them only
    when they log).
    With ``across_ranks`` (a no-op in a single process), each rank's ``(b, D)``
    views are gathered from all ranks to ``(W b, D)`` for variance and covariance,
    gradients flowing back to each rank's own rows; the invariance term is a mean
    over pairs and stays local (DDP averages it over ranks). The logged invariance
    is this rank's. ``variance`` and ``covariance``: the two regularisers, ``(B, D) -> 0-d``
    (notebook 00 trains with the learner's own once they pass their checks).
    """
    inv = multi_view_invariance(z_a, z_b, local)
    views = (z_a, z_b, *local)
    if across_ranks:  # the batch statistics of the global batch, as on one device
        views = distributed.gather_rows(*views)
    var = sum(variance(z) for z in views) / len(views)
    cov = sum(covariance(z) for z in views) / len(views)
    total = inv_coeff * inv + std_coeff * var + cov_coeff * cov
    return total, {"invariance": inv.detach(), "variance": var.detach(),
                   "covariance": cov.detach()}
